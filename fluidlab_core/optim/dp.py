"""Gradient-based trajectory optimisation (DP) with FluidLab's techniques, and plain DP-H.

Each iteration runs the differentiable simulator over the optimisation region (the first r steps), takes
the gradient of the loss with respect to the trajectory parameters θ (actions through a linear
parametrisation, optim/params.py, and the initial tool position), and makes an Adam step, projected on the
bounds (±max_tool_speed, the workspace):

    m ← β1 m + (1 − β1) g,  v ← β2 v + (1 − β2) g²,  θ ← clip(θ − α m̂ / (sqrt(v̂) + ε))

The techniques of Xian et al. (2023, §5), each switchable:
- soft contact: optimise on the task with the soft tool contact model (smoother gradients); the result is
  evaluated on the reference (hard contact) physics.
- temporally expanding region: start with the first quarter of the horizon and grow it by a quarter when the
  loss stops improving (relative change < 2 % over two iterations), and in any case so that the whole
  horizon is reached by half of the budget. Not for a task that sets `expanding_region = False` (Pouring: its
  goal is the state after a pour and the way back, which no partial horizon approaches).
- attraction: add w·Σ_k |p_tool(k) − x̄_body(k)|² (horizontal), which pulls the tool towards the fluid it
  must move, where the task loss alone has no gradient (the project's own, used before the paper's gradient
  sharing below existed here). w starts at 10 % of the task loss per unit of attraction and decays by half
  each iteration.
- gradient sharing within fluid bodies, where the task defines it (`Task.gradient_sharing`: Pouring and
  Transporting, as in the paper's released code; tasks/losses.py gives the terms): particles the tool does not
  move are tied to those it does, so that they carry a gradient. Its weight is set once, to 10 % of the task
  loss per unit of the term on the first rollout, and then held (the released code holds it too; the Pouring
  term shrinks by itself as the liquid leaves).
DP-H is the same loop with hard contact, the full horizon from the start, and neither attraction nor sharing.

DP over free knots ("dp-free", our own): DP with its techniques over the parametrisation of "cma-es-free" where a
task has the paper's periodic stroke (Gathering: 8 knots per axis, piecewise linear over the whole horizon, so
that the tool may end anywhere; `DPOptions.free_knots`), and plain DP elsewhere. The stroke held CMA-ES back on
Gathering (README); this tells whether it held DP back too. Its region starts at a quarter of the horizon, as on
a task without a stroke.

DP over windows ("dp-window", our own, for long horizons whose gradient explodes backwards in time): the horizon
is cut into windows of w steps (`Task.gradient_window`, default a quarter of the horizon). An iteration runs
the current actions forward without gradients to the start s of one window, then differentiates the loss of
the window and of a look-ahead of w more steps (what the window's actions cause shows up later: air takes
time to reach a sensor), (1/n) Σ_{k=s+1}^{s+n} ℓ_k with n = min(2w, N − s), and steps only the parameters of
the window's own actions and the tool's starting position; the windows take turns, each with its own Adam
moments. The state at s is held fixed (a truncated gradient: the effect of a window's actions past its
look-ahead is left out), which keeps each backward pass short, where the gradient still matches finite
differences. For tasks whose loss is the mean of the per-step term ℓ_k over the horizon
(`Task.loss_is_step_mean`). Before each turn through the windows, and after the last step, the whole horizon
is evaluated forward (its steps count in the budget) for the best so far.

Budget: simulated steps. An iteration over r steps counts r (the backward pass re-simulates those steps too
and costs a few forward passes in time; the reports give wall time beside steps).

Resuming (DP, DP-H and the ablations; not "dp-window"): each Progress carries `state()`, the whole loop's state
after that iteration (θ, Adam's moments and step count, the best so far, the region and its recent losses, the
helpers' weights, steps, iterations, seconds) as a dict of numbers and arrays, and `run(..., resume=state)`
continues from it: on the CPU (bit-identical reruns) the resumed run's iterates equal an uninterrupted run's. A
state is refused when its method, task, seed, budget or parameter count differs from the run's. The benchmark
saves it every few minutes, so that a run of hours survives an interrupted session (benchmark.py).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from fluidlab_core.optim import params as P
from fluidlab_core.optim.progress import Progress, Result


@dataclass
class DPOptions:
    soft_contact: bool = True
    expanding_region: bool = True
    attraction: bool = True
    gradient_sharing: bool = True
    learning_rate: float = 0.1  # Adam step, as a fraction of max_tool_speed (actions) or of 5 mm (tool position)
    initial_noise: float = 0.3  # std of the initial actions, as a fraction of max_tool_speed
    optimise_pose: bool = True
    gradient_window: int | None = None  # steps per window ("dp-window"); None: the region scheme above
    free_knots: bool = False  # "dp-free": free knots over the horizon instead of a periodic task's stroke

    @classmethod
    def plain(cls) -> "DPOptions":
        return cls(soft_contact=False, expanding_region=False, attraction=False, gradient_sharing=False)

    @classmethod
    def windowed(cls, task) -> "DPOptions":
        """"dp-window": soft contact, the task's gradient window, no expanding region, attraction or sharing."""
        return cls(expanding_region=False, attraction=False, gradient_sharing=False,
                   gradient_window=task.gradient_window or max(1, task.horizon // 4))


class _Adam:
    def __init__(self, lr: np.ndarray, beta1=0.9, beta2=0.999, eps=1e-12):
        self.lr, self.b1, self.b2, self.eps = lr, beta1, beta2, eps
        self.m = np.zeros_like(lr)
        self.v = np.zeros_like(lr)
        self.t = 0

    def step(self, theta, g):
        self.t += 1
        self.m = self.b1 * self.m + (1 - self.b1) * g
        self.v = self.b2 * self.v + (1 - self.b2) * g * g
        m_hat = self.m / (1 - self.b1 ** self.t)
        v_hat = self.v / (1 - self.b2 ** self.t)
        return theta - self.lr * m_hat / (np.sqrt(v_hat) + self.eps)


def _start(task, seed: int, opts: DPOptions):
    """The parametrisation, the seeded starting parameters, Adam's step per parameter, and the gradient simulator."""
    par = P.knots(task, free=True) if opts.free_knots and task.periodic else P.default(task)
    rng = np.random.default_rng(seed)
    theta = np.zeros(par.size)
    start = task.initial_actions()
    noise = opts.initial_noise if start is None else task.start_noise
    theta[: par.n_action_params] = rng.normal(0.0, noise * task.max_tool_speed, par.n_action_params)
    if start is not None:  # the task's documented starting motion (Task.initial_actions), in the parametrisation,
        # with less noise than a start from rest: the motion is there to be refined, not scrambled (Pouring's
        # pour turns on a tenth of a radian of tilt; DP's noise at rest scrambles its tilt by about 0.5 rad)
        theta[: par.n_action_params] += par.fit(start)
    theta = par.clip(theta)
    rate = task.learning_rate if task.learning_rate is not None else opts.learning_rate
    lr = np.concatenate([np.full(par.n_action_params, rate * task.max_tool_speed),
                         np.full(par.size - par.n_action_params, opts.learning_rate * 5e-3 if opts.optimise_pose else 0.0)])
    sim = task.simulator(grad=True, contact="soft" if opts.soft_contact else "hard")
    return par, theta, lr, sim


STATE_FORMAT = "fluidlab-dp-state"
STATE_VERSION = 1


def _grown(region: int, region_losses: list, steps_used: int, horizon: int, budget: int) -> tuple[int, list]:
    """The expanding region after an iteration: a quarter of the horizon more when the loss over the region stopped
    improving (relative change ≤ 2 % over two iterations) or when the schedule demands it (the whole horizon by
    half the budget); the region's recent losses start again when it grows."""
    if region < horizon:
        plateau = len(region_losses) >= 3 and abs(region_losses[-1] - region_losses[-3]) <= \
            0.02 * abs(region_losses[-3])
        forced = region < horizon * min(1.0, 0.25 + 1.5 * steps_used / budget)
        if plateau or forced:
            return min(horizon, region + int(np.ceil(0.25 * horizon))), []
    return region, region_losses


def _check_state(state: dict, method: str, task, seed: int, budget: int, n_params: int):
    """Refuse a saved state that belongs to another run, naming the field that differs."""
    if state.get("format") != STATE_FORMAT or int(state.get("version", -1)) != STATE_VERSION:
        raise ValueError(f"not a DP state of version {STATE_VERSION} (format {state.get('format')!r}, version "
                         f"{state.get('version')!r})")
    want = {"method": method, "task": task.name, "seed": int(seed), "budget": int(budget), "n_params": int(n_params)}
    for key, value in want.items():
        if state.get(key) != value:
            raise ValueError(f"the saved DP state is for {key} {state.get(key)!r}, this run has {value!r}")


def run(task, budget: int, seed: int, callback=None, options: DPOptions | None = None, method: str = "dp",
        max_iterations: int | None = None, resume: dict | None = None) -> Result:
    opts = options or DPOptions()
    if opts.gradient_window is not None:
        if resume is not None:
            raise ValueError("DP over windows (dp-window) cannot resume a saved state; start it again")
        return _run_windows(task, budget, seed, callback, opts, method, max_iterations)
    par, theta, lr, sim = _start(task, seed, opts)
    adam = _Adam(lr)
    horizon = task.horizon
    expanding = opts.expanding_region and task.expanding_region
    region = max(1, int(np.ceil(0.25 * horizon))) if expanding else horizon
    if task.periodic and not opts.free_knots:  # at least one period of the stroke
        region = max(region, min(horizon, sum(task.periodic)))
    attraction = task.attraction(0.0) if opts.attraction else None
    sharing = task.gradient_sharing(0.0) if opts.gradient_sharing else None
    helpers = [h for h in (attraction, sharing) if h is not None]
    scales: list[float | None] = [None] * len(helpers)
    history, steps_used, iteration = [], 0, 0
    best = (np.inf, theta.copy())
    region_losses: list[float] = []
    elapsed_before = 0.0
    if resume is not None:
        _check_state(resume, method, task, seed, budget, par.size)
        theta = np.array(resume["theta"], dtype=float)
        adam.m, adam.v, adam.t = np.array(resume["adam_m"], float), np.array(resume["adam_v"], float), int(resume["adam_t"])
        history = [float(x) for x in resume["history"]]
        steps_used, iteration, region = int(resume["steps_used"]), int(resume["iteration"]), int(resume["region"])
        best = (float(resume["best_loss"]), np.array(resume["best_theta"], dtype=float))
        region_losses = [float(x) for x in resume["region_losses"]]
        scales = [None if x is None else float(x) for x in resume["scales"]]
        if len(scales) != len(helpers):
            raise ValueError(f"the saved DP state has {len(scales)} helper weight(s), this run has {len(helpers)} "
                             "(attraction, gradient sharing): another set of techniques")
        if attraction is not None:
            attraction.weight = (scales[0] or 0.0) * 0.5 ** iteration
        if sharing is not None:
            sharing.weight = scales[-1] or 0.0
        elapsed_before = float(resume["elapsed"])
    t0 = time.perf_counter() - elapsed_before

    def state() -> dict:
        """The loop's state after the last iteration (what `resume` takes)."""
        nxt, nxt_losses = _grown(region, region_losses, steps_used, horizon, budget)
        return {"format": STATE_FORMAT, "version": STATE_VERSION, "method": method, "task": task.name,
                "seed": int(seed), "budget": int(budget), "n_params": int(par.size), "theta": theta.copy(),
                "adam_m": adam.m.copy(), "adam_v": adam.v.copy(), "adam_t": int(adam.t),
                "history": [float(x) for x in history], "steps_used": int(steps_used), "iteration": int(iteration),
                "region": int(nxt), "region_losses": [float(x) for x in nxt_losses],
                "best_loss": float(best[0]), "best_theta": best[1].copy(),
                "scales": [None if x is None else float(x) for x in scales],
                "elapsed": float(time.perf_counter() - t0)}

    while steps_used + region <= budget and (max_iterations is None or iteration < max_iterations):
        actions = par.actions(theta)
        task.reset(sim, par.tool_position(theta))
        loss = task.loss(region)
        for h in helpers:
            h.values.clear()
            loss = loss + h
        res = sim.rollout(task.twists(actions[:region]), loss, grad=True)
        steps_used += region
        iteration += 1
        task_loss = res.loss - sum(h.total for h in helpers)
        for i, h in enumerate(helpers):  # 10 % of the task loss per unit of its value, from the first rollout
            if scales[i] is None and sum(h.values.values()) > 0:  # in which the helper has a value
                scales[i] = 0.1 * abs(task_loss) / sum(h.values.values())
        if attraction is not None:
            attraction.weight = (scales[0] or 0.0) * 0.5 ** iteration
        if sharing is not None:
            sharing.weight = scales[-1] or 0.0
        ga = np.zeros((horizon, task.n_actions))
        ga[:region] = res.grad_actions[:, 0, list(task.action_axes)]
        g = par.gradient(ga, res.grad_tool_position[0])
        if region == horizon:
            history.append(task_loss)
            if task_loss < best[0]:
                best = (task_loss, theta.copy())
        theta = par.clip(adam.step(theta, g))
        elapsed = time.perf_counter() - t0
        region_losses.append(task_loss)
        if callback and callback(Progress(method, iteration, task_loss, best[0], steps_used, budget, elapsed,
                                          region, best[1], par, state)):
            break
        region, region_losses = _grown(region, region_losses, steps_used, horizon, budget)
    if not np.isfinite(best[0]):  # never reached the whole horizon: keep the last parameters
        best = (np.nan, theta)
    return Result(par, best[1], history, steps_used, iteration, time.perf_counter() - t0,
                  {"soft_contact": opts.soft_contact and task.tool_touches_particles, "expanding_region": expanding,
                   "attraction": attraction is not None, "gradient_sharing": sharing is not None,
                   "parametrisation": par.name})


def windows(horizon: int, window: int) -> list[tuple[int, int]]:
    """(start, length) of each gradient window: consecutive, the last one shorter where w does not divide the
    horizon."""
    if not (isinstance(window, (int, np.integer)) and 1 <= window <= horizon):
        raise ValueError(f"gradient window must be a whole number of steps from 1 to the horizon ({horizon}), "
                         f"got {window!r}")
    return [(s, min(window, horizon - s)) for s in range(0, horizon, int(window))]


def _differentiated(start: int, length: int, horizon: int) -> int:
    """Steps a window's iteration differentiates: the window and a look-ahead as long, within the horizon."""
    return min(2 * length, horizon - start)


def window_step(task, sim, par, theta: np.ndarray, start: int, length: int, grad: bool = True):
    """The loss of one window of `length` steps and its look-ahead, (1/n) Σ_{k=start+1}^{start+n} ℓ_k with
    n = min(2·length, horizon − start), under the parameters θ; with grad also its gradient with respect to θ
    through those steps only (the state at `start` held fixed), from the actions of the window itself and the
    tool's starting position: reset, run forward without gradients to `start`, then differentiate the n steps.
    Returns (loss, gradient or None, simulated steps run)."""
    from fluidlab_core.losses import Loss

    n = _differentiated(start, length, task.horizon)
    twists = task.twists(par.actions(theta))
    task.reset(sim, par.tool_position(theta))
    if start:
        sim.rollout(twists[:start], Loss(steps=()), grad=False)  # a loss active at no step: nothing evaluated
    res = sim.rollout(twists[start:start + n], (1.0 / n) * task.step_term(), grad=grad)
    if not grad:
        return float(res.loss), None, start + n
    ga = np.zeros((task.horizon, task.n_actions))
    ga[start:start + length] = res.grad_actions[:length, 0, list(task.action_axes)]
    return float(res.loss), par.gradient(ga, res.grad_tool_position[0]), start + n


def _run_windows(task, budget, seed, callback, opts, method, max_iterations) -> Result:
    if not task.loss_is_step_mean:
        raise ValueError(f"DP over windows needs a loss that is the mean of a per-step term over the horizon; "
                         f"{task.name}'s is not (Task.loss_is_step_mean)")
    horizon = task.horizon
    spans = windows(horizon, opts.gradient_window)
    par, theta, lr, sim = _start(task, seed, opts)
    adams = [_Adam(lr) for _ in spans]  # each window its own moments: a window's step ignores the others' gradients
    history, steps_used, iteration, turn = [], 0, 0, 0
    best = (np.inf, theta.copy())
    judged = None  # the parameters last evaluated over the whole horizon
    t0 = time.perf_counter()

    def whole_horizon():
        nonlocal steps_used, best, judged
        task.reset(sim, par.tool_position(theta))
        value = float(sim.rollout(task.twists(par.actions(theta)), task.loss(), grad=False).loss)
        steps_used += horizon
        history.append(value)
        judged = theta.copy()
        if value < best[0]:
            best = (value, theta.copy())

    while max_iterations is None or iteration < max_iterations:
        start, length = spans[turn % len(spans)]
        if turn % len(spans) == 0:  # before each turn through the windows (the first too): the whole horizon
            if steps_used + horizon > budget:
                break
            whole_horizon()
        if steps_used + start + _differentiated(start, length, horizon) > budget:
            break
        loss, g, used = window_step(task, sim, par, theta, start, length)
        steps_used += used
        iteration += 1
        theta = par.clip(adams[turn % len(spans)].step(theta, g))
        turn += 1
        if callback and callback(Progress(method, iteration, loss, best[0], steps_used, budget,
                                          time.perf_counter() - t0, length, best[1], par)):
            break
    if steps_used + horizon <= budget and not np.array_equal(judged, theta):
        whole_horizon()  # the last parameters, unless they were just judged
    return Result(par, best[1], history, steps_used, iteration, time.perf_counter() - t0,
                  {"soft_contact": opts.soft_contact and task.tool_touches_particles,
                   "gradient_window": int(opts.gradient_window),
                   "windows": len(spans), "parametrisation": par.name})
