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

Budget: simulated steps. An iteration over r steps counts r (the backward pass re-simulates those steps too
and costs a few forward passes in time; the reports give wall time beside steps).
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

    @classmethod
    def plain(cls) -> "DPOptions":
        return cls(soft_contact=False, expanding_region=False, attraction=False, gradient_sharing=False)


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


def run(task, budget: int, seed: int, callback=None, options: DPOptions | None = None, method: str = "dp",
        max_iterations: int | None = None) -> Result:
    opts = options or DPOptions()
    par = P.default(task)
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
    adam = _Adam(lr)
    sim = task.simulator(grad=True, contact="soft" if opts.soft_contact else "hard")
    horizon = task.horizon
    expanding = opts.expanding_region and task.expanding_region
    region = max(1, int(np.ceil(0.25 * horizon))) if expanding else horizon
    if task.periodic:
        region = max(region, min(horizon, sum(task.periodic)))
    attraction = task.attraction(0.0) if opts.attraction else None
    sharing = task.gradient_sharing(0.0) if opts.gradient_sharing else None
    helpers = [h for h in (attraction, sharing) if h is not None]
    scales: list[float | None] = [None] * len(helpers)
    history, steps_used, iteration = [], 0, 0
    best = (np.inf, theta.copy())
    t0 = time.perf_counter()
    region_losses: list[float] = []
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
                                          region, best[1], par)):
            break
        if region < horizon:
            plateau = len(region_losses) >= 3 and abs(region_losses[-1] - region_losses[-3]) <= \
                0.02 * abs(region_losses[-3])
            forced = region < horizon * min(1.0, 0.25 + 1.5 * steps_used / budget)
            if plateau or forced:
                region = min(horizon, region + int(np.ceil(0.25 * horizon)))
                region_losses = []
    if not np.isfinite(best[0]):  # never reached the whole horizon: keep the last parameters
        best = (np.nan, theta)
    return Result(par, best[1], history, steps_used, iteration, time.perf_counter() - t0,
                  {"soft_contact": opts.soft_contact, "expanding_region": expanding,
                   "attraction": attraction is not None, "gradient_sharing": sharing is not None,
                   "parametrisation": par.name})
