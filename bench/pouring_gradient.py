"""Pouring: DP's gradient with respect to the tilt-rate knots against central finite differences of the same
loss, at the task's starting pour (Task.initial_actions), over the whole 8 s horizon.

    python bench/pouring_gradient.py [--knots 3 5 7 9] [--eps 0.02 0.005]

Writes bench/results/pouring_gradient_small.txt. Finite differences use the simulator the gradient came from
(float32 CPU), with steps of eps rad/s on one knot.
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
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "pouring_gradient_small.txt"))
    args = ap.parse_args()
    import fluidlab_core
    from fluidlab_core import tasks
    from fluidlab_core.optim import params as P

    fluidlab_core.init("cpu")
    task = tasks.make("Pouring", "small")
    par = P.default(task)
    theta = np.zeros(par.size)
    theta[: par.n_action_params] = np.linalg.lstsq(par.matrix, task.initial_actions().reshape(-1), rcond=None)[0]
    sim = task.simulator(grad=True, contact="soft")
    t0 = time.perf_counter()
    task.reset(sim, par.tool_position(theta))
    res = sim.rollout(task.twists(par.actions(theta)), task.loss(task.horizon), grad=True)
    grad = par.gradient(res.grad_actions[:, 0, list(task.action_axes)], res.grad_tool_position[0])
    seconds = time.perf_counter() - t0

    def loss(th):
        return task.evaluate(par.actions(th), tool_position=par.tool_position(th), sim=sim, rewards=False)["loss"]

    knot_time = task.horizon * task.dt / (task.action_knots - 1)
    lines = [f"Pouring (small, {task.horizon} steps of {task.dt * 1e3:g} ms, {task.action_knots} knots "
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


if __name__ == "__main__":
    main()
