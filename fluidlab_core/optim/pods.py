"""PODS: policy optimisation with the simulator's gradients (Mora et al., ICML 2021), first-order variant.

The paper's extra baseline: a policy network π_φ(o) (the environment's observation, envs.py) is improved in
two steps per iteration, as in Mora et al.'s Algorithm 1:

1. Roll out π_φ from the start state, with Gaussian exploration noise of std σ_i, on the reference physics
   (hard contact): observations o_t and applied actions a_t (m/s), and the task loss L(a).
2. Improve the actions with the simulator's gradient (the differentiable solver, hard contact, the task loss: the
   same gradient DP-H takes), a step of fixed size in the normalised gradient direction, projected on the bounds:

       a*_t = clip(a_t − η · v_max · g_t / rms(g)),   g = ∂L/∂a,   rms(g) = sqrt(mean(g²))

3. Fit the policy to the improved actions by regression: minimise Σ_t |π_φ(o_t) − a*_t|² (Adam, full batch).

Budget: each iteration costs two rollouts of the horizon (the policy's rollout, which records the observations,
and the gradient rollout), 2·N simulated steps. The result is the best rolled-out episode by task loss (the
start state is deterministic, so it is an open-loop trajectory, as for the RL baselines, optim/rl.py).

Settings (SETTINGS): policy two hidden layers of 64 (tanh), output v_max·tanh; η = 0.02 (the hard-contact
loss is rough: on LatteArtStir (small) from a random start, steps of η = 0.003, 0.01 and 0.03 lowered the loss,
by 2.1, 3.7 and 3.4e-6, and η = 0.1 and 0.3 raised it, by 2.1 and 1.6e-5); exploration σ from
0.3·v_max at the first iteration falling linearly to 0 at the end of the budget; regression 100 Adam steps of
learning rate 1e-3 per iteration. The first iteration's policy outputs about zero; its noise gives the gradient
something to act on, as DP's initial noise does.

Needs torch (the `rl` extra).
"""
from __future__ import annotations

import time

import numpy as np

from fluidlab_core.optim import params as P
from fluidlab_core.optim.progress import Progress, Result

SETTINGS = {"hidden": [64, 64], "step": 0.02, "noise_start": 0.3, "fit_steps": 100, "fit_learning_rate": 1e-3}


def _import_torch():
    try:
        import torch
    except ImportError:
        raise ImportError("PODS needs torch: pip install \".[rl]\" (or pip install torch==2.13.0)") from None
    return torch


def improve(actions: np.ndarray, grad: np.ndarray, v_max: float, step: float = SETTINGS["step"]) -> np.ndarray:
    """Step 2: the actions moved against the loss gradient by `step`·v_max per unit of the gradient's RMS, clipped
    to ±v_max (unchanged where the gradient is zero or not finite)."""
    rms = float(np.sqrt(np.mean(grad ** 2)))
    if rms == 0.0 or not np.isfinite(rms):
        return actions.copy()
    return np.clip(actions - step * v_max * grad / rms, -v_max, v_max)


def run(task, budget: int, seed: int, callback=None, max_iterations: int | None = None) -> Result:
    """Run first-order PODS for `budget` simulated steps (two rollouts per iteration); `callback(progress)` after
    each iteration (True stops). Returns the best episode's actions as an open-loop Result."""
    from fluidlab_core.envs import FluidLabEnv
    from fluidlab_core.optim.rl import set_torch_threads

    torch = _import_torch()
    set_torch_threads(torch)
    torch.manual_seed(int(seed))
    rng = np.random.default_rng(seed)
    horizon, k, v = task.horizon, task.n_actions, float(task.max_tool_speed)
    if budget < 2 * horizon:
        raise ValueError(f"PODS needs at least two rollouts per iteration ({2 * horizon} steps for {task.name}), "
                         f"got a budget of {budget}")
    env = FluidLabEnv(task.name, size=task.size, task=task)
    gsim = task.simulator(grad=True, contact="hard")
    n_obs = env.observation_space.shape[0]
    layers, width = [], n_obs
    for h in SETTINGS["hidden"]:
        layers += [torch.nn.Linear(width, h), torch.nn.Tanh()]
        width = h
    last = torch.nn.Linear(width, k)
    torch.nn.init.zeros_(last.weight)  # the first policy keeps the tool about still; the noise explores
    torch.nn.init.zeros_(last.bias)
    policy = torch.nn.Sequential(*layers, last, torch.nn.Tanh())
    optimiser = torch.optim.Adam(policy.parameters(), lr=SETTINGS["fit_learning_rate"])
    par = P.open_loop(task)
    zero_offset = np.zeros(par.size - par.n_action_params)
    iterations_max = budget // (2 * horizon)
    best = (np.inf, None)
    history, steps, iteration = [], 0, 0
    t0 = time.perf_counter()
    while steps + 2 * horizon <= budget and (max_iterations is None or iteration < max_iterations):
        sigma = SETTINGS["noise_start"] * v * (1.0 - iteration / max(iterations_max, 1))
        obs, _ = env.reset()
        observations, actions, loss = [], [], 0.0
        for _ in range(horizon):
            with torch.no_grad():
                mean = v * policy(torch.as_tensor(obs, dtype=torch.float32)).numpy().astype(np.float64)
            a = np.clip(mean + rng.normal(0.0, sigma, k), -v, v)
            observations.append(obs)
            actions.append(a)
            obs, _, _, _, info = env.step(a)
            loss += info["task_loss"]
        actions = np.array(actions)
        task.reset(gsim)
        res = gsim.rollout(task.twists(actions), task.loss(horizon), grad=True)
        steps += 2 * horizon
        iteration += 1
        history.append(loss)
        if loss < best[0]:
            best = (loss, np.concatenate([actions.reshape(-1), zero_offset]))
        target = improve(actions, res.grad_actions[:, 0, list(task.action_axes)], v)
        o = torch.as_tensor(np.array(observations), dtype=torch.float32)
        y = torch.as_tensor(target / v, dtype=torch.float32)
        for _ in range(SETTINGS["fit_steps"]):
            optimiser.zero_grad()
            fit = torch.mean((policy(o) - y) ** 2)
            fit.backward()
            optimiser.step()
        if callback and callback(Progress("pods", iteration, loss, best[0], steps, budget,
                                          time.perf_counter() - t0, horizon, best[1], par)):
            break
    return Result(par, best[1], history, steps, iteration, time.perf_counter() - t0,
                  {**SETTINGS, "result": "best rolled-out episode by task loss", "steps_per_iteration": 2 * horizon})
