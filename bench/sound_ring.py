"""The sound ring of the weakly compressible liquid, and what a bulk viscosity does to it (issue: physics fidelity).

    python bench/sound_ring.py [--zeta 0 5 20 50] [--res 24]

Writes bench/results/sound_ring_cpu.txt. For each bulk viscosity ζ (Pa·s; 0 is the catalogue's water, otherwise
materials.DampedLiquid with water's density and bulk modulus):
- the ring: a 6 cm water column in a 12 cm slab tank released without its hydrostatic pressure
  (apps/validation.py's sound_ring): the mid-depth pressure's period against 4H/c, its first swing, the decay
  rate of its swings, against the viscous theory ζk²/(2ρ) for the quarter wave k = π/2H (plus what the scheme
  damps by itself, the ζ = 0 row), and the mean pressure against ρgH/2;
- what it must leave alone: the inviscid cellular vortex's decay over 50 ms (apps/vortex.py, divergence-free:
  ζ should not touch it); the dam break's front at T = 2.5 and its ratio to Martin & Moyce (apps/validation.py,
  32 cells, a free-surface flow); water at rest (16 cells, 1 s): hydrostatic slope, volume error and the spread
  of the free surface's top layer (a smeared surface spreads).
Every run uses the stable substep count (a bulk viscosity lowers the explicit limit ρΔx²/(6ζ)); the table shows it.
"""
from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np


def liquid_with(zeta: float):
    from fluidlab_core import materials as M

    if zeta <= 0:
        return M.WATER
    return M.DampedLiquid(f"water_zeta_{zeta:g}", density=M.WATER.density, bulk_modulus=M.WATER.bulk_modulus,
                          bulk_viscosity_pas=zeta)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--zeta", type=float, nargs="+", default=[0.0, 5.0, 20.0, 50.0], help="bulk viscosities (Pa·s)")
    ap.add_argument("--res", type=int, default=24, help="cells across the 12 cm tank for the ring")
    ap.add_argument("--no-save", action="store_true")
    args = ap.parse_args()
    import fluidlab_core as fl
    from fluidlab_core import materials as M
    from fluidlab_core.apps import validation, vortex

    fl.init("cpu")
    t_start = time.time()
    depth = 0.06
    c = math.sqrt(M.WATER.bulk_modulus / M.WATER.density)
    k = math.pi / (2 * depth)
    dx = 0.12 / args.res
    lines = [f"Sound ring and bulk viscosity (bench/sound_ring.py), float32 CPU; water ρ = 1000 kg/m³, c = {c:.1f} m/s; "
             f"ring: 6 cm column, {args.res} cells over 12 cm (ρcΔx = {M.WATER.density * c * dx:.0f} Pa·s)",
             "", f"{'zeta Pa s':>9} {'subst':>5} {'period ms':>9} {'4H/c ms':>7} {'swing Pa':>8} {'decay 1/s':>9} "
             f"{'theory':>7} {'mean/hyd':>8} | {'vortex 1/s':>10} | {'dam Z(2.5)':>10} {'ratio':>11} | "
             f"{'slope':>6} {'vol err':>8} {'surf mm':>7}"]
    print(lines[0], "\n", lines[-1], flush=True)
    base_rate = None
    for zeta in args.zeta:
        liquid = liquid_with(zeta)
        ring = validation.sound_ring(args.res, depth=depth, liquid=liquid)
        sub, period, amp, rate, mean = (ring[k] for k in ("substeps", "period", "first_swing", "decay_rate",
                                                          "mean_over_hydro"))
        if base_rate is None:
            base_rate = rate
        theory = zeta * k * k / (2 * M.WATER.density) + (base_rate if zeta > 0 else 0.0)
        v_rate, _, _ = vortex.decay_rate(liquid, res=24, duration=0.05, every=5)
        dam = validation.dam_break(res=32, substeps=None, liquid=liquid)
        z25 = float(np.interp(2.5, dam["times"], dam["fronts"]))
        rest = validation.water_column(res=16, steps=500, average=100, substeps=None, liquid=liquid)
        line = (f"{zeta:>9g} {sub:>5} {period * 1e3:>9.1f} {4 * depth / c * 1e3:>7.1f} {amp:>8.0f} {rate:>9.2f} "
                f"{theory:>7.2f} {mean:>8.3f} | {v_rate:>10.2f} | {z25:>10.3f} "
                f"{dam['ratio'].min():>5.3f}-{dam['ratio'].max():<5.3f} | {rest['slope_ratio']:>6.3f} "
                f"{rest['worst_volume_error']:>8.1e} {rest['surface_spread'] * 1e3:>7.2f}")
        lines.append(line)
        print(line, flush=True)
    lines += ["", "theory: ζ k²/(2ρ), k = π/(2H), plus the ζ = 0 row's decay; vortex: inviscid cellular vortex, 24 cells, "
              "50 ms (0 in Navier–Stokes); dam: 32 cells; slope, vol err, surf: water at rest, 16 cells, 1 s (slope over "
              "ρg, worst volume error, std of the top layer's heights)", f"total {time.time() - t_start:.0f} s"]
    text = "\n".join(lines) + "\n"
    print(text, flush=True)
    if not args.no_save:
        (Path(__file__).resolve().parent / "results" / "sound_ring_cpu.txt").write_text(text)


if __name__ == "__main__":
    main()
