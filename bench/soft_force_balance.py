"""The pressure's force on a floating body against Archimedes (issue 19; docs/engine.md, "Elastic bodies in the
projection"): a 4 cm cube of density D started at Archimedes' depth in 6 cm of water (12 cm tank, the projection),
left to settle, then over [T0, T1] s, sampled every third substep:
- the pressure's vertical force on the body (the solve's Δx² Σ_K G_K over the solids' nodes; a rigid body's ΔP/Δt)
  over its weight, and over ρ_w g V_under, V_under the body's volume below the pressure's own zero level H_p (the
  far field's p(z), fitted in four columns near the tank's corners, extrapolated to p = 0): 1 where the discrete
  force is Archimedes' for where the pressure puts the surface;
- V_under/V (Archimedes ρ/ρ_w);
- for a deformable body, that force by row of node columns (summed along y) against ρ_w g V_under spread to the
  columns by linear weights: where along the body the force falls short.

    python bench/soft_force_balance.py [--res 16] [--density 800] [--body elastic|rigid] [--t0 0.5] [--t1 0.8]
                                       [--tilt DEG]

--tilt DEG turns the cube by DEG about the y axis (45: edge down, how a cube of 0.28-0.72 ρ_w floats) and starts it at
that orientation's Archimedes' depth, the water filled round it. Also printed: the share of the body's volume under
the surface its liquid's volume fills the tank to (validation.cube_volume_share), the buoyancy bench's measure.

Appends its lines to bench/results/soft_force_balance.txt.
"""
from __future__ import annotations

import argparse
import datetime
import os
import subprocess
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

RHO_W, G = 1000.0, 9.81


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--res", type=int, default=16)
    ap.add_argument("--density", type=float, default=800.0)
    ap.add_argument("--body", choices=["elastic", "rigid"], default="elastic")
    ap.add_argument("--t0", type=float, default=0.5)
    ap.add_argument("--t1", type=float, default=0.8)
    ap.add_argument("--tilt", type=float, default=0.0, help="the cube turned by this many degrees about y")
    args = ap.parse_args()
    from fluidlab_core import materials as M
    from fluidlab_core.apps import validation
    from fluidlab_core.engine import projection

    rho, res, rigid = args.density, args.res, args.body == "rigid"
    body = (M.Rigid(f"rigid_{rho:g}", density=rho) if rigid else
            M.Elastic(f"elastic_{rho:g}", density=rho, shear_modulus=5000.0, lame_lambda=14000.0))
    if args.tilt:
        sim, x_start = _tilted_sim(res, body, np.radians(args.tilt))
    else:
        sim, _ = validation.floating_cube_sim(res, body, M.WATER, drop=None, width=0.12, side=0.04,
                                              pressure="projection")
    proj, model = sim.solver.proj, sim.solver.model
    dx, pad = model.dx, int(round(-model.origin[0] / model.dx))
    far = [(pad + 2, pad + 2), (pad + 2, pad + res - 2), (pad + res - 2, pad + 2), (pad + res - 2, pad + res - 2)]
    rows = {"F": [], "V": [], "H": [], "colF": [], "colI": [], "share": []}
    count = [0]
    impulse = proj.body_impulse

    def sampled(state):  # the solve's impulse, then a sample of what it used
        impulse(state)
        count[0] += 1
        if sim.time < args.t0 or count[0] % 3:
            return
        H = validation.pressure_zero(sim, far)
        x = sim.positions("cube")
        under = validation.volumes_below(H, x, sim.volumes("cube"))
        if rigid:
            F = float(proj.body_dP.to_numpy()[2]) / float(model.dt)
        else:
            fmap = (proj.soft_m.to_numpy() * proj.soft_dv.to_numpy()[..., 2]).sum(axis=2) * dx * dx
            F = float(fmap.sum())
            fx, fy = (x[:, 0] - model.origin[0]) / dx, (x[:, 1] - model.origin[1]) / dx
            i0, j0 = np.floor(fx).astype(int), np.floor(fy).astype(int)
            tx, ty = fx - i0, fy - j0
            ideal = np.zeros(fmap.shape)
            for a, wa in ((0, 1 - tx), (1, tx)):
                for b, wb in ((0, 1 - ty), (1, ty)):
                    np.add.at(ideal, (i0 + a, j0 + b), RHO_W * G * under * wa * wb)
            rows["colF"].append(fmap.sum(axis=1))
            rows["colI"].append(ideal.sum(axis=1))
        rows["F"].append(F)
        rows["V"].append(float(under.sum()))
        rows["H"].append(H)
        rows["share"].append(validation.cube_volume_share(sim, 0.12)[0])

    proj.body_impulse = sampled
    while sim.time < args.t1 - 1e-9:
        sim.step(n=25)
    F, V, H = np.array(rows["F"]), np.array(rows["V"]), np.array(rows["H"])
    volume, weight = float(sim.volumes("cube").sum()), float(sim.volumes("cube").sum()) * rho * G
    rev = subprocess.run(["git", "describe", "--always", "--dirty"], capture_output=True, text=True,
                         cwd=os.path.dirname(os.path.abspath(__file__))).stdout.strip()
    lines = [f"# bench/soft_force_balance.py, {datetime.datetime.now():%Y-%m-%d %H:%M}, commit {rev}: {args.body} "
             f"cube of {rho:g} kg/m³ at Archimedes' depth, {res} cells, {len(F)} samples over {args.t0:g}-{args.t1:g} s"
             + f", free surface θ {projection.THETA_RULE}"
             + (f", turned {args.tilt:g}° about y (by {_turned_since(x_start, sim):+.1f}° more at the end)" if args.tilt else ""),
             f"force/weight {F.mean() / weight:.4f}; force/(ρ_w g V_under(H_p)) {F.mean() / (RHO_W * G * V.mean()):.4f}; "
             f"V_under/V {V.mean() / volume:.4f} (Archimedes {rho / RHO_W:.3f}); H_p {H.mean() * 1e3:.2f} mm; "
             f"share under the liquid's volume level {np.mean(rows['share']):.4f}"]
    if rows["colF"]:
        cf, ci = np.mean(rows["colF"], axis=0), np.mean(rows["colI"], axis=0)
        parts = [f"{(model.origin[0] + i * dx) * 1e3:.1f} mm {cf[i] / ci[i]:.3f}" for i in range(len(cf)) if ci[i] > 1e-4]
        lines.append("by row of columns (x; force over ρ_w g V_under there): " + ", ".join(parts))
    text = "\n".join(lines)
    print(text)
    out = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "soft_force_balance.txt")
    with open(out, "a") as f:
        f.write(text + "\n\n")


SIDE, WIDTH, LEVEL = 0.04, 0.12, 0.06


class _TurnedCube:
    """A cube of SIDE centred at `centre`, turned by `angle` (rad) about y: its particles the axis-aligned cube's
    lattice turned (fluidlab_core.shapes duck type: bounds, sdf, sample, cell_volume, volume)."""

    def __init__(self, centre, angle):
        from fluidlab_core.shapes import Box
        self.c, self.box = np.asarray(centre, float), Box(tuple(-SIDE / 2 * np.ones(3)), tuple(SIDE / 2 * np.ones(3)))
        ca, sa = np.cos(angle), np.sin(angle)
        self.R = np.array([[ca, 0.0, sa], [0.0, 1.0, 0.0], [-sa, 0.0, ca]])

    def bounds(self):
        r = SIDE / 2 * np.sqrt(3)
        return self.c - r, self.c + r

    def sdf(self, points):
        return self.box.sdf((np.asarray(points) - self.c) @ self.R)  # R^T (x − c), row-wise

    def sample(self, spacing, rng=None, jitter=0.0):
        return self.box.sample(spacing, rng, jitter) @ self.R.T + self.c

    def cell_volume(self, spacing):
        return self.box.cell_volume(spacing)

    def volume(self):
        return SIDE ** 3


class _WaterBeside:
    """LEVEL of water filling the tank, less the turned cube."""

    def __init__(self, cube):
        from fluidlab_core.shapes import Box
        self.cube, self.box = cube, Box((0, 0, 0), (WIDTH, WIDTH, LEVEL))

    def bounds(self):
        return self.box.bounds()

    def sdf(self, points):
        return np.maximum(self.box.sdf(points), -self.cube.sdf(points))

    def sample(self, spacing, rng=None, jitter=0.0):
        p = self.box.sample(spacing, rng, jitter)
        return p[self.cube.sdf(p) > 0.0]

    def cell_volume(self, spacing):
        return self.box.cell_volume(spacing)

    def volume(self):
        raise NotImplementedError


def _tilted_sim(res, body, angle):
    """(simulator, the cube's particles' start positions): the bench's tank with the cube turned by `angle` about y
    at the height that puts ρ/ρ_w of its volume under the still surface (bisection on its lattice, each point a layer
    as validation.volumes_below counts it)."""
    import fluidlab_core as fl
    from fluidlab_core import materials as M
    from fluidlab_core.apps import validation

    scene = fl.Scene(lower=(0, 0, 0), upper=(WIDTH, WIDTH, 0.12), grid_res=res, dt=2e-3, substeps=1,
                     pressure="projection")
    s = scene.particle_spacing
    pts = _TurnedCube((0, 0, 0), angle).sample(s)
    vol = np.full(len(pts), SIDE ** 3 / len(pts))
    lo, hi = -SIDE, SIDE
    for _ in range(60):  # the centre's height below the surface that puts the share under it
        mid = 0.5 * (lo + hi)
        if validation.volumes_below(0.0, pts + [0, 0, mid], vol).sum() / SIDE ** 3 > body.density / RHO_W:
            lo = mid
        else:
            hi = mid
    cube = _TurnedCube((WIDTH / 2, WIDTH / 2, LEVEL + 0.5 * (lo + hi)), angle)
    scene.add_particles(_WaterBeside(cube), M.WATER, name="water")
    scene.add_particles(cube, body, name="cube")
    scene.substeps = scene.stable_substeps()
    sim = scene.build()
    return sim, sim.positions("cube").copy()


def _turned_since(x_start, sim):
    """How far the cube has turned about y since its particles were at x_start (degrees; validation.best_rotation)."""
    from fluidlab_core.apps import validation
    R = validation.best_rotation(x_start, sim.positions("cube"))
    return float(np.degrees(np.arctan2(R[0, 2], R[0, 0])))


if __name__ == "__main__":
    main()
