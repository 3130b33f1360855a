"""The Magnus effect in the particle engine (the gas issue's MPM demo): a spinning body moving through water.

    python bench/magnus_mpm.py [--quick] [--out bench/results/magnus_mpm.txt]

Three tables.

1. Held (apps/validation.py's `magnus_held`): a rigid body of water's density held at U = 0.2 m/s along x and
spin ω = α U / r about z, as a hand or a tool would hold it, in water of sound speed 4 m/s, no gravity; the
water's force on it, averaged over two periods of the closed tank's sound (0.1–0.26 s). The lift is along ω × U
(+y for α > 0). Reference for the disc: Kutta–Joukowski, L = ρ U Γ × span, Γ = 2π r² ω (inviscid, the water at
the surface moving with it); viscous cylinders at moderate Re reach about 0.4 of it at α = 1 (Mittal & Kumar
2003). Cases: the disc (a slab two cells thick, radius 12 mm) at 32, 64 and 96 cells along the 0.16 m tank; a
ball (radius 15 mm, closed 3-D tank full of water) at 32 cells. Columns: lift (N), lift over Kutta–Joukowski,
lift and drag coefficients over ½ρU² × frontal area.
2. Free across: the same disc held only along x and in spin, free to move across the stream: its sideways
displacement after 0.26 s (mm), the demo's deflection.
3. Thrown (apps/validation.py's `magnus`), the first attempt, kept for the record: a rigid body of water's density started at U = 0.2 m/s along x with spin
ω = α U / r about z, in water of sound speed 4 m/s (Mach 0.05, the tasks' liquids). Magnus: it deflects along
ω × U, i.e. +y for α > 0; not at all for α = 0; more for larger α. A scale for the deflection, the inviscid
upper bound for the disc (Kutta–Joukowski with the fluid co-rotating, Γ = 2π r² ω, over the disc's mass plus
its added mass ρπr²): a_y = U ω, 0.67 mm after 20 ms at α = 1 if U and ω held (they do not: they decay).

Cases of table 3 (each a row):
- disc (quasi-2-D, a slab two cells thick, no gravity, radius 12 mm) at 32, 64 and 96 cells along the 0.16 m
  tank, with the engine's contact test (contact_fill 0.97: the body and the water share a velocity only at
  nodes their particles fill) and at 64 cells with contact_fill 0.05 (they share it wherever both have mass,
  as on a single velocity field);
- ball (3-D, 15 mm radius, at mid-depth under gravity) at 32 cells, contact_fill 0.97.
Columns: the sideways displacement y at 20 and 60 ms (mm; the α = 0 run's subtracted, so that what remains is
the spin's), whether its sign is that of ω × U, the speed and spin kept after 10 ms (v_x/U, ω/ω₀).
--quick: tables 1 and 2 for the 32-cell disc, α = 0 and 1 (about 1 min).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
U = 0.2  # m/s, the throw (validation.magnus's default)
RADIUS = {2: 0.012, 3: 0.015}  # m, the disc's and the ball's


def thrown_cases():
    return [(2, 32, 0.97, (0.0, 1.0, -1.0, 2.0)), (2, 64, 0.97, (0.0, 1.0, -1.0, 2.0)),
            (2, 96, 0.97, (0.0, 1.0, -1.0, 2.0)), (2, 64, 0.05, (0.0, 1.0, -1.0, 2.0)),
            (3, 32, 0.97, (0.0, 1.0, -1.0))]


def held_cases(quick: bool):
    if quick:
        return [(2, 32, (0.0, 1.0))]
    return [(2, 32, (0.0, 1.0, -1.0, 2.0, 0.5)), (2, 64, (0.0, 1.0, -1.0, 2.0, 0.5)), (2, 96, (0.0, 1.0, 2.0)),
            (3, 32, (0.0, 1.0, 2.0))]


def free_cases(quick: bool):
    return [(32, (0.0, 1.0))] if quick else [(32, (0.0, 1.0, -1.0, 2.0)), (64, (0.0, 1.0, 2.0))]


def at(r: dict, t: float, key: str):
    i = int(np.argmin(np.abs(r["times"] - t)))
    return r[key][i]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "magnus_mpm.txt"))
    args = ap.parse_args(argv)
    import fluidlab_core as fl
    from fluidlab_core.apps import validation

    fl.init(arch="cpu")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    lines = ["Magnus effect in the particle engine (bench/magnus_mpm.py), U = 0.2 m/s, spin α U / r about z, water of "
             "sound speed 4 m/s. Expected: lift and deflection along ω × U (+y for α > 0), none without spin, growing with α.",
             "", "1. Held at U and ω: the water's force, mean over 0.1-0.26 s (Kutta-Joukowski for the disc: ρ U 2π r² ω × span).",
             f"{'body':<5} {'cells':>5} {'r/dx':>5} {'alpha':>6} {'lift N':>11} {'lift/KJ':>8} {'C_L':>7} {'C_D':>6} "
             f"{'along wxU':>9} {'run s':>6}"]
    print("\n".join(lines), flush=True)

    def flush():
        out.write_text("\n".join(lines) + "\n")

    for dims, res, alphas in held_cases(args.quick):
        for alpha in alphas:
            t0 = time.perf_counter()
            r = validation.magnus_held(res=res, alpha=alpha, dims=dims, speed=U)
            kj = r["lift"] / r["kutta_joukowski"] if alpha and dims == 2 else float("nan")
            along = "-" if alpha == 0.0 else ("yes" if np.sign(r["lift"]) == np.sign(alpha) else "NO")
            radius = 0.012 if dims == 2 else 0.015
            lines.append(f"{'disc' if dims == 2 else 'ball':<5} {res:>5} {radius / r['dx']:>5.1f} {alpha:>6.1f} "
                         f"{r['lift']:>11.3e} {kj:>8.3f} {r['lift_coefficient']:>7.3f} {r['drag_coefficient']:>6.2f} "
                         f"{along:>9} {time.perf_counter() - t0:>6.0f}")
            print(lines[-1], flush=True)
            flush()
    lines += ["", "2. Held along x and in spin, free across the stream: sideways displacement after 0.26 s.",
              f"{'body':<5} {'cells':>5} {'alpha':>6} {'y 0.1s mm':>10} {'y 0.26s mm':>11} {'along wxU':>9} {'run s':>6}"]
    print("\n".join(lines[-3:]), flush=True)
    for res, alphas in free_cases(args.quick):
        for alpha in alphas:
            t0 = time.perf_counter()
            r = validation.magnus_held(res=res, alpha=alpha, dims=2, speed=U, free_across=True)
            y1, y = at(r, 0.1, "displacement")[1], r["displacement"][-1, 1]
            along = "-" if alpha == 0.0 else ("yes" if np.sign(y) == np.sign(alpha) else "NO")
            lines.append(f"{'disc':<5} {res:>5} {alpha:>6.1f} {1e3 * y1:>10.3f} {1e3 * y:>11.3f} {along:>9} "
                         f"{time.perf_counter() - t0:>6.0f}")
            print(lines[-1], flush=True)
            flush()
    if args.quick:
        print(f"wrote {out}")
        return 0
    lines += ["", "3. Thrown (the first attempt): a rigid body of water's density started at U with spin α U / r and "
              "left free. Expected: y > 0 for α > 0 (along ω × U), growing with α.",
              f"{'body':<5} {'cells':>5} {'r/dx':>5} {'fill':>5} {'alpha':>6} {'y 20ms mm':>10} {'y 60ms mm':>10} "
              f"{'along wxU':>9} {'vx/U 10ms':>9} {'w/w0 10ms':>9} {'run s':>6}"]
    print("\n".join(lines[-3:]), flush=True)
    for dims, res, fill, alphas in thrown_cases():
        base = None
        for alpha in alphas:
            t0 = time.perf_counter()
            radius = RADIUS[dims]
            r = validation.magnus(res=res, alpha=alpha, dims=dims, contact_fill=fill, radius=radius, speed=U)
            y20, y60 = at(r, 0.02, "displacement")[1], at(r, 0.06, "displacement")[1]
            if alpha == 0.0:
                base = (y20, y60)
            else:
                y20, y60 = y20 - base[0], y60 - base[1]
            along = "-" if alpha == 0.0 else ("yes" if np.sign(y60) == np.sign(alpha) else "NO")
            vx = at(r, 0.01, "velocity")[0] / U
            w = at(r, 0.01, "spin") / r["omega"] if r["omega"] else float("nan")
            lines.append(f"{'disc' if dims == 2 else 'ball':<5} {res:>5} {radius / r['dx']:>5.1f} {fill:>5.2f} "
                         f"{alpha:>6.1f} {1e3 * y20:>10.3f} {1e3 * y60:>10.3f} {along:>9} {vx:>9.2f} {w:>9.2f} "
                         f"{time.perf_counter() - t0:>6.0f}")
            print(lines[-1], flush=True)
            flush()
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
