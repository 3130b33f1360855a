"""Pouring: DP's gradient with respect to the tilt-rate knots against central finite differences of the same
loss, at the task's starting pour (Task.initial_actions), over the whole 8 s horizon.

    python bench/pouring_gradient.py [--knots 3 5 7 9] [--eps 0.02 0.005]
    python bench/pouring_gradient.py --short      # 200 steps, float64, a smooth loss, steps from 5e-3 to 1e-6
    python bench/pouring_gradient.py --short --softness 400   # the same with a soft glass (contact law, 1/m)
    python bench/pouring_gradient.py --softness 400           # the 8 s gradient with a soft glass

Writes bench/results/pouring_gradient_small.txt (--short: pouring_gradient_short.txt; with --softness k the
names end in _soft<k>). Finite differences use
the simulator the gradient came from, with steps of eps rad/s on one knot.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--knots", type=int, nargs="+", default=[3, 5, 7, 9])
    ap.add_argument("--eps", type=float, nargs="+", default=[0.02, 0.005])
    ap.add_argument("--out", default=None)
    ap.add_argument("--short", action="store_true",
                    help="the first 200 steps in float64 with a smooth loss (mean squared distance of every particle "
                         "to a point), knot 1, eps 5e-3 1e-4 1e-6: is the loss smooth at the scale of the step?")
    ap.add_argument("--softness", type=float, default=None,
                    help="the glass's soft contact in 1/m in the gradient's scene (Pouring.glass_softness; default: hard)")
    args = ap.parse_args()
    results = Path(__file__).resolve().parent / "results"
    suffix = f"_soft{args.softness:g}" if args.softness else ""
    if args.short:
        return short(results / f"pouring_gradient_short{suffix}.txt", softness=args.softness)
    args.out = args.out or str(results / f"pouring_gradient_small{suffix}.txt")
    import fluidlab_core

    fluidlab_core.init("cpu")
    task, par, theta, sim = _starting_pour(args.softness)
    t0 = time.perf_counter()
    task.reset(sim, par.tool_position(theta))
    res = sim.rollout(task.twists(par.actions(theta)), task.loss(task.horizon), grad=True)
    grad = par.gradient(res.grad_actions[:, 0, list(task.action_axes)], res.grad_tool_position[0])
    seconds = time.perf_counter() - t0

    def loss(th):
        return task.evaluate(par.actions(th), tool_position=par.tool_position(th), sim=sim, rewards=False)["loss"]

    knot_time = task.horizon * task.dt / (task.action_knots - 1)
    lines = [f"Pouring (small, {_glass(args.softness)}, {task.horizon} steps of {task.dt * 1e3:g} ms, {task.action_knots} knots "
             f"{knot_time:.2f} s apart), at the starting pour: loss {res.loss:.5g} m; gradient by the "
             f"differentiable simulator ({seconds:.0f} s) against central differences of the loss (m per rad/s).",
             f"{'knot':>4} {'time s':>7} {'gradient':>12} " + " ".join(f"{'FD eps ' + format(e, 'g'):>14}"
                                                                    for e in args.eps)]
    for k in args.knots:
        fds = []
        for eps in args.eps:
            e = np.zeros_like(theta)
            e[k] = eps
            fds.append((loss(theta + e) - loss(theta - e)) / (2 * eps))
        lines.append(f"{k:>4} {k * knot_time:>7.2f} {grad[k]:>12.4g} " + " ".join(f"{f:>14.4g}" for f in fds))
        print(lines[-1], flush=True)
    lines.append("gradient at every knot: " + " ".join(f"{g:.3g}" for g in grad[: par.n_action_params]))
    Path(args.out).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def _starting_pour(softness):
    """The small Pouring task with the glass's softness in DP's soft scene, its parametrisation, the parameters of
    its starting pour (Task.initial_actions) and its soft-contact gradient simulator."""
    from fluidlab_core import tasks
    from fluidlab_core.optim import params as P

    task = tasks.make("Pouring", "small")
    task.glass_softness = softness
    par = P.default(task)
    theta = np.zeros(par.size)
    theta[: par.n_action_params] = par.fit(task.initial_actions())
    return task, par, theta, task.simulator(grad=True, contact="soft")


def _glass(softness) -> str:
    return "hard glass" if softness is None else f"soft glass ({softness:g} /m)"


def short(out: Path, steps: int = 200, knot: int = 1, eps=(5e-3, 1e-4, 1e-6), softness=None):
    import fluidlab_core
    from fluidlab_core import losses

    fluidlab_core.init("cpu", precision="f64")
    task, par, theta, sim = _starting_pour(softness)

    def run(th, grad):
        task.reset(sim, par.tool_position(th))
        loss = losses.MeanSquaredDistance(np.array([0.5, 0.0, 0.0]))  # smooth in the particles
        return sim.rollout(task.twists(par.actions(th)[:steps]), loss, grad=grad)

    res = run(theta, True)
    ga = np.zeros((task.horizon, task.n_actions))
    ga[:steps] = res.grad_actions[:, 0, list(task.action_axes)]
    g = par.gradient(ga, res.grad_tool_position[0])[knot]
    lines = [f"Pouring (small, {_glass(softness)}), the first {steps} steps in float64, loss: mean squared distance "
             f"of every particle to (0.5, 0, 0) (m²), at the starting pour; knot {knot}: gradient {g:.4g} (m² per rad/s).",
             f"forward loss: differentiable solver {res.loss:.12g}, fast solver {run(theta, False).loss:.12g}"]
    for e in eps:
        d = np.zeros_like(theta)
        d[knot] = e
        fd = (run(theta + d, False).loss - run(theta - d, False).loss) / (2 * e)
        lines.append(f"central difference with a step of {e:g} rad/s: {fd:.4g}")
        print(lines[-1], flush=True)
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
