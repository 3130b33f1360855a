"""Trajectory optimisers: `optimise(task, method, budget, seed, callback)` returns a Trajectory.

Methods: "dp" (gradients with FluidLab's techniques: soft contact, expanding region, attraction, gradient sharing
within fluid bodies; optim/dp.py), "dp-h" (the same loop without them), "cma-es" (optim/cmaes.py), and the
model-free RL baselines "sac" and "ppo" (Stable-Baselines3 on the Gymnasium environment; optim/rl.py), and "pods"
(a policy network improved with the simulator's gradients; optim/pods.py), the paper's six (PAPER_METHODS); sac,
ppo and pods need the `rl` extra (torch). And our own: "dp-window", DP over short windows of the horizon for
tasks whose long-horizon gradient explodes (optim/dp.py; tasks whose loss is a mean over steps); "cma-es-free",
CMA-ES over knots spread over the whole horizon where a task has the paper's periodic stroke (Gathering), which
held CMA-ES back on both liquids (docs/benchmark.md); and "dp-free", DP with its techniques over the same free
knots, to tell whether the stroke or the method held DP back there. Every method
- takes a budget in simulated steps (one rollout of the whole horizon costs `task.horizon`),
- takes a seed and is reproducible with it (the same seed gives the same trajectory, up to the order of
  floating-point sums in multithreaded CPU kernels),
- reports each iteration to `callback(progress)` (optim/progress.py); a callback that returns True stops
  the run, which then returns the best trajectory so far,
- is judged by the loss of its best parameters on the task's reference physics (hard contact), which the
  returned trajectory records in `metadata["final_loss"]` with the reward return.
Methods in RESUMABLE ("dp", "dp-h" and DP's ablations) also hand the callback `progress.state()`, their whole
state after the iteration, and `optimise(..., resume=state)` continues a run from it (optim/dp.py).
"""
from __future__ import annotations

import numpy as np

from fluidlab_core.optim.progress import Progress, Result

PAPER_METHODS = ("dp", "dp-h", "cma-es", "sac", "ppo", "pods")
METHODS = (*PAPER_METHODS, "dp-window", "cma-es-free", "dp-free")
CMA_ES_METHODS = ("cma-es", "cma-es-free")  # CMA-ES over the task's parametrisation, and over free knots
RESUMABLE = ("dp", "dp-h", "dp-free")  # methods that can continue from a saved state (DP with techniques off too)
GRADIENT_METHODS = ("dp", "dp-h", "pods", "dp-window", "dp-free")  # methods that need the differentiable simulator
DESCRIPTIONS = {
    "dp": "gradient descent through the differentiable simulator with the paper's techniques: soft tool contact, "
          "a temporally expanding loss region, an attraction of the tool to the fluid it must move, and gradient "
          "sharing that ties untouched fluid to the fluid the tool moves (Pouring, Transporting)",
    "dp-h": "the same gradient descent on the hard-contact physics without those techniques (the paper's DP-H)",
    "cma-es": "CMA-ES (the cma package), gradient-free, one rollout per sample, no backward pass",
    "sac": "Soft Actor-Critic (Stable-Baselines3) on the Gymnasium environment, reward c1 - c2 * step loss",
    "ppo": "Proximal Policy Optimisation (Stable-Baselines3) on the Gymnasium environment, reward c1 - c2 * step loss",
    "pods": "PODS (Mora et al. 2021): a policy network fitted to actions improved by the simulator's gradient, "
            "two rollouts per iteration",
    "cma-es-free": "CMA-ES over knots spread over the whole horizon where the task has the paper's periodic stroke "
                   "(Gathering): the tool may end anywhere, as the RL policies' may; the same as cma-es elsewhere",
    "dp-free": "dp over the knots of cma-es-free (8 per axis over the whole horizon) where the task has the paper's "
               "periodic stroke (Gathering); the same as dp elsewhere",
    "dp-window": "gradient descent over short windows of the horizon in turn (each from the state the current "
                 "actions reach, its gradient truncated there), for long horizons whose whole gradient explodes; "
                 "tasks whose loss is a mean over steps (AirCirculation, Gathering, Transporting)",
}


def check_request(task, method: str, budget, seed):
    """Refuse an optimisation request before any work starts: unknown method, a budget under one rollout of the
    horizon, a negative seed, a gradient method on a task whose liquid is projected (each with the reason)."""
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; methods: {', '.join(METHODS)}")
    if not isinstance(budget, (int, np.integer)) or isinstance(budget, bool) or budget < task.horizon:
        raise ValueError(f"budget must be a whole number of simulated steps of at least one rollout "
                         f"({task.horizon} steps for {task.name}, {task.size}), got {budget!r}")
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if method in GRADIENT_METHODS and task.pressure == "projection":
        raise ValueError(f"method {method!r} needs the simulator's gradients, which the liquid projection "
                         f"(pressure 'projection') does not have yet; use cma-es, sac or ppo on it, or pressure "
                         f"'state'")
    if method == "dp-window" and not task.loss_is_step_mean:
        raise ValueError(f"method 'dp-window' needs a loss that is a mean over the horizon's steps; {task.name}'s "
                         f"is not (use dp or dp-h)")


TECHNIQUES = ("soft_contact", "expanding_region", "attraction", "gradient_sharing")  # DP's, each switchable


def optimise(task, method: str, budget: int, seed: int = 0, callback=None, max_iterations: int | None = None,
             size: str = "small", without=(), min_generations: int | None = None, resume: dict | None = None):
    """Optimise `task` (a Task or a task name, made at `size`) and return its Trajectory. `without`: DP techniques
    to switch off (names from TECHNIQUES), for ablations; only with method "dp". `min_generations` (CMA-ES): the
    population is chosen so that the budget holds that many complete generations, and a budget that cannot is
    refused before anything runs (optim/cmaes.py). `resume`: a state from `progress.state()` of an earlier run of
    the same method, task, seed and budget (methods in RESUMABLE only), to continue that run."""
    from fluidlab_core import tasks
    from fluidlab_core.optim import cmaes, dp, pods, rl

    if isinstance(task, str):
        task = tasks.make(task, size=size)
    check_request(task, method, budget, seed)
    without = tuple(without)
    unknown = [w for w in without if w not in TECHNIQUES]
    if unknown:
        raise ValueError(f"unknown DP technique(s) {', '.join(map(repr, unknown))}; techniques: {', '.join(TECHNIQUES)}")
    if without and method != "dp":
        raise ValueError(f"switching techniques off applies to method 'dp' only ({method} has none to switch)")
    if resume is not None and method not in RESUMABLE:
        raise ValueError(f"{method} cannot resume a saved state (resumable: {', '.join(RESUMABLE)}); start it again")
    if method == "pods":
        result = pods.run(task, int(budget), int(seed), callback, max_iterations=max_iterations)
    elif method in rl.RL_METHODS:
        result = rl.run(task, method, int(budget), int(seed), callback, max_iterations=max_iterations)
    elif method in CMA_ES_METHODS:
        result = cmaes.run(task, int(budget), int(seed), callback, max_iterations=max_iterations,
                           min_generations=min_generations, method=method, free=method == "cma-es-free")
    else:
        opts = (dp.DPOptions(**{w: False for w in without}) if method == "dp" else
                dp.DPOptions(free_knots=True) if method == "dp-free" else
                dp.DPOptions.windowed(task) if method == "dp-window" else dp.DPOptions.plain())
        result = dp.run(task, int(budget), int(seed), callback, opts, method=method, max_iterations=max_iterations,
                        resume=resume)
    par = result.parametrisation
    actions, position = par.actions(result.theta), par.tool_position(result.theta)
    final = task.evaluate(actions, tool_position=position)
    meta = {"final_loss": final["loss"], "return": final["return"], "budget_steps": int(budget),
            "steps_used": result.steps, "iterations": result.iterations, "seconds": round(result.seconds, 2),
            "settings": result.settings}
    return task.trajectory(actions, tool_position=position, method=method, seed=int(seed),
                           loss_history=result.history, metadata=meta)


__all__ = ["optimise", "check_request", "METHODS", "CMA_ES_METHODS", "PAPER_METHODS", "RESUMABLE", "TECHNIQUES", "DESCRIPTIONS", "Progress", "Result"]
