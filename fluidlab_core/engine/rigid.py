"""Rigid bodies made of particles: projection to the best rigid motion (shape matching).

After each substep the particles of body b (masses m_i, rest offsets q_i from the rest centre of mass)
are replaced by the rigid motion closest to what the MPM step produced (Müller et al. 2005):
    c = Σ m x / M,  v_c = Σ m v / M                      (linear momentum kept)
    A = Σ m (x − c) qᵀ,  R = polar(A)                    (best rotation)
    L = Σ m (x − c) × v,  I = Σ m (|r|² 1 − r rᵀ), r = R q,  ω = I⁻¹ L   (angular momentum kept)
    J ← J (1 + Δt tr C_grid),  x ← c + R q,  v ← v_c + ω × r,  C ← [ω]×,  F ← R J^(1/3)
J tracks the volume change the grid flow imposes on the body (tr C = div v, taken before C is replaced):
the body then resists compression with the pressure λ J (J − 1), as a liquid does. Without it, liquid
particles drift into a rigid body, which then sinks.

Exclusion: liquid particles follow the grid velocity and body particles the rigid one, so liquid seeps into
a floating body (about 10 % of a block's volume in 1.5 s without the step below). After the projection,
every particle of another body found inside body b, by b's own SDF in its current pose
(φ(Rᵀ(x − c) + c⁰) < 0), is put back on b's surface and loses its velocity into b relative to b's motion.
This one-way push does not act back on b; the grid coupling carries the forces.

Known limitation, measured in the buoyancy set-up (tests/test_physics_solids.py, 7.5 mm cells): floating
blocks start at Archimedes' depth but sink relative to the surface by about 2.5 mm/s, and the far-field water
surface drops by about 1 mm/s while they float; without rigid bodies the same water keeps its level. In a
single-block check (800 kg/m³, 7.5 mm cells) an elastic block of the same density floats at exactly
Archimedes' depth with no drift, while the rigid block sinks at 1.6 mm/s, the same whether F is kept as
elastic strain or reset as here, and with or without the exclusion step: the projection itself is the
cause. A likely mechanism: snapping the supported bottom particles to the body's mean (downward) velocity
pushes them into the liquid every substep, so liquid is squeezed out from under the body. Still open.

Linear and angular momentum of each body are unchanged by the projection, so coupling through the grid
conserves momentum.
"""
from __future__ import annotations

import numpy as np
import taichi as ti

from fluidlab_core.engine import svd as svd3

# The exclusion step is unrolled per body; past this many bodies it is skipped (compile time).
MAX_EXCLUDING_BODIES = 16


@ti.data_oriented
class RigidBodies:
    def __init__(self, solver, body_index: np.ndarray, real, shapes=None, dx: float = 0.0):
        """shapes: each body's Shape in its rest pose (world coordinates), for the exclusion step."""
        self.solver = solver
        n_bodies = int(body_index.max()) + 1
        self.n_bodies = n_bodies
        n = len(body_index)
        self.body = ti.field(ti.i32, shape=n)  # body of each particle, −1 for none
        self.rest_offset = ti.Vector.field(3, real, shape=n)  # q: rest position − rest centre of mass (m)
        self.mass = ti.field(real, shape=n_bodies)  # kg
        self.com = ti.Vector.field(3, real, shape=n_bodies)  # centre of mass (m)
        self.momentum = ti.Vector.field(3, real, shape=n_bodies)  # Σ m v (kg m/s)
        self.A = ti.Matrix.field(3, 3, real, shape=n_bodies)  # shape-matching moment Σ m (x − c) qᵀ
        self.angular_momentum = ti.Vector.field(3, real, shape=n_bodies)  # about c (kg m²/s)
        self.inertia = ti.Matrix.field(3, 3, real, shape=n_bodies)  # about c, current orientation (kg m²)
        self.rotation = ti.Matrix.field(3, 3, real, shape=n_bodies)  # R from rest
        self.omega = ti.Vector.field(3, real, shape=n_bodies)  # angular velocity (rad/s)
        self.rest_com = ti.Vector.field(3, real, shape=n_bodies)  # c⁰: centre of mass at rest (m)
        self.body.from_numpy(body_index.astype(np.int32))
        self.sdfs = []
        if shapes is not None and n_bodies <= MAX_EXCLUDING_BODIES:
            from fluidlab_core.engine import statics

            self.sdfs = [statics.sdf_func(shape, real, 0.5 * dx) for shape in shapes]
            self.normals = [statics.sdf_normal(sdf, 0.01 * dx) for sdf in self.sdfs]

    def set_rest(self, x_rest: np.ndarray, mass: np.ndarray, body_index: np.ndarray):
        """Rest offsets q from each body's rest centre of mass (numpy, once at build)."""
        q = np.zeros_like(x_rest)
        for b in range(self.n_bodies):
            sel = body_index == b
            com = np.average(x_rest[sel], axis=0, weights=mass[sel])
            q[sel] = x_rest[sel] - com
            self.rest_com[b] = com.tolist()
        self.rest_offset.from_numpy(q.astype(self.solver.np_real))

    @ti.kernel
    def project(self):
        """Replace each body's particle motion by its best rigid motion (see the module docstring)."""
        s = self.solver
        for b in range(self.n_bodies):
            self.mass[b] = 0.0
            self.com[b] = ti.Vector.zero(float, 3)
            self.momentum[b] = ti.Vector.zero(float, 3)
            self.A[b] = ti.Matrix.zero(float, 3, 3)
            self.angular_momentum[b] = ti.Vector.zero(float, 3)
            self.inertia[b] = ti.Matrix.zero(float, 3, 3)
        for p in s.x:
            b = self.body[p]
            if b >= 0:
                m = s.mass[p]
                self.mass[b] += m
                self.com[b] += m * s.x[p]
                self.momentum[b] += m * s.v[p]
        for b in range(self.n_bodies):
            self.com[b] /= self.mass[b]
        for p in s.x:
            b = self.body[p]
            if b >= 0:
                m = s.mass[p]
                r = s.x[p] - self.com[b]
                self.A[b] += m * r.outer_product(self.rest_offset[p])
                self.angular_momentum[b] += m * r.cross(s.v[p])
        for b in range(self.n_bodies):
            # scale A to order one first: its entries are ~ m q² (1e-9 kg m² per particle), where a float32
            # SVD's absolute tolerances break down
            A = self.A[b]
            U, _, V = svd3.svd(A / (A.norm() + 1e-30))
            self.rotation[b] = U @ V.transpose()
        for p in s.x:
            b = self.body[p]
            if b >= 0:
                r = self.rotation[b] @ self.rest_offset[p]
                self.inertia[b] += s.mass[p] * (r.dot(r) * ti.Matrix.identity(float, 3) - r.outer_product(r))
        for b in range(self.n_bodies):
            self.omega[b] = self.inertia[b].inverse() @ self.angular_momentum[b]
        for p in s.x:
            b = self.body[p]
            if b >= 0:
                R = self.rotation[b]
                omega = self.omega[b]
                r = R @ self.rest_offset[p]
                s.x[p] = self.com[b] + r
                s.v[p] = self.momentum[b] / self.mass[b] + omega.cross(r)
                # volume change from the grid flow (tr C = div v, before C is replaced below): a body that the
                # flow compresses pushes back, which keeps liquid particles out of it
                J = s.F[p].determinant() * (1.0 + s.dt * s.C[p].trace())
                J = ti.min(ti.max(J, 0.5), 2.0)
                s.F[p] = R * ti.pow(J, 1.0 / 3.0)
                s.C[p] = ti.Matrix([[0.0, -omega[2], omega[1]], [omega[2], 0.0, -omega[0]], [-omega[1], omega[0], 0.0]])

    @ti.kernel
    def exclude(self):
        """Put particles found inside another body back on its surface (see the module docstring)."""
        s = self.solver
        for p in s.x:
            own = self.body[p]
            xp, vp = s.x[p], s.v[p]
            for b in ti.static(range(len(self.sdfs))):
                if own != b:
                    R, c = self.rotation[b], self.com[b]
                    xl = R.transpose() @ (xp - c) + self.rest_com[b]
                    phi = self.sdfs[b](xl)
                    if phi < 0.0:
                        n = R @ self.normals[b](xl)
                        xp -= phi * n
                        v_body = self.momentum[b] / self.mass[b] + self.omega[b].cross(xp - c)
                        vn = (vp - v_body).dot(n)
                        if vn < 0.0:
                            vp -= vn * n
            s.x[p] = xp
            s.v[p] = vp
