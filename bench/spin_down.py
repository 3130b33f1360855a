"""A submerged cube's spin in an ideal liquid: how much of it each coupling keeps (issue 19: floating bodies).

Why: a floating cube of density ratio 0.4 is unstable upright (bench/cube_roll.py, the metacentric criterion) and on
the projection it rolls over within 0.2-0.3 s, but on the tasks' default liquid it creeps from 5 to 9 degrees in a
second, at about the same rate from 15 degrees as from 5. A creep whose rate barely depends on the driving torque
is what a strong rotational damper gives: the body turns at the rate ω = M / c where the torque M balances the
damping c ω. This script measures c directly, with no gravity and no free surface.

Physics. A rigid cube of side a spinning at ω₀ about a horizontal axis, started at once in a liquid at rest, gives
the liquid its potential flow in the first instant (an inviscid liquid takes the impulse at once); the body keeps
ω₁ = ω₀ I_b / (I_b + I_a), with I_a the liquid's added moment of inertia for the rotation, and from then on an
inviscid liquid exerts no torque on a body turning steadily (the kinetic energy ½ (I_b + I_a) ω² is conserved;
Lamb, Hydrodynamics, ch. VI, on the motion of a solid through a liquid). So after the start ω stays at ω₁: what
it loses later is the coupling's (or the transfer's) dissipation. With a constant damping c alone, ω would decay as
e^(−t/τ), τ = (I_b + I_a) / c; a no-slip surface whose angular momentum spreads into the liquid by a viscosity
gives a decay that slows as a power of t instead (here about 1/t; docs/engine.md, "A floating cube's roll").

Set-up: a 4 cm rigid cube of 400 kg/m³ (the Gathering foam's density) centred in a closed 12 cm box filled with
the tasks' water to 11 cm (the cube 3 cm under the surface, 4 cm over the floor), gravity off, the water at rest,
the cube spinning at --omega rad/s about y. Each row: ω_y of the cube (the least-squares rigid rotation of its
particles' velocities) at the listed times, the cube started with the rigid motion's velocities and APIC's
C = [ω]× (validation._set_rigid_motion). "air" is the cube alone, which keeps its spin.

    python bench/spin_down.py [--res 16 24 32] [--pressures state projection] [--omega 5]
        [--water task|std] [--substep-factor F] [--flip A] [--air] [--out bench/results/spin_down.txt]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from cube_roll import WATERS, add_liquid_options, liquid_of  # bench/cube_roll.py (this script's folder)
from results_file import append_table  # bench/results_file.py (this script's folder is on the path)

ROOT = Path(__file__).resolve().parents[1]
WIDTH, HEIGHT, FILL, SIDE = 0.12, 0.12, 0.11, 0.04  # m: the box, the water's depth, the cube's side
DENSITY = 400.0  # kg/m³


def spin_rate(x: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The angular velocity (rad/s) of the rigid rotation that best fits velocities v at positions x (equal
    masses): ω = I⁻¹ Σ r × (v − v̄), I = Σ (|r|² 1 − r rᵀ), r = x − x̄."""
    x = np.asarray(x, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    r = x - x.mean(axis=0)
    L = np.cross(r, v - v.mean(axis=0)).sum(axis=0)
    inertia = np.eye(3) * (r ** 2).sum() - r.T @ r
    return np.linalg.solve(inertia, L)


def run(pressure: str, res: int, omega: float, times: list[float], water: str = "task", liquid_on: bool = True,
        substep_factor: float = 1.0, flip: float | None = None):
    """(ω_y at each of `times`, wall seconds of the stepping, substeps per 2 ms step) of the spinning cube."""
    import fluidlab_core as fl
    from fluidlab_core import materials as M
    from fluidlab_core.apps import validation
    from fluidlab_core.shapes import Box
    from fluidlab_core.tasks.common import Without

    scene = fl.Scene(lower=(0, 0, 0), upper=(WIDTH, WIDTH, HEIGHT), grid_res=res, dt=2e-3, substeps=1,
                     gravity=(0, 0, 0), pressure=pressure, flip=flip)
    c = WIDTH / 2
    z0 = FILL - 0.03 - SIDE
    cube = Box((c - SIDE / 2, c - SIDE / 2, z0), (c + SIDE / 2, c + SIDE / 2, z0 + SIDE))
    if liquid_on:
        scene.add_particles(Without(Box((0, 0, 0), (WIDTH, WIDTH, FILL)), [cube]), liquid_of(water), name="water")
    scene.add_particles(cube, M.Rigid("spinning", density=DENSITY, bulk_modulus=M.RIGID.bulk_modulus), name="cube")
    validation._substeps(scene, None)
    scene.substeps = max(1, int(round(scene.substeps * substep_factor)))
    sim = scene.build()
    state = sim.get_state()
    validation._set_rigid_motion(state, sim.handle("cube").slice, np.zeros(3), np.array([0.0, omega, 0.0]))
    sim.set_state(state)
    out, t0 = [], time.perf_counter()
    for t in times:
        sim.step(n=int(round((t - sim.time) / scene.dt)))
        out.append(float(spin_rate(sim.positions("cube"), sim.velocities("cube"))[1]))
    wall = time.perf_counter() - t0
    fl.runtime.reset()
    return out, wall, scene.substeps


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--res", nargs="+", type=int, default=[16, 24, 32])
    ap.add_argument("--pressures", nargs="+", default=["state", "projection"], choices=["projection", "state"])
    ap.add_argument("--omega", type=float, default=5.0, help="the start spin about y (rad/s)")
    ap.add_argument("--substep-factor", type=float, default=1.0,
                    help="the stable substep count times this (more transfers per second)")
    add_liquid_options(ap)
    ap.add_argument("--air", action="store_true", help="also the cube alone (no liquid), per resolution")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "spin_down.txt"))
    args = ap.parse_args(argv)
    import fluidlab_core as fl

    fl.init(arch="cpu")
    times = [0.002, 0.02, 0.05, 0.1, 0.2]
    water = WATERS[args.water]
    lines = [f"# bench/spin_down.py, {time.strftime('%Y-%m-%d %H:%M')}, CPU, float32: a 4 cm rigid cube of "
             f"{DENSITY:g} kg/m³ spinning at {args.omega:g} rad/s about y, 3 cm under {water} in a closed 12 cm box, "
             "no gravity, the water at rest"
             + ("" if args.flip is None else f", flip {args.flip:g}") + ("" if args.substep_factor == 1.0 else
                                                                        f", {args.substep_factor:g}x the substeps"),
             "# an inviscid liquid keeps ω after the start's impulse (ω₁ = ω₀ I_b / (I_b + I_a)): the last column "
             "is ω(0.2 s) / ω(20 ms), 1 for no dissipation",
             "# liquid | cells | ω_y (rad/s) at " + ", ".join(f"{t * 1e3:g}" for t in times)
             + " ms | ω(0.2 s)/ω(20 ms) | substeps per 2 ms | wall s"]
    print("\n".join(lines), flush=True)
    cases = [("air", r) for r in args.res] if args.air else []
    cases += [(p, r) for p in args.pressures for r in args.res]
    for pressure, res in cases:
        omegas, wall, substeps = run("state" if pressure == "air" else pressure, res, args.omega, times,
                                     args.water, liquid_on=pressure != "air", substep_factor=args.substep_factor,
                                     flip=args.flip)
        keep = omegas[-1] / omegas[1] if omegas[1] else float("nan")
        line = (f"{pressure} | {res} | " + ", ".join(f"{w:.3f}" for w in omegas) + f" | {keep:.2f} | {substeps} | {wall:.0f}")
        print(line, flush=True)
        lines.append(line)
    append_table(args.out, lines)


if __name__ == "__main__":
    main()
