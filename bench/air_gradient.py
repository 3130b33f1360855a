"""Why gradient descent trails on AirCirculation: the 240-step loss against its gradient, at several scales.

    python bench/air_gradient.py [--quick] [--rows I ...] [--horizon N] [--out bench/results/air_gradient.txt]

AirCirculation (small, float64, pressure solved to a relative residual of 1e-10 so that the solve's stopping
point is not what is measured), DP's seed-0 start (yaw-rate knots drawn as DP draws them). For one knot (knot 1:
the yaw rate about 0.1–0.2 of the way into the episode), the backward pass's derivative of the whole-episode loss
against central differences over ±ε for ε from 1e-8 to 1e-3 rad/s. Rows:
- MacCormack advection with the cell limiter (the task's reference physics), the conditioner blocking the gas
  (the task) and not (so that its voxelised cells cannot switch);
- MacCormack with the continuous limiter (engine/gas.py: its clamp range moves with the traced point), likewise;
- semi-Lagrangian advection, not blocking;
- MacCormack with either limiter, the conditioner blocking by face fractions (`tool_faces="fractions"`: the
  blocked share of each face moves continuously with it, so no cell switches; blocks "frac").
Where the differences agree with the backward pass at small ε but not at large, the loss is piecewise smooth
with pieces about that wide: the gradient is exact and says nothing about a step of DP's size (0.01–0.05 rad/s).
--quick: the first row only, ε 1e-7 and 1e-4. --rows: only these rows (0-based, in the order above). --horizon: the
loss over the first N steps only (its mean over them), to see how the roughness builds up with the horizon. Each
run appends its table to --out.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
KNOT = 1


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--rows", type=int, nargs="+", default=None)
    ap.add_argument("--horizon", type=int, default=None)
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "air_gradient.txt"))
    args = ap.parse_args(argv)
    from fluidlab_core import runtime

    runtime.init("cpu", "f64", cpu_threads=1)
    import fluidlab_core.scene as scene_module
    from fluidlab_core.optim import params as P
    from fluidlab_core.tasks import make

    rows = [("maccormack", "cell", False), ("maccormack", "cell", True), ("maccormack", "continuous", False),
            ("maccormack", "continuous", True), ("semi-lagrangian", "-", False),
            ("maccormack", "cell", "fractions"), ("maccormack", "continuous", "fractions")]
    eps_list = (1e-8, 1e-7, 1e-5, 1e-4, 1e-3)
    if args.rows:
        rows = [rows[i] for i in args.rows]
    if args.quick:
        rows, eps_list = rows[:1], (1e-7, 1e-4)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    horizon = args.horizon or 240
    lines = [f"AirCirculation small, float64, pressure to 1e-10, DP's seed-0 start; d(loss)/d(knot 1), the loss over the "
             f"first {horizon} steps of the 240-step episode (K per rad/s): the backward pass against central "
             "differences over ±ε (bench/air_gradient.py)",
             f"{'advection':<16} {'limiter':<10} {'blocks':>6} {'backward':>10} " + " ".join(f"{'FD ' + format(e, 'g'):>10}" for e in eps_list)
             + f" {'run s':>6}"]
    print("\n".join(lines), flush=True)
    original = scene_module.Scene.add_gas
    for advection, limiter, blocks in rows:
        t0 = time.perf_counter()

        def add_gas(self, *a, **k):
            k.update(advection=advection, tools_block=bool(blocks), tolerance=1e-10, max_iterations=1000,
                     limiter=limiter if limiter != "-" else "cell",
                     tool_faces="fractions" if blocks == "fractions" else "cells")
            return original(self, *a, **k)

        scene_module.Scene.add_gas = add_gas
        try:
            task = make("AirCirculation", "small")
            par = P.default(task)
            rng = np.random.default_rng(0)
            theta = par.clip(rng.normal(0.0, 0.3 * task.max_tool_speed, par.size))  # DP's start (optim/dp.py)
            sim = task.simulator(grad=True, grad_max_steps=task.horizon)

            def run(th, grad=False):
                task.reset(sim, par.tool_position(th))
                return sim.rollout(task.twists(par.actions(th))[:horizon], task.loss(horizon), grad=grad)

            r = run(theta, True)
            ga = np.zeros((task.horizon, len(task.action_axes)))  # the steps after the horizon have no gradient
            ga[:horizon] = r.grad_actions[:, 0, list(task.action_axes)]
            g = par.gradient(ga, r.grad_tool_position[0])
            e = np.zeros(par.size)
            e[KNOT] = 1.0
            fd = [(run(par.clip(theta + eps * e)).loss - run(par.clip(theta - eps * e)).loss) / (2 * eps)
                  for eps in eps_list]
        finally:
            scene_module.Scene.add_gas = original
        shown = "frac" if blocks == "fractions" else ("yes" if blocks else "no")
        lines.append(f"{advection:<16} {limiter:<10} {shown:>6} {g[KNOT]:>+10.4g} "
                     + " ".join(f"{v:>+10.4g}" for v in fd) + f" {time.perf_counter() - t0:>6.0f}")
        print(lines[-1], flush=True)
    with open(out, "a") as f:
        f.write("\n".join(lines) + "\n\n")
    print(f"appended to {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
