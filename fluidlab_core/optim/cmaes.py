"""CMA-ES (Hansen's `cma` package) over a low-dimensional trajectory parametrisation.

The search runs in normalised coordinates u ∈ [−1, 1]ⁿ, θ = lower + (u + 1)(upper − lower)/2, over the knots
parametrisation of optim/params.py (8 knots per axis, or the knots of a periodic stroke) plus the initial
tool position. Each candidate is one rollout of the whole horizon on the task's reference physics (hard
contact, no gradients); its task loss is the fitness. σ0 = 0.3 (of the half-range), seeded from the optimiser's
seed. Population: the package's default 4 + ⌊3 ln n⌋, unless `min_generations` is given: then the largest
population (at most the default, at least MIN_POPULATION) with which the budget holds that many generations,
and a budget that cannot hold them is refused with the reason. Without it a small budget may end before the
first generation is complete, when CMA-ES has not updated anything: random search.

Budget: simulated steps; one candidate costs the horizon.
"""
from __future__ import annotations

import time

import numpy as np

from fluidlab_core.optim import params as P
from fluidlab_core.optim.progress import Progress, Result


MIN_POPULATION = 4


def default_population(n: int) -> int:
    """The cma package's default population for n parameters: 4 + ⌊3 ln n⌋."""
    return 4 + int(3 * np.log(n))


def search_size(task, n_knots: int = P.KNOTS) -> int:
    """The number of parameters CMA-ES searches for `task` (the knots parametrisation above; the same over free
    knots)."""
    return P.knots(task, n_knots).size


def population_for(task, budget: int, min_generations: int, n_knots: int = P.KNOTS) -> int:
    """The largest population (≤ the default, ≥ MIN_POPULATION) whose `min_generations` generations fit in the
    budget; ValueError with the figures when none does."""
    rollouts = int(budget) // task.horizon
    pop = min(default_population(search_size(task, n_knots)), rollouts // max(1, int(min_generations)))
    if pop < MIN_POPULATION:
        need = MIN_POPULATION * int(min_generations)
        raise ValueError(f"CMA-ES needs at least {min_generations} generations of at least {MIN_POPULATION} "
                         f"candidates: {need} rollouts ({need * task.horizon} simulated steps for {task.name}, "
                         f"{task.size}); the budget holds {rollouts}")
    return pop


def run(task, budget: int, seed: int, callback=None, n_knots: int = P.KNOTS, sigma0: float = 0.3,
        max_iterations: int | None = None, method: str = "cma-es", min_generations: int | None = None,
        free: bool = False) -> Result:
    import warnings

    with warnings.catch_warnings():  # cma warns that matplotlib (for its plots) is missing
        warnings.simplefilter("ignore")
        import cma

    par = P.knots(task, n_knots, free=free)
    lo, hi = par.bounds()
    span = np.where(hi > lo, hi - lo, 1.0)

    def theta_of(u):
        return par.clip(lo + (np.asarray(u) + 1.0) * 0.5 * span)

    u0 = 2.0 * (par.clip(np.zeros(par.size)) - lo) / span - 1.0
    opts = {"bounds": [-1.0, 1.0], "seed": int(seed) + 1, "verbose": -9, "verb_log": 0, "verb_disp": 0}
    if min_generations:
        opts["popsize"] = population_for(task, budget, min_generations, n_knots)
    es = cma.CMAEvolutionStrategy(u0, sigma0, opts)
    sim = task.simulator(grad=False, contact="hard")
    history, steps_used, iteration, generations = [], 0, 0, 0
    best = (np.inf, theta_of(u0))
    t0 = time.perf_counter()
    stop = False
    while not stop and steps_used + task.horizon <= budget and (max_iterations is None or iteration < max_iterations):
        candidates = es.ask()
        fitness = []
        for u in candidates:
            if steps_used + task.horizon > budget:
                break
            theta = theta_of(u)
            out = task.evaluate(par.actions(theta), tool_position=par.tool_position(theta), sim=sim, rewards=False)
            steps_used += task.horizon
            fitness.append(out["loss"])
            history.append(out["loss"])
            if out["loss"] < best[0]:
                best = (out["loss"], theta.copy())
        iteration += 1
        if len(fitness) == len(candidates):  # a complete generation: CMA-ES updates its distribution
            es.tell(candidates, fitness)
            generations += 1
        if fitness and callback and callback(Progress(method, iteration, float(np.min(fitness)), best[0], steps_used,
                                                      budget, time.perf_counter() - t0, task.horizon, best[1], par)):
            stop = True
    return Result(par, best[1], history, steps_used, iteration, time.perf_counter() - t0,
                  {"parametrisation": par.name, "sigma0": sigma0, "popsize": es.popsize,
                   "generations": generations})
