"""Static colliders as signed distance fields, evaluated at grid nodes.

Each static shape becomes a Taichi function φ(x) (metres, negative inside) built when the scene is built:
analytic for primitives and containers (the same formulas as `fluidlab_core.shapes`), trilinear
interpolation of a cached grid for meshes (`mesh_sdf.mesh_sdf_grid`). The normal is n = ∇φ/|∇φ| by central
differences.

Boundary condition at a grid node with φ < ½ Δx (inside the collider or within half a cell of its surface:
ON_SURFACE), velocity v after the grid update:
    sticky:           v ← 0 (for φ < Δx, so that the particles touching the surface stop)
    on a medial surface (|∇φ| < ½, MEDIAL_GRADIENT: no normal): v ← 0
    otherwise, with vₙ = v·n: if vₙ < 0 (moving into the collider)
                      v_t = v − vₙ n,  v ← v_t · max(0, 1 + μ vₙ / |v_t|)     (Coulomb friction, μ ≥ 0)
    separating velocities (vₙ ≥ 0) are left alone.
Which of these applies at a node, and its normals, depend on the node's position only: `Collider.geometry` is
evaluated once per node when the model is uploaded (grid.fill_static_geometry) and each grid update applies it
(`Collider.apply`), so the SDF is not in the grid update's kernels, nor in their reverse mode.

Particle projection after G2P: a particle found inside (φ(x_p) < 0) is moved back to the surface,
x_p ← x_p − φ n, and loses its inward normal velocity.

No-leak rule: walls must be at least `scene.MIN_WALL_CELLS` = 2 grid cells thick. The grid condition alone lets
particles creep through thin walls: past a wall's mid-plane the SDF normal points out of the far side, so
nodes there let particles leave. The particle projection stops that as long as no particle crosses the
mid-plane in one substep; the CFL limit keeps a substep's motion under half a cell, so a wall of two cells
(mid-plane one cell deep) holds. Thinner walls are refused when the scene is built.
"""
from __future__ import annotations

import numpy as np
import taichi as ti

from fluidlab_core import shapes as S

# Added under the square root of every norm that can be exactly zero (inside a box, on a cylinder's axis, a
# node at rest): d|v|/dv = v/|v| is 0/0 there, and reverse-mode autodiff would turn it into NaN even where
# the norm's adjoint is zero. It shifts a norm by at most 1e-15 (the unit of the vector).
NORM_EPS2 = 1e-30
# The grid condition holds every node within half a cell outside a static's surface (φ < ON_SURFACE Δx) as well as
# those inside, so that the node row nearest the surface is held, and a node inside a static where |∇φ| (central
# differences) is below MEDIAL_GRADIENT, on the solid's medial surface (the mid-plane of a wall two cells thick,
# where ∇φ is zero and the slip condition had no normal), stops (v = 0).
# Why: a liquid stands on the held node row nearest its surface, not on the surface between the rows, and the
# particles that the grid carries past the surface are put back on it each substep: they pile up there, and the
# liquid loses that band's volume (its J does not see it). Until 2026-12-05 only nodes inside (φ < 0) were held,
# and where the tasks' tank (small size) has its floor's surface and mid-plane on node rows, the surface row's
# rounding put it a few nm outside and the mid-plane had no normal: the first held row lay two cells down, and in
# 0.1 s the tank's water surface fell 5 mm of its 25 with a quarter of its particles piled on the floor
# (GatheringEasy, the tool still); the cups' coffee (a cylinder between node rows) lost 3-4 mm of its 12 mm mean
# height in 2 s, and water 25 mm deep on a static floor 0.9 cells above a node row 32 % of its depth. Now the held row is at most half a cell from the surface and a second surface within it is held too
# (SECOND_SURFACE): water at rest keeps its depth to within 0.15 cells at any offset of the floor from the node rows,
# the tank's and the cups' to their hydrostatic compression (tests/test_statics.py; bench/static_floor.py). A swirl
# in the cup keeps its angular momentum as before: the held nodes outside lose only the velocity into the static.
ON_SURFACE = 0.5
MEDIAL_GRADIENT = 0.5
# A node held by one surface is held by a second one too where the point half a cell out from the first along its
# normal lies within SECOND_SURFACE Δx of it: the nodes along a tank's inner edge, nearest the wall, are also within
# half a cell of the floor, and without this they let the liquid into the floor along the edges (water in a tank
# with its floor 0.9 cells above a node row piled 2.5 % of its particles on the floor there in 1 s).
SECOND_SURFACE = 0.45
# Collider.geometry's modes: what the grid condition does at a node (kept per node in Model.static_mode)
FREE, STOP, SLIP, SLIP2 = 0, 1, 2, 3


@ti.func
def safe_norm(v):
    """|v| with a finite derivative at v = 0 (see NORM_EPS2)."""
    return ti.sqrt(v.dot(v) + NORM_EPS2)


def _box_sdf(lo, hi):
    c = [0.5 * (a + b) for a, b in zip(lo, hi)]
    h = [0.5 * (b - a) for a, b in zip(lo, hi)]

    @ti.func
    def sdf(p):
        q = ti.abs(p - ti.Vector(c)) - ti.Vector(h)
        return safe_norm(ti.max(q, 0.0)) + ti.min(ti.max(q[0], ti.max(q[1], q[2])), 0.0)

    return sdf


def _sphere_sdf(center, radius):
    @ti.func
    def sdf(p):
        return safe_norm(p - ti.Vector(center)) - radius

    return sdf


def _cylinder_sdf(center, radius, height):
    half = 0.5 * height

    @ti.func
    def sdf(p):
        d = p - ti.Vector(center)
        q = ti.Vector([ti.sqrt(d[0] * d[0] + d[1] * d[1] + NORM_EPS2) - radius, ti.abs(d[2]) - half])
        return safe_norm(ti.max(q, 0.0)) + ti.min(ti.max(q[0], q[1]), 0.0)

    return sdf


def _frustum_sdf(base, r1, r2, height):
    """shapes.primitives.frustum_sdf in Taichi (the same formula)."""
    half = 0.5 * height
    k2r, k2z = r2 - r1, 2.0 * half
    k2sq = k2r * k2r + k2z * k2z

    @ti.func
    def sdf(p):
        d = p - ti.Vector(base)
        q_r = ti.sqrt(d[0] * d[0] + d[1] * d[1] + NORM_EPS2)
        q_z = d[2] - half
        cap = r2
        if q_z < 0.0:
            cap = r1
        ca_r = q_r - ti.min(q_r, cap)
        ca_z = ti.abs(q_z) - half
        t = ti.min(ti.max(((r2 - q_r) * k2r + (half - q_z) * k2z) / k2sq, 0.0), 1.0)
        cb_r, cb_z = q_r - r2 + k2r * t, q_z - half + k2z * t
        sign = 1.0
        if cb_r < 0.0 and ca_z < 0.0:
            sign = -1.0
        return sign * ti.sqrt(ti.min(ca_r * ca_r + ca_z * ca_z, cb_r * cb_r + cb_z * cb_z) + NORM_EPS2)

    return sdf


def _difference(outer, hollow):
    @ti.func
    def sdf(p):
        return ti.max(outer(p), -hollow(p))

    return sdf


class MeshSDF:
    """A mesh static: its SDF grid in a Taichi field, read by trilinear interpolation."""

    def __init__(self, grid, real, uploads=None):
        """uploads: a list to append (field, data) to, for an upload once everything is allocated (model.py);
        None uploads now."""
        self.origin = tuple(float(v) for v in grid.origin)
        self.spacing = float(grid.spacing)
        self.shape = tuple(int(n) for n in grid.values.shape)
        self.values = ti.field(real, shape=self.shape)  # signed distance at the SDF grid's nodes (m)
        data = grid.values.astype(np.float64 if real == ti.f64 else np.float32)
        if uploads is None:
            self.values.from_numpy(data)
        else:
            uploads.append((self.values, data))

    def func(self):
        values, origin, inv_h, h, shape = self.values, self.origin, 1.0 / self.spacing, self.spacing, self.shape

        @ti.func
        def sdf(p):
            g = (p - ti.Vector(origin)) * inv_h
            # outside the grid: distance to the grid box plus the nearest stored value (conservative)
            gc = ti.Vector([ti.min(ti.max(g[d], 0.0), shape[d] - 1.001) for d in ti.static(range(3))])
            outside = safe_norm(g - gc) * h
            i = ti.cast(ti.floor(gc), ti.i32)
            f = gc - i
            value = 0.0
            for a, b, c in ti.static(ti.ndrange(2, 2, 2)):
                w = (f[0] if a else 1.0 - f[0]) * (f[1] if b else 1.0 - f[1]) * (f[2] if c else 1.0 - f[2])
                value += w * values[i[0] + a, i[1] + b, i[2] + c]
            return value + outside

        return sdf


def sdf_func(shape, real, mesh_spacing: float, uploads=None):
    """A Taichi SDF function for a static shape (metres). A mesh's SDF grid goes into a field whose data is
    appended to `uploads` (or uploaded now if None, see MeshSDF)."""
    if isinstance(shape, S.Box):
        return _box_sdf(shape.lower, shape.upper)
    if isinstance(shape, S.Sphere):
        return _sphere_sdf(shape.center, shape.radius)
    if isinstance(shape, S.Cylinder):
        return _cylinder_sdf(shape.center, shape.radius, shape.height)
    if isinstance(shape, S.Frustum):
        return _frustum_sdf(tuple(shape.base_center), shape.bottom_radius, shape.top_radius, shape.height)
    if isinstance(shape, S.CONTAINERS):
        outer = shape._outer() if isinstance(shape, (S.Cup, S.Cone)) else S.Box(shape.lower, shape.upper)
        hollow = shape._hollow()
        return _difference(sdf_func(outer, real, mesh_spacing, uploads), sdf_func(hollow, real, mesh_spacing, uploads))
    if isinstance(shape, S.Mesh):
        from fluidlab_core.shapes.mesh_sdf import mesh_sdf_grid

        return MeshSDF(mesh_sdf_grid(shape.mesh(), mesh_spacing), real, uploads).func()
    raise TypeError(f"no static collider for shape type {type(shape).__name__}")


@ti.func
def bspline_cdf(t):
    """∫_{−∞}^{t} w(s) ds of the quadratic B-spline w (support |s| < 3/2, in cells): the share of a node's stencil
    on one side of a plane t cells from the node (0 far outside, ½ through the node, 1 far inside)."""
    t = ti.min(ti.max(t, -1.5), 1.5)
    a = ti.max(t + 1.5, 0.0)
    b = ti.max(1.5 - t, 0.0)
    lo = a * a * a / 6.0  # t ≤ −½
    mid = 1.0 / 6.0 + 0.75 * (t + 0.5) - (t * t * t + 0.125) / 3.0  # −½ < t ≤ ½
    hi = 1.0 - b * b * b / 6.0  # t > ½
    return ti.select(t <= -0.5, lo, ti.select(t <= 0.5, mid, hi))


def sdf_gradient(sdf, h: float):
    """∇φ(x) of a Taichi SDF function by central differences of step h (m): a unit vector where φ is a distance,
    shorter where the two differences see different surfaces (a medial surface), zero on the mid-plane of a slab."""

    @ti.func
    def gradient(x):
        return ti.Vector([sdf(x + ti.Vector.unit(3, d) * h) - sdf(x - ti.Vector.unit(3, d) * h)
                          for d in ti.static(range(3))]) / (2.0 * h)

    return gradient


def sdf_normal(sdf, h: float):
    """n(x) = ∇φ/|∇φ| of a Taichi SDF function by central differences of step h (m)."""
    gradient = sdf_gradient(sdf, h)

    @ti.func
    def normal(x):
        grad = gradient(x)
        return grad / (safe_norm(grad) + 1e-12)

    return normal


class Collider:
    """A static collider's Taichi hooks: at grid nodes `geometry(x) -> (mode, n, n2)`, computed once per node since
    a static does not move, and `apply(mode, n, n2, v) -> v` in each grid update; `particle(x, v) -> (x, v)` after
    G2P (see the module docstring)."""

    def __init__(self, sdf, friction: float, sticky: bool, h: float, dx: float):
        sticky_band = dx  # sticky statics hold nodes up to a cell outside, so the touching particles stop
        on_surface = ON_SURFACE * dx
        second_surface = SECOND_SURFACE * dx

        normal = sdf_normal(sdf, h)
        gradient = sdf_gradient(sdf, h)

        @ti.func
        def slip(v, n):
            """v without its velocity into the surface of normal n, with Coulomb friction on the rest."""
            vn = v.dot(n)
            if vn < 0.0:
                vt = v - vn * n
                vt_norm = safe_norm(vt)
                scale = 0.0
                if vt_norm > 1e-12:
                    scale = ti.max(0.0, 1.0 + friction * vn / vt_norm)
                v = vt * scale
            return v

        @ti.func
        def geometry(x):
            """What the grid condition does at the node at x: (mode, n, n2), mode FREE (nothing), STOP (v = 0),
            SLIP (slip along the normal n) or SLIP2 (then along a second surface's n2). It depends on the node's
            position only, so the model computes it once per node (grid.fill_static_geometry) and the grid
            update reads it (apply)."""
            mode = FREE
            n = ti.Vector.zero(float, 3)
            n2 = ti.Vector.zero(float, 3)
            phi = sdf(x)
            if ti.static(sticky):
                if phi < sticky_band:
                    mode = STOP
            elif phi < on_surface:
                grad = gradient(x)
                g = safe_norm(grad)
                if g < MEDIAL_GRADIENT:  # no direction to slip along: the node stops
                    mode = STOP
                else:
                    mode = SLIP
                    n = grad / g
                    # a second surface within half a cell: seen from the point half a cell out from the first
                    # (SECOND_SURFACE), as a floor beside a wall is from the nodes along their edge
                    x2 = x + (on_surface - phi) * n
                    if sdf(x2) < second_surface:
                        mode = SLIP2
                        grad2 = gradient(x2)
                        n2 = grad2 / (safe_norm(grad2) + 1e-12)
            return mode, n, n2

        @ti.func
        def apply(mode, n, n2, v):
            """The grid condition on velocity v at a node whose geometry() is (mode, n, n2)."""
            if mode == STOP:
                v = ti.Vector.zero(float, 3)
            elif mode >= SLIP:
                v = slip(v, n)
                if mode == SLIP2:
                    v = slip(v, n2)
            return v

        @ti.func
        def particle(x, v):
            phi = sdf(x)
            if phi < 0.0:
                n = normal(x)
                x -= phi * n
                vn = v.dot(n)
                if vn < 0.0:
                    v -= vn * n
            return x, v

        @ti.func
        def stencil_fill(x):
            """The share of a node's B-spline stencil inside the collider (grid.solid_share_of), its surface taken
            as a plane at distance φ(x): the contact test counts it as filled."""
            return bspline_cdf(-sdf(x) / dx)

        self.sdf = sdf  # φ(x) in the world frame (m), negative inside (the liquid projection's face shares)
        self.normal = normal  # ∇φ/|∇φ| (rigid.py's contact)
        self.friction, self.sticky = float(friction), bool(sticky)  # (rigid.py's contact reads them)
        self.geometry = geometry
        self.apply = apply
        self.particle = particle
        self.stencil_fill = stencil_fill
