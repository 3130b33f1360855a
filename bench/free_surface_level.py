"""Where the projection puts a still pool's free surface against where its volume fills the tank (issue 19;
docs/engine.md, "The free surface's height").

    python bench/free_surface_level.py [--res 16] [--phases 0 0.125 0.25 0.375 0.5 0.625 0.75 0.875]
        [--rules linear spline] [--seconds 0.15] [--threads 1]

A pool of the catalogue's water in a closed 12 cm box, `res` cells across, Scene(pressure="projection"), the stable
substep count, filled to 6 cm plus `phase` of a cell (so that its surface lies that share of the way from one node
row to the next), for each rule that places p = 0 between a liquid and an air node (projection.THETA_RULE). From
a third of `seconds` on, every tenth substep: H_p, the height at which the pressure's linear fit in the interior
columns (each liquid node but the lowest and the highest) reaches 0, against H_V, the height the liquid's volume
(Σ V⁰, m³) fills the tank to; the table gives (H_p − H_V)/Δx, the mean over the samples. A floating body sits in
the pressure that H_p sets, so its depth against H_V (how bench/buoyancy_3d.py and the tests measure it) is off by
about that (times its waterline's area over its volume). Appends its table to
bench/results/free_surface_level_cpu.txt.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from results_file import append_table  # bench/results_file.py (this script's folder is on the path)

WIDTH, LEVEL = 0.12, 0.06


def run(res: int, phase: float, rule: str, seconds: float) -> float:
    import fluidlab_core as fl
    from fluidlab_core import materials as M
    from fluidlab_core.apps import validation
    from fluidlab_core.engine import projection
    from fluidlab_core.shapes import Box

    fl.runtime.reset()
    projection.THETA_RULE = rule  # read when the kernels compile
    dx = WIDTH / res
    level = LEVEL + phase * dx
    scene = fl.Scene(lower=(0, 0, 0), upper=(WIDTH, WIDTH, 0.12), grid_res=res, dt=2e-3, substeps=1,
                     pressure="projection")
    scene.add_particles(Box((0, 0, 0), (WIDTH, WIDTH, level)), M.WATER, name="water")
    scene.substeps = scene.stable_substeps()
    sim = scene.build()
    pad = int(round(-sim.solver.model.origin[0] / sim.solver.model.dx))
    interior = [(i, j) for i in range(pad + 2, pad + res - 1) for j in range(pad + 2, pad + res - 1)]
    gaps = []
    while sim.time < seconds - 1e-9:
        sim.step(n=1)
        if sim.time < seconds / 3:
            continue
        h_v = float(sim.volumes("water").sum()) / WIDTH ** 2
        gaps.append((validation.pressure_zero(sim, interior) - h_v) / dx)
    return float(np.mean(gaps))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=16)
    ap.add_argument("--phases", type=float, nargs="+", default=[0, 0.125, 0.25, 0.375, 0.5, 0.625, 0.75, 0.875])
    ap.add_argument("--rules", nargs="+", default=["linear", "spline"], choices=["linear", "spline"])
    ap.add_argument("--seconds", type=float, default=0.15)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    import fluidlab_core as fl

    fl.init(arch="cpu", cpu_threads=args.threads)
    t0 = time.time()
    rows = []
    for phase in args.phases:
        gaps = []
        for rule in args.rules:
            gaps.append(run(args.res, phase, rule, args.seconds))
            print(f"phase {phase:.3f}, {rule}: (H_p - H_V)/dx = {gaps[-1]:+.4f}", flush=True)
        rows.append([f"{phase:.3f}"] + [f"{g:+.4f}" for g in gaps])
    head = ["phase"] + [f"{r}: (H_p - H_V)/dx" for r in args.rules]
    lines = [f"# bench/free_surface_level.py --res {args.res} --seconds {args.seconds:g}, {time.strftime('%Y-%m-%d %H:%M')}, "
             f"{args.threads} thread(s), {time.time() - t0:.0f} s: a still pool's pressure zero H_p against its "
             f"volume's level H_V in cells, by where the surface lies between node rows (phase: cells above one)",
             "  ".join(f"{h:>26}" for h in head)]
    lines += ["  ".join(f"{c:>26}" for c in r) for r in rows]
    append_table(Path(__file__).resolve().parent / "results" / "free_surface_level_cpu.txt", lines)


if __name__ == "__main__":
    main()
