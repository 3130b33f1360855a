"""Where the cellular vortex loses its amplitude: the domain walls (issue: physics fidelity; docs/engine.md).

    python bench/vortex_walls.py [--res 24] [--eta 0 5] [--ms 40]

The vortex of fluidlab_core/apps/vortex.py (L = 10 cm, U = 0.1 m/s, free-slip domain walls, float32) is run and,
every 5 ms, the particle velocities are projected onto the mode (amplitude a, over exp(−2νk²t)) as a whole and
within bands by distance to the nearest x or z wall (0–1, 1–2, 2–4, 4–8 and over 8 cells). If the scheme
dissipated the vortex evenly, every band would keep the same amplitude; a band whose local amplitude falls
below the others is where the loss is. The residual (velocity not in the mode, rms over a) says how far the
flow has left the mode's shape.

Appends its table to bench/results/vortex_walls_cpu.txt.
"""
import argparse
import math
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

BANDS = [(0, 1), (1, 2), (2, 4), (4, 8), (8, 1e9)]


def on_walls(sim) -> bool:
    """Whether the grid has a row of nodes on the lower walls (origin a whole number of cells below them)."""
    offset = (np.asarray(sim.model.lower) - np.asarray(sim.model.origin)) / sim.model.dx
    return bool(np.allclose(offset, np.round(offset), atol=1e-3))


def run(res: int, eta: float, ms: float, log) -> None:
    from fluidlab_core import materials as M
    from fluidlab_core.apps.vortex import mode_shape, vortex_simulator

    size, amplitude = 0.1, 0.1
    liquid = (M.ViscousLiquid(f"viscous_{eta:g}", density=1000.0, viscosity_pas=eta) if eta > 0
              else M.NewtonianLiquid("water_inviscid", density=1000.0, bulk_modulus=M.WATER.bulk_modulus))
    dx = size / res
    sim, k = vortex_simulator(liquid, res, size, amplitude)
    nu = eta / 1000.0
    log(f"\nres {res} cells per L, eta {eta:g} Pa·s (2νk² = {2 * nu * k * k:.2f} /s), {sim.model.substeps} substeps "
        f"per 1 ms, {sim.n_particles} particles, {time.strftime('%Y-%m-%d')}, "
        f"{'nodes on the walls' if on_walls(sim) else 'nodes half a cell inside the walls'}")
    log(" t ms  a/exp(-2νk²t)  residual/a   local a / a in bands by distance to the wall (cells): "
        + " ".join(f"{lo:g}-{hi:g}" if hi < 1e8 else f"{lo:g}+" for lo, hi in BANDS))
    while sim.time <= ms * 1e-3 + 1e-9:
        x = sim.positions("liquid").astype(np.float64)
        v = sim.velocities("liquid").astype(np.float64)
        shape, _ = mode_shape(x, k)
        a = float((v * shape).sum() / (shape * shape).sum())
        resid = v - a * shape
        wall = np.minimum(np.minimum(x[:, 0], size - x[:, 0]), np.minimum(x[:, 2], size - x[:, 2])) / dx
        local = []
        for lo, hi in BANDS:
            m = (wall >= lo) & (wall < hi)
            local.append(float((v[m] * shape[m]).sum() / (shape[m] * shape[m]).sum()) / a)
        log(f"{sim.time * 1e3:5.0f} {a / (amplitude * math.exp(-2 * nu * k * k * sim.time)):14.3f} "
            f"{math.sqrt((resid ** 2).sum(1).mean()) / a:11.3f}   " + " ".join(f"{x:7.3f}" for x in local))
        sim.step(n=5)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=24, help="cells across the 10 cm vortex")
    ap.add_argument("--eta", type=float, nargs="+", default=[0.0, 5.0], help="viscosities (Pa·s)")
    ap.add_argument("--ms", type=float, default=40.0, help="simulated milliseconds")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    import fluidlab_core as fl

    fl.init(arch="cpu", precision="f32")
    lines = []

    def log(line):
        print(line, flush=True)
        lines.append(line)
    for eta in args.eta:
        run(args.res, eta, args.ms, log)
    out = args.out or os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "vortex_walls_cpu.txt")
    with open(out, "a") as f:
        f.write("\n".join(lines) + "\n")
    print(f"appended to {out}", file=sys.stderr)


if __name__ == "__main__":
    main()
