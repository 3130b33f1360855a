"""The added mass of a body in a tank of liquid, from potential flow: an independent reference for the coupling.

A body moving at velocity V through still, inviscid, incompressible liquid sets it moving with the potential
flow u = ∇φ:
    ∇²φ = 0 in the liquid,   ∂φ/∂n = V·n on the body (n out of the body),   ∂φ/∂n = 0 on the tank's walls,
    φ = 0 on the free surface (the pressure there stays atmospheric; valid for the first instants of a motion,
    before the surface has moved),
and the liquid's kinetic energy ½ ρ ∫|∇φ|² dV = ½ m_a V² defines the added mass m_a (Newman, Marine
Hydrodynamics, §4.13). Discretised here with the finite-volume Laplacian on a regular grid of cubic cells of side
h (φ at the cells' centres; a body face is a Neumann flux V·n h², the free surface a Dirichlet face half a cell
away), the discrete Green identity gives the energy of the cells' dual mesh from the body's faces, and the half
cells between the body's faces and the liquid's centres beside them, where the normal gradient is V·n, add theirs:
    ∫|∇φ|² dV = −Σ_body faces φ_i (V·n) h² + Σ_body faces (h/2) (V·n)² h²,   m_a = ρ ∫|∇φ|² dV / |V|²
(exact for a piston carrying a column of liquid; without the second sum, low by about h/a for a body of side a).
The grids below are chosen so that the body's faces lie on cell faces (no staircase), and m_a is extrapolated
to h → 0 from three grids (Richardson, with the observed order).

Checks: a sphere far from all walls (its staircase, with φ = 0 on a box 10 radii wide) against ½ ρ V (0.494 with
φ = 0 on a sphere 5 radii out, (b³ − R³)/(2b³ + R³)): 0.5145 extrapolated, 3-4 % high (the staircase). A cube (on
the grid's faces, no staircase) with φ = 0 on a box 2.5 sides out: 0.632 extrapolated, against the tabulated
0.67 ρ a³ (DNV-RP-H103, Table A-2; the near box lowers it by a percent or two, as it does the sphere's). So the
extrapolated values below hold to about ± 5 %. tests/test_reference_models.py checks the piston (exact) and the
cube's coarse grids. Then the cube of issue 19's runs in
its tank, heaving (V = e_z): mid-depth in 100 mm of water and near the floor in 60 mm, as bench/buoyancy_3d.py
starts them with `--level 0.10 --raise -0.038` and `--raise -0.02`.

    python bench/added_mass.py [--quick]     → bench/results/added_mass.txt
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


def added_mass_coefficient(solid: np.ndarray, h: float, free_top: bool, dirichlet_box: bool = False,
                           direction: int = 2) -> tuple[float, int, float]:
    """C_a = m_a / (ρ V_body) for the body `solid` (bool cells, True inside) moving along axis `direction` in the
    liquid filling the rest of the grid. free_top: φ = 0 on the top face of the domain (a free surface); the other
    outer faces are walls (∂φ/∂n = 0), or all of them φ = 0 with dirichlet_box (an unbounded liquid, far away).
    Returns (C_a, CG iterations, seconds)."""
    t0 = time.time()
    shape = solid.shape
    liquid = ~solid
    index = -np.ones(shape, dtype=np.int64)
    n = int(liquid.sum())
    index[liquid] = np.arange(n)
    rows, cols, vals = [], [], []
    diag = np.zeros(n)
    rhs = np.zeros(n)
    strip = 0.0  # Σ over the body's faces of (h/2) (V·m)² h²: the half cells between them and the liquid's centres
    for axis in range(3):
        for side in (-1, 1):
            # the neighbour of every cell across its face on this side
            nb_liquid = np.zeros(shape, dtype=bool)
            nb_solid = np.zeros(shape, dtype=bool)
            sl_from = [slice(None)] * 3
            sl_to = [slice(None)] * 3
            if side == 1:
                sl_from[axis], sl_to[axis] = slice(0, -1), slice(1, None)
            else:
                sl_from[axis], sl_to[axis] = slice(1, None), slice(0, -1)
            nb_liquid[tuple(sl_from)] = liquid[tuple(sl_to)]
            nb_solid[tuple(sl_from)] = solid[tuple(sl_to)]
            boundary = np.zeros(shape, dtype=bool)  # the face is the domain's outer face
            edge = [slice(None)] * 3
            edge[axis] = -1 if side == 1 else 0
            boundary[tuple(edge)] = True
            # liquid-liquid faces: (φ_j − φ_i) h
            m = liquid & nb_liquid
            i = index[m]
            nb_index = np.roll(index, -side, axis=axis)
            j = nb_index[m]
            rows.append(i)
            cols.append(j)
            vals.append(np.full(i.size, h))
            np.add.at(diag, i, -h)
            # liquid-body faces: flux −(V·n_body) h², n_body = −side e_axis, V = e_direction
            m = liquid & nb_solid
            if axis == direction:
                np.add.at(rhs, index[m], -(side * 1.0) * h * h)  # moved to the right-hand side: −flux
                strip += 0.5 * h * h * h * float(m.sum())
            # outer faces: walls (nothing) or φ = 0 half a cell away (−2 φ_i h)
            dirichlet = dirichlet_box or (free_top and axis == 2 and side == 1)
            if dirichlet:
                m = liquid & boundary
                np.add.at(diag, index[m], -2.0 * h)
    A = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    A = A + sp.diags(diag)
    # Σ_j (φ_j − φ_i) h − 2 φ_i h [Dirichlet] + flux_body = 0  →  A φ = −flux_body = rhs (flux = side h² on
    # axis `direction`: the liquid next to a body face follows the body's normal velocity)
    # A is negative definite (with a Dirichlet face) or semi-definite (walls only; the body's flux sums to zero)
    M = sp.diags(-1.0 / A.diagonal())
    it = [0]

    def count(_):
        it[0] += 1

    phi, info = spla.cg(-A, -rhs, rtol=1e-10, maxiter=20000, M=M, callback=count)
    if info != 0:
        raise RuntimeError(f"CG did not converge (info {info}) on a grid of {shape}")
    # φᵀ A φ = φᵀ rhs and −φᵀ A φ = Σ_faces (Δφ)² h + 2 Σ_surface φ² h (the discrete Green identity): the energy
    # of the cells' dual mesh, which leaves out the half cells between the body's faces and the centres of the
    # liquid's cells beside them, where the normal gradient is V·m (the Neumann condition). Added back:
    energy = -float(phi @ rhs) + strip
    volume = float(solid.sum()) * h ** 3
    return energy / volume, it[0], time.time() - t0


def cell_centres(h, extent):
    """X, Y, Z of the centres of the cells (side h) over [0, extent] (m)."""
    return np.meshgrid(*[(np.arange(int(round(e / h))) + 0.5) * h for e in extent], indexing="ij")


def box_cells(lo, hi, h, extent):
    """Bool grid of cells (side h) over [0, extent] with centres inside the box [lo, hi] (m)."""
    X, Y, Z = cell_centres(h, extent)
    return (X > lo[0]) & (X < hi[0]) & (Y > lo[1]) & (Y < hi[1]) & (Z > lo[2]) & (Z < hi[2])


def sphere_cells(c, r, h, extent):
    """Bool grid of cells (side h) over [0, extent] with centres inside the sphere of centre c, radius r (m)."""
    X, Y, Z = cell_centres(h, extent)
    return (X - c[0]) ** 2 + (Y - c[1]) ** 2 + (Z - c[2]) ** 2 < r * r


def richardson(values: list[float]) -> tuple[float | None, float]:
    """Extrapolate f(h), f(h/2), f(h/4) to h → 0; returns (limit, observed order), limit None where the three do
    not converge monotonically at a positive order (then the finest value is all there is)."""
    f1, f2, f3 = values
    ratio = (f1 - f2) / (f2 - f3) if f2 != f3 else float("inf")
    p = float(np.log2(ratio)) if ratio > 0 and np.isfinite(ratio) else float("nan")
    if not (np.isfinite(p) and p > 0.1):
        return None, p
    return float(f3 + (f3 - f2) / (2 ** p - 1)), p


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the two coarser grids only (a smoke run; writes nothing)")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "added_mass.txt"))
    args = ap.parse_args()
    lines = ["# Added mass coefficient C_a = m_a / (rho V) from potential flow (bench/added_mass.py), heave unless said",
             "# case                                     h (mm)   C_a      CG its   s"]
    cases = [
        # name, builder(h) -> (solid, free_top, dirichlet_box), grid sides (m), reference
        ("sphere R 20 mm, phi = 0 on a 200 mm box",
         lambda h: (sphere_cells((0.1, 0.1, 0.1), 0.02, h, (0.2, 0.2, 0.2)), False, True),
         [0.01, 0.005, 0.0025], "0.494-0.500 (a sphere in a sphere of phi = 0 at 5 R: (b3 - R3)/(2 b3 + R3))"),
        ("cube 40 mm, phi = 0 on a 240 mm box",
         lambda h: (box_cells((0.1, 0.1, 0.1), (0.14, 0.14, 0.14), h, (0.24, 0.24, 0.24)), False, True),
         [0.01, 0.005, 0.0025], "0.67 (DNV-RP-H103, unbounded)"),
        ("cube mid-depth: 100 mm water, 30 below/above",
         lambda h: (box_cells((0.04, 0.04, 0.03), (0.08, 0.08, 0.07), h, (0.12, 0.12, 0.10)), True, False),
         [0.01, 0.005, 0.0025, 0.00125], "bench/buoyancy_3d.py --level 0.10 --raise -0.038"),
        ("cube near floor: 60 mm water, 8 below",
         lambda h: (box_cells((0.04, 0.04, 0.008), (0.08, 0.08, 0.048), h, (0.12, 0.12, 0.06)), True, False),
         [0.004, 0.002, 0.001], "bench/buoyancy_3d.py --raise -0.02"),
    ]
    for name, build, hs, ref in cases:
        values = []
        for h in hs[:2] if args.quick else hs:
            solid, free_top, box = build(h)
            ca, its, secs = added_mass_coefficient(solid, h, free_top, box)
            values.append(ca)
            lines.append(f"  {name:<42} {h * 1e3:6.3f}   {ca:.4f}   {its:6d}   {secs:6.1f}")
            print(lines[-1], flush=True)
        if len(values) >= 3:
            limit, order = richardson(values[-3:])
            if limit is None:
                lines.append(f"  {name:<42} h -> 0   not extrapolated (observed order {order:.2f}); reference: {ref}")
            else:
                lines.append(f"  {name:<42} h -> 0   {limit:.4f}   (observed order {order:.2f}); reference: {ref}")
            print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    out = Path(args.out)
    if not args.quick:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_suffix(".tmp")
        tmp.write_text(text)
        tmp.replace(out)
        print(f"wrote {out}")


if __name__ == "__main__":
    main()
