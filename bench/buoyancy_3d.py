"""Buoyancy in 3-D (the open problem of floating bodies, docs/engine.md): a 4 cm cube of 500 kg/m³ in 6 cm of
water in a closed 12 cm box (the domain's walls), 24 cells across; the share of the cube below the far-field
surface every 0.1 s. Archimedes: ρ/ρ_w (0.50 by default, 0.40 for the foam).

    python bench/buoyancy_3d.py BODY LIQUID SECONDS [--res 24] [--drop M] [--raise M] [--every S]
        [--substep-factor F] [--bulk-factor F] [--body-bulk-factor F] [--width M] [--density KG_M3]
        [--contact-fill F] [--jbar [affine]] [--flip A] [--pressure projection] [--open-min S] [--theta-min T] [--no-save]

BODY: rigid | elastic | foam (the tasks' floating foam, 400 kg/m³, E = 4.75 kPa). LIQUID: std (the catalogue's
water) | task (the tasks' water, sound speed 4 m/s) | nt (the same water without tension: p = max(0,
−λ(J − 1)), J ≤ 1, a model registered here, as a user would). --drop M: the cube starts M above the flat
surface (dropped); otherwise at Archimedes' depth (water filled around it), or --raise M above it.
--substep-factor and --bulk-factor scale the stable substep count and the water's bulk modulus (the knobs
that separate the transfers' dissipation from the sound waves', docs/engine.md); --body-bulk-factor scales the
rigid body's bulk modulus, whose sound speed otherwise sets the substep count when the water's is lowered.
--jbar [affine] and --flip A: the Scene's J-bar (plain or affine) and AFLIP share (engine/transfer.py).
--pressure projection: the liquid's pressure by a projection solved with the body's motion (engine/projection.py;
the substep count then comes from the flow's CFL); --theta-min T: its THETA_MIN (the ghost fluid's least θ; default
0.1), set before the build; --open-min S: its OPEN_MIN (a shell node whose faces are open by
less than S in all is the body's; default 0.5), set before the build.
Columns: the cube's lowest face below the far-field surface over its side (depth / b), and the share of its
particles below that surface (share), both against the 99th percentile of the far field's particle heights
(`surface mm`, validation.submerged); the cube's centre height (`cube z mm`); and the share of the cube's volume
below the surface that the liquid's volume Σ V⁰ J fills the tank to (`vol share`, `vol surf mm`,
validation.submerged_by_volume), which a rough surface does not read high (the percentile sat 1.2–2.6 mm above
it in the catalogue's water in the runs of 2026-11-29, 0.03–0.07 of the side; −0.6 to +1.1 mm in the tasks'
water). The header gives the cube's volume over its rest volume (Σ V⁰ det F / Σ V⁰, least and most over the rows):
a body that the pressure compresses displaces less, and floats deeper by that ratio. The particle `share` moves in
steps of one particle layer (1/11 of the side at 16 cells); `vol share` does not. The header says whether the engine
had one velocity field or two
(engine/grid.py; an engine from before the two fields has one). Appends its table to
bench/results/buoyancy_3d.txt unless --no-save.
"""
from __future__ import annotations

import argparse
import inspect
import time
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("body", choices=["rigid", "elastic", "foam"])
    ap.add_argument("liquid", choices=["std", "nt", "task"])
    ap.add_argument("seconds", type=float)
    ap.add_argument("--res", type=int, default=24)
    ap.add_argument("--drop", type=float, default=None)
    ap.add_argument("--raise", dest="lift", type=float, default=0.0)
    ap.add_argument("--substep-factor", type=float, default=1.0, help="substeps × this (over the stable count)")
    ap.add_argument("--bulk-factor", type=float, default=1.0, help="the water's bulk modulus × this")
    ap.add_argument("--body-bulk-factor", type=float, default=1.0, help="the rigid body's bulk modulus × this")
    ap.add_argument("--width", type=float, default=0.12, help="tank width (m)")
    ap.add_argument("--density", type=float, default=500.0, help="the cube's density (kg/m³)")
    ap.add_argument("--every", type=float, default=0.1, help="print every this many seconds")
    ap.add_argument("--contact-fill", type=float, default=0.97, help="Scene(contact_fill=...), engine/grid.py")
    ap.add_argument("--jbar", nargs="?", const="on", choices=["on", "affine"],
                    help="Scene(jbar=True) (or jbar='affine' with --jbar affine), engine/transfer.py")
    ap.add_argument("--flip", type=float, default=None, help="Scene(flip=...), AFLIP, engine/transfer.py")
    ap.add_argument("--pressure", choices=["state", "projection"], default="state",
                    help="Scene(pressure=...): the liquid's equation of state or the projection with the body "
                         "(engine/projection.py)")
    ap.add_argument("--elastic-mu", type=float, default=1e5,
                    help="the elastic body's shear modulus (Pa; its λ is 2.8 μ, a Poisson ratio of 0.37)")
    ap.add_argument("--open-min", type=float, default=None,
                    help="engine/projection.py's OPEN_MIN for this run (default: the engine's)")
    ap.add_argument("--theta-min", type=float, default=None,
                    help="engine/projection.py's THETA_MIN for this run (default: the engine's, 0.1)")
    ap.add_argument("--no-save", action="store_true")
    args = ap.parse_args()
    import taichi as ti

    import fluidlab_core as fl
    from fluidlab_core import materials as M
    from fluidlab_core.apps import validation
    from fluidlab_core.engine import constitutive

    @constitutive.register("liquid_no_tension", params=("lam",), needs_svd=False, fluid=True)
    @ti.func
    def liquid_no_tension(F, C, prm, U, sig, V):
        J = ti.min(F.determinant(), 1.0)
        return (ti.Matrix.identity(float, 3) * ti.pow(ti.max(J, 1e-6), 1.0 / 3.0),
                ti.Matrix.identity(float, 3) * (prm.lam * J * (J - 1.0)))

    @dataclass(frozen=True)
    class NoTensionLiquid(M.NewtonianLiquid):
        model: ClassVar[str] = "liquid_no_tension"

    fl.init("cpu")
    width, level, b, rho = args.width, 0.06, 0.04, args.density
    from fluidlab_core.tasks import common
    if args.body == "foam":
        rho = common.FLOAT_FOAM.density
    if args.liquid == "task":
        water = M.NewtonianLiquid("water_task", density=common.WATER.density,
                                  bulk_modulus=common.WATER.bulk_modulus * args.bulk_factor)
    else:
        cls = M.NewtonianLiquid if args.liquid == "std" else NoTensionLiquid
        water = cls(f"water_{args.liquid}", density=M.WATER.density,
                    bulk_modulus=M.WATER.bulk_modulus * args.bulk_factor)
    kw = {"contact_fill": args.contact_fill} if "contact_fill" in inspect.signature(fl.Scene).parameters else {}
    if args.jbar:
        kw["jbar"] = True if args.jbar == "on" else "affine"
    if args.flip is not None:
        kw["flip"] = args.flip
    if args.pressure != "state":
        kw["pressure"] = args.pressure
    rigid_bulk = M.RIGID.bulk_modulus * args.body_bulk_factor
    body = M.Rigid("light_rigid", density=rho, bulk_modulus=rigid_bulk) if args.body == "rigid" else \
        common.FLOAT_FOAM if args.body == "foam" else \
        M.Elastic("light_elastic", density=rho, shear_modulus=args.elastic_mu, lame_lambda=2.8 * args.elastic_mu)
    if args.theta_min is not None:  # the ghost fluid's clamp, read when the projection's kernels compile
        if args.pressure != "projection":
            raise SystemExit("--theta-min is the projection's (--pressure projection)")
        from fluidlab_core.engine import projection
        projection.THETA_MIN = args.theta_min
    # the scene of the physics test's floating cube (apps/validation.py), here with the bench's options
    sim, scene = validation.floating_cube_sim(args.res, body, water, drop=args.drop, width=width, level=level,
                                              side=b, lift=args.lift, substep_factor=args.substep_factor, **kw)
    if args.open_min is not None:  # the shell-node rule's threshold, read when the projection's kernels compile
        if args.pressure != "projection":
            raise SystemExit("--open-min is the projection's (--pressure projection)")
        sim.solver.proj.open_min = args.open_min
    c = width / 2
    dx, s = width / args.res, scene.particle_spacing
    t0, rows, series = time.time(), [], []
    rest_volume, volume_ratios = float(sim.volumes("cube").sum()), []  # the cube starts undeformed (F = I)
    while sim.time < args.seconds - 1e-9:
        sim.step(n=int(round(args.every / scene.dt)))
        xc = sim.positions("cube")
        vshare, vsurface, x_water = validation.cube_volume_share(sim, width)
        volume_ratios.append(float(sim.volumes("cube").sum()) / rest_volume)
        depth, share, surface = validation.submerged(x_water, xc, (c, c), b, dx, s)
        series.append((sim.time, depth, share, vshare))
        rows.append(f"{sim.time:>5.1f} {depth:>9.3f} {share:>9.3f} {surface * 1e3:>10.1f} {xc[:, 2].mean() * 1e3:>10.1f}"
                    f" {vshare:>9.3f} {vsurface * 1e3:>10.1f}")
        print(rows[-1], f"({time.time() - t0:.0f} s)", flush=True)  # progress
    start = f"dropped from {args.drop * 1e3:g} mm" if args.drop is not None else \
        f"at Archimedes' depth + {args.lift * 1e3:g} mm"
    fields = f"two velocity fields (contact_fill {sim.model.contact_fill:g})" \
        if getattr(sim.model, "two_fields", False) else "one velocity field"
    fields += "".join(f", {k} {kw[k]}" for k in ("jbar", "flip", "pressure") if k in kw)
    if args.open_min is not None:
        fields += f", OPEN_MIN {args.open_min:g}"
    if args.theta_min is not None:
        fields += f", THETA_MIN {args.theta_min:g}"
    what = f"{args.body} cube" + (f" (μ {args.elastic_mu:g} Pa)" if args.body == "elastic" else "")
    text = "\n".join([f"{what} of {rho:g} kg/m³ (λ × {args.body_bulk_factor:g}) in {args.liquid} water "
                      f"(λ × {args.bulk_factor:g}), {fields}, "
                      f"{width * 100:g} cm tank, {args.res} cells, {start}: {len(sim.positions())} "
                      f"particles, {scene.substeps} substeps, {time.time() - t0:.0f} s; the cube's volume over its rest "
                      f"volume {min(volume_ratios):.4f}-{max(volume_ratios):.4f}",
                      f"{'t s':>5} {'depth / b':>9} {'share':>9} {'surface mm':>10} {'cube z mm':>10} {'vol share':>9}"
                      f" {'vol surf mm':>10}", *rows,
                      *per_second(series, rho / M.WATER.density)]) + "\n"
    print(text, flush=True)
    if args.no_save:
        return
    with open(Path(__file__).resolve().parent / "results" / "buoyancy_3d.txt", "a") as f:
        f.write(text + "\n")


def per_second(series, expected):
    """Means of depth / b and share over each whole simulated second (t in (k, k + 1]), against Archimedes."""
    t, depth, share, vshare = (np.array(c) for c in zip(*series))
    out = [f"means over each second (Archimedes {expected:.2f}):"]
    for k in range(int(np.floor(t.max() + 1e-9))):
        m = (t > k + 1e-9) & (t <= k + 1 + 1e-9)
        out.append(f"  {k:>2}-{k + 1:<2} s  depth / b {depth[m].mean():.3f}  share {share[m].mean():.3f}"
                   f"  vol share {vshare[m].mean():.3f}")
    return out


if __name__ == "__main__":
    main()
