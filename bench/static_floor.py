"""Liquid at rest on a static floor: does it keep its depth? (issue 19: the tasks' physics)

    python bench/static_floor.py [--res 20] [--offsets 0 0.25 0.5 0.75 0.9] [--seconds 0.1 1 2]
        [--tasks GatheringEasy LatteArtStir Mixing] [--out bench/results/static_floor_cpu.txt] [--label TEXT]

The tasks hold their liquids in statics (a tank, a cup: SDFs on the grid, engine/statics.py), not in the domain's
walls. Water at rest fills V/A whatever holds it (less its hydrostatic compression, ρgh/(2K) on average: 0.77 % for
the tasks' water, c = 4 m/s, 25 mm deep). Rows:
- walls: the tasks' water 25 mm deep held by the domain's walls (a node row on each wall; the reference);
- tank, offset o: the same water in a static tank (walls two cells thick), its floor's surface o cells above a node
  row (0: on one, as the tasks' tank at the small size; the paper size's is at 0.4);
- a task (the tool held still): its first body's (the tank's water, the cup's coffee) mean height against its start,
  the share of its particles on the floor (a quarter cell under its lowest particle at the start), their mean J.
Each row: the depth 2 (mean z − floor) at each time (mm), the share of particles within 0.05 cells of the floor, the
particles' mean J. Appends its table to the output file. About 3 minutes on two cores.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from results_file import append_table  # bench/results_file.py (this script's folder is on the path)

ROOT = Path(__file__).resolve().parents[1]


def task_row(name: str, seconds) -> str:
    import fluidlab_core as fl
    from fluidlab_core import tasks

    task = tasks.make(name, "small")
    sim = task.simulator()
    task.reset(sim)
    dx = task.scene().dx
    body = task.observed_bodies[0]  # the tank's water, the cup's coffee
    x = sim.positions(body)
    floor = x[:, 2].min() - 0.25 * dx  # the lowest particle row sits a quarter cell above the floor
    z0 = x[:, 2].mean()
    cells = []
    for t in seconds:
        while sim.time < t - 1e-9:
            sim.step(action=np.zeros(6))
        z = sim.positions(body)[:, 2]
        J = np.linalg.det(sim.deformation_gradients(body)).mean()
        cells.append(f"{1e3 * (z.mean() - z0):+.2f} mm, {(z < floor + 0.05 * dx).mean():.3f}, "
                     f"{J:.4f}")
    fl.runtime.reset()
    return f"{name} ({body}'s mean height from its start) | " + " | ".join(cells)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--res", type=int, default=20)
    ap.add_argument("--offsets", type=float, nargs="*", default=[0.0, 0.25, 0.5, 0.75, 0.9])
    ap.add_argument("--seconds", type=float, nargs="+", default=[0.1, 1.0, 2.0])
    ap.add_argument("--tasks", nargs="*", default=["GatheringEasy", "LatteArtStir", "Mixing"])
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "static_floor_cpu.txt"))
    ap.add_argument("--label", default="", help="a note for the table's header (e.g. the engine's revision)")
    args = ap.parse_args(argv)
    import fluidlab_core as fl
    from fluidlab_core.apps import validation

    fl.init(arch="cpu")
    lines = [f"# bench/static_floor.py, {time.strftime('%Y-%m-%d %H:%M')}, CPU, float32, {args.res} cells per 0.1 m, "
             f"the tasks' water 25 mm deep{'; ' + args.label if args.label else ''}",
             "# case | at " + " | at ".join(f"{t:g} s: depth (mm), share on the floor, mean J" for t in args.seconds)]
    print("\n".join(lines), flush=True)
    cases = [("walls", dict(walls=True))] + [(f"tank, offset {o:g}", dict(offset=o)) for o in args.offsets]
    for label, kw in cases:
        r = validation.static_tank(res=args.res, times=args.seconds, **kw)
        lines.append(f"{label} | " + " | ".join(f"{1e3 * d:.2f}, {f:.3f}, {j:.4f}"
                                                 for d, f, j in zip(r["depth"], r["on_floor"], r["J"])))
        print(lines[-1], flush=True)
        fl.runtime.reset()
    for name in args.tasks:
        lines.append(task_row(name, args.seconds))
        print(lines[-1], flush=True)
    append_table(args.out, lines)


if __name__ == "__main__":
    main()
