"""A still pool on the projection (issue 19; docs/engine.md, "Open problems"): how still it stays, and its surface row.

    python bench/still_pool_projection.py [--res 16] [--level 0.06] [--seconds 2] [--flips 0.99 0.95 0.9 0]
        [--theta-mins 0.1 0.01] [--threads 1] [--out bench/results/still_pool_projection_cpu.txt]

`level` m of the catalogue's water in a closed 12 cm box, `res` cells across, `Scene(pressure="projection")`, the
stable substep count, for each FLIP share (the Scene's `flip`; 0.99 is its default on the projection, 0 is APIC,
which the tasks take) and each THETA_MIN (projection.py: the least share θ of the way from a liquid node to an air
node at which the ghost-fluid boundary puts p = 0). Every 0.5 s:
- rms speed: the particles' root-mean-square speed (m/s); the pool is still, so this is the scheme's noise;
- top rows: the rows (node indices) that hold the highest liquid unknown of a column. Where the surface lies near a
  node row, its nodes' fills straddle FILL = ½ and the row is a mixture of liquid and air nodes;
- top p std: the spread of the pressure over those highest unknowns (Pa); parity: the mean of the columns with
  i + j even less the odd ones' (Pa; a checkerboard in the plane would show here);
- p − ρgh: the mean pressure's excess over ρ_w g (level − z) in the 1st, 2nd and 3rd rows below the lowest top row
  (Pa; ρ_w g Δx is 73.6 Pa at 16 cells).
Appends its table to the output file.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from results_file import append_table  # bench/results_file.py (this script's folder is on the path)


def run(res: int, level: float, seconds: float, flip: float, theta_min: float, every: float = 0.5):
    import fluidlab_core as fl
    from fluidlab_core import materials as M
    from fluidlab_core.engine import projection
    from fluidlab_core.shapes import Box

    fl.runtime.reset()
    projection.THETA_MIN = theta_min  # read when the kernels compile
    width = 0.12
    scene = fl.Scene(lower=(0, 0, 0), upper=(width, width, 0.12), grid_res=res, dt=2e-3, substeps=1,
                     pressure="projection", flip=flip)
    scene.add_particles(Box((0, 0, 0), (width, width, level)), M.WATER, name="water")
    scene.substeps = scene.stable_substeps()
    sim = scene.build()
    rows = []
    n = int(round(every / scene.dt))
    while sim.time < seconds - 1e-9:
        sim.step(n=n)
        proj, model = sim.solver.proj, sim.solver.model
        kind, p = proj.kind.to_numpy(), proj.p.to_numpy()
        liquid = kind == projection.LIQ
        top = np.full(kind.shape[:2], -1)
        for k in range(kind.shape[2]):
            top[liquid[:, :, k]] = k
        i, j = np.nonzero(top >= 0)
        p_top = p[i, j, top[i, j]]
        even = (i + j) % 2 == 0
        z = model.origin[2] + np.arange(kind.shape[2]) * model.dx
        lowest = int(top[top >= 0].min())
        excess = [float(p[:, :, lowest - d][liquid[:, :, lowest - d]].mean()
                        - M.WATER.density * 9.81 * (level - z[lowest - d])) for d in (1, 2, 3)]
        v = sim.velocities("water")
        rows.append({"t": sim.time, "rms": float(np.sqrt((v ** 2).sum(axis=1).mean())),
                     "top_rows": sorted(int(k) for k in np.unique(top[top >= 0])), "p_std": float(p_top.std()),
                     "parity": float(p_top[even].mean() - p_top[~even].mean()), "excess": excess})
    return rows, scene.substeps


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--res", type=int, default=16)
    ap.add_argument("--level", type=float, default=0.06, help="water depth (m)")
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--flips", type=float, nargs="+", default=[0.99, 0.95, 0.9, 0.0])
    ap.add_argument("--theta-mins", type=float, nargs="+", default=[0.1, 0.01])
    ap.add_argument("--threads", type=int, default=1, help="Taichi CPU threads")
    ap.add_argument("--out", default="bench/results/still_pool_projection_cpu.txt")
    args = ap.parse_args(argv)
    import subprocess

    import fluidlab_core as fl

    fl.init(arch="cpu", precision="f32", cpu_threads=args.threads)
    commit = subprocess.run(["git", "describe", "--always", "--dirty"], capture_output=True, text=True).stdout.strip()
    lines = [f"# bench/still_pool_projection.py: {args.level * 1e3:g} mm of water in a closed 12 cm box, {args.res} "
             f"cells, the projection, float32, CPU {args.threads} thread(s); {time.strftime('%Y-%m-%d')}, {commit}",
             "#  flip  θ_min  substeps   t s   rms m/s  top rows   top p std Pa  parity Pa   p − ρgh 1/2/3 rows under Pa"]
    for flip in args.flips:
        for theta_min in args.theta_mins:
            t0 = time.perf_counter()
            rows, substeps = run(args.res, args.level, args.seconds, flip, theta_min)
            for r in rows:
                line = (f"  {flip:5.2f}  {theta_min:5.2f}  {substeps:8d}  {r['t']:5.2f}  {r['rms']:7.4f}  "
                        f"{','.join(map(str, r['top_rows'])):9s}  {r['p_std']:12.2f}  {r['parity']:+9.2f}   "
                        + " / ".join(f"{e:+.2f}" for e in r["excess"]))
                lines.append(line)
                print(line, flush=True)
            print(f"({time.perf_counter() - t0:.0f} s)", flush=True)
    append_table(args.out, lines)


if __name__ == "__main__":
    main()
