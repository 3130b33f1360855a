"""The liquid's numerical dissipation, measured (issue: physics fidelity; docs/engine.md, "Open problems").

    python bench/numerical_dissipation.py [--quick]

Writes bench/results/numerical_dissipation_cpu.txt. Three measurements, each at several resolutions:

1. Inviscid decay of the cellular (Taylor–Green) vortex ψ = (U/k) sin(kx) sin(kz), k = π/L, L = 10 cm, between
   free-slip walls, in water without viscosity: Navier–Stokes says it keeps its amplitude, so the fitted
   decay rate r (1/s, over 50 ms) is the scheme's own dissipation, and ν_num = r/(2k²) the kinematic viscosity
   it amounts to (water: 1e-6 m²/s). The observed order of convergence is p = ln(r₁/r₂)/ln(Δx₁/Δx₂). At one
   resolution it is also measured with three times the substeps (more transfers, same sound speed) and
   with a tenth of the bulk modulus (sound speed /√10, a third of the substeps): which of the two the
   dissipation follows says whether it is the transfers themselves or the liquid's sound waves.
2. The viscous excess: the same vortex with η = 5 Pa·s; its decay rate minus the inviscid one, over 2νk²,
   over 10 ms and over 100 ms. Navier–Stokes: 1.
3. A submerged light body: a 4 cm rigid cube of 500 kg/m³ starting at rest 3 cm above the floor of 9 cm of
   water in a 12 cm tank; its rise over 0.15 s. Physically it accelerates at a = (ρ_w − ρ_b) V g / (m + m_a),
   about 2–4 m/s² with an added mass m_a between 0.7 and 3 times ρ_w V (free and confined), i.e. it rises
   20–45 mm in 0.15 s; a liquid as viscous as ν_num slows it to a terminal speed instead.
4. The sound ring of a water column released without its hydrostatic pressure: the mid-depth pressure's period
   against 4H/c, its first swing, the decay rate of its swings and its mean against ρ g H.
"""
from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np


def vortex_decay(res: int, duration: float, eta: float = 0.0, bulk_factor: float = 1.0, substep_factor: float = 1.0,
                 every: int = 5):
    """(decay rate 1/s, substeps per 1 ms step, k) of the cellular vortex (fluidlab_core/apps/vortex.py) in water of
    viscosity eta (Pa·s) and bulk modulus × bulk_factor, at the stable substeps × substep_factor."""
    from fluidlab_core import materials as M
    from fluidlab_core.apps import vortex

    bulk = M.WATER.bulk_modulus * bulk_factor
    liquid = (M.ViscousLiquid(f"viscous_{eta:g}", density=1000.0, bulk_modulus=bulk, viscosity_pas=eta) if eta > 0
              else M.NewtonianLiquid("water_inviscid", density=1000.0, bulk_modulus=bulk))
    rate, k, substeps = vortex.decay_rate(liquid, res=res, duration=duration, every=every,
                                          substep_factor=substep_factor)
    return rate, substeps, k


def cube_rise(res: int, seconds: float = 0.15, flip: float = 0.0, jbar: bool = False):
    """(rise of a submerged 500 kg/m³ rigid cube after `seconds`, m; substeps); flip, jbar: the Scene's AFLIP share
    and J-bar."""
    import fluidlab_core as fl
    from fluidlab_core import materials as M
    from fluidlab_core.shapes import Box

    width, b, bottom, level = 0.12, 0.04, 0.03, 0.09
    scene = fl.Scene(lower=(0, 0, 0), upper=(width, width, 0.12), grid_res=res, dt=2e-3, substeps=1, flip=flip,
                     jbar=jbar)
    lo, hi, top = width / 2 - b / 2, width / 2 + b / 2, bottom + b
    for box in [((0, 0, 0), (width, width, bottom)), ((0, 0, bottom), (lo, width, top)),
                ((hi, 0, bottom), (width, width, top)), ((lo, 0, bottom), (hi, lo, top)),
                ((lo, hi, bottom), (hi, width, top)), ((0, 0, top), (width, width, level))]:
        scene.add_particles(Box(*box), M.WATER)
    scene.add_particles(Box((lo, lo, bottom), (hi, hi, top)), M.Rigid("light_rigid", density=500.0), name="cube")
    scene.substeps = scene.stable_substeps()
    sim = scene.build()
    z0 = sim.positions("cube")[:, 2].mean()
    sim.step(n=int(round(seconds / scene.dt)))
    return sim.positions("cube")[:, 2].mean() - z0, scene.substeps


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer resolutions (a smoke run)")
    args = ap.parse_args()
    import fluidlab_core as fl

    from fluidlab_core.apps import validation

    fl.init("cpu")
    t_start = time.time()
    lines = ["The liquid's numerical dissipation (bench/numerical_dissipation.py), float32 CPU; water: ρ = 1000 kg/m³, "
             "λ = 2.78e5 Pa (c = 16.7 m/s)."]

    def out(line=""):
        print(line, flush=True)
        lines.append(line)

    out("")
    out("1. Inviscid cellular vortex, L = 10 cm, U = 0.1 m/s, decay rate over 50 ms (Navier–Stokes: 0)")
    out(f"{'cells/L':>8} {'dx mm':>6} {'substeps':>8} {'variant':>18} {'rate 1/s':>9} {'nu_num m2/s':>12} {'order':>6}")
    resolutions = (16, 24) if args.quick else (16, 24, 32, 48)
    prev = None
    for res in resolutions:
        rate, sub, k = vortex_decay(res, 0.05)
        order = "" if prev is None else f"{math.log(prev[1] / rate) / math.log(res / prev[0]):6.2f}"
        out(f"{res:>8} {100 / res:>6.2f} {sub:>8} {'as built':>18} {rate:>9.2f} {rate / (2 * k * k):>12.2e} {order:>6}")
        prev = (res, rate)
    for label, kw in (("substeps x3", dict(substep_factor=3.0)), ("bulk modulus /10", dict(bulk_factor=0.1))):
        rate, sub, k = vortex_decay(24, 0.05, **kw)
        out(f"{24:>8} {100 / 24:>6.2f} {sub:>8} {label:>18} {rate:>9.2f} {rate / (2 * k * k):>12.2e}")

    out("")
    out("2. Viscous excess: (rate(η = 5 Pa·s) − rate(inviscid)) / 2νk², Navier–Stokes: 1")
    out(f"{'cells/L':>8} {'window':>7} {'2nu k^2':>8} {'viscous':>8} {'inviscid':>9} {'ratio':>6}")
    for res in ((24,) if args.quick else (24, 48)):
        for window in (0.01, 0.1):
            every = 1 if window <= 0.01 else 5
            r_v, _, k = vortex_decay(res, window, eta=5.0, every=every)
            r_0, _, _ = vortex_decay(res, window, every=every)
            expected = 2 * 5.0 / 1000.0 * k * k
            out(f"{res:>8} {window * 1e3:>5.0f}ms {expected:>8.2f} {r_v:>8.2f} {r_0:>9.2f} {(r_v - r_0) / expected:>6.2f}")

    out("")
    out("3. Submerged 4 cm rigid cube, 500 kg/m³, 12 cm tank, 9 cm water: rise after 0.15 s (physics: 20–45 mm)")
    out(f"{'cells':>6} {'dx mm':>6} {'substeps':>8} {'rise mm':>8}")
    for res in ((16, 24) if args.quick else (16, 24, 32)):
        rise, sub = cube_rise(res)
        out(f"{res:>6} {120 / res:>6.2f} {sub:>8} {rise * 1e3:>8.2f}")
    out("")
    out("4. Sound ring: a 6 cm water column (12 cm tank, slab) released without its hydrostatic pressure; "
        "pressure at mid-depth")
    c = math.sqrt(2.7778e5 / 1000.0)
    out(f"{'cells':>6} {'period ms':>9} {'4H/c ms':>8} {'first swing Pa':>14} {'decay 1/s':>9} {'mean/hydro':>10}")
    for res in ((24,) if args.quick else (24, 48)):
        ring = validation.sound_ring(res)
        period, amp, rate, mean = (ring[k] for k in ("period", "first_swing", "decay_rate", "mean_over_hydro"))
        out(f"{res:>6} {period * 1e3:>9.1f} {4 * 0.06 / c * 1e3:>8.1f} {amp:>14.0f} {rate:>9.2f} {mean:>10.3f}")
    out("")
    out(f"total {time.time() - t_start:.0f} s")
    if not args.quick:
        path = Path(__file__).resolve().parent / "results" / "numerical_dissipation_cpu.txt"
        path.write_text("\n".join(lines) + "\n")
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
