"""Rigid bodies made of particles: projection to the best rigid motion (shape matching).

After each substep's G2P the particles of body b (masses m_i, rest offsets q_i from the rest centre of
mass) are replaced by the rigid motion closest to what the MPM step produced (Müller et al. 2005):
    c = Σ m x / M,  v_c = Σ m v / M                      (linear momentum kept)
    A = Σ m (x − c) qᵀ,  R = polar(A) = U Vᵀ with U Σ Vᵀ = A/|A|   (best rotation; A scaled to norm 1 first,
                                                          its entries ~ m q² broke a float32 SVD)
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

Linear and angular momentum of each body are unchanged by the projection, so coupling through the grid
conserves momentum.

Known limitation of the default coupling (issue 19; docs/engine.md, "Floating bodies in 3-D"; with
Scene(pressure="projection"), engine/projection.py, a rigid body floats at Archimedes' depth): a floating body
does not settle at one depth. It creeps, and stops anywhere in a band (a 500 kg/m³ cube at 24 cells held still at 0.545 and at 0.671 of
its side below the surface, Archimedes 0.50). The liquid's push at a contact node is shared with the liquid's
own mass there; the body receives it only as the liquid it presses into compresses the body's bottom layers
and so builds the pressure gradient (from J above) that holds the body up, a slow and history-dependent route.
Measured and ruled out: the exclusion step (made two-way, or pushing to s/4 outside: the same creep) and the
layer-to-layer alternation of J (a linear fit of J over the body still holds it in a band). Tried and not kept: giving the
body the liquid's push at its contact nodes directly (a frictionless wall-like contact law, no stress in the body): right
from rest at Archimedes' depth (0.51-0.53), but a landing cube then stops far too high (0.27-0.30); the same law at the
nodes inside the body's SDF, with the fields never joined and without the exclusion: one depth from any start (no band),
but 0.68-0.70 at 16 and 24 cells: those nodes take only their share of the partition of unity at the face (about 0.75
of the liquid's pressure force measured at 16 cells, where the face reads hydrostatic pressure), the rest goes into
the exclusion, which does not act back (made two-way, the body sinks steadily at balanced force); the body's nodes, with the liquid at its contact nodes, fitted on the grid to one rigid motion
(a clump): it stays wherever it starts (0.52 from Archimedes' depth, 0.90 from 16 mm deeper); the body as a moving
slip wall for the liquid, pushed only by the liquid's grid-averaged pressure summed over its surface (the patch in
docs/experiments/): a dropped 500 kg/m3 cube floats at 0.50 +- 0.005 over 4 s at 16 cells, a deep start holds 0.54
and an 800 kg/m3 cube 0.86-0.87 (the read-out is low near the face's edges); at 24 cells the 500 kg/m3 cube sits at a
share of 0.545, tilted. The most promising route so far, not yet converged. The same force as a volume integral over a band of liquid
around the body, with the liquid's acceleration (the patch's band mode, 2026-12-01): a dropped 500 kg/m3 cube holds
0.47 of its volume under for 5 s without creeping at 16 cells (0.60 at 24), but a deep start stays deep and an 800 kg/m3 cube sinks through
its depth at balanced force: what is left is the liquid's pressure around the body, which its J's history sets.

Contact with the walls, the statics and the tools (scenes with `Scene(pressure="projection")`, where a rigid body
carries no stress and so cannot be held up by the nodes of a floor pressing into its particles): after the body's v
and ω are known, each body particle whose surface (h/2 beyond it, h its spacing) lies within h of a surface is a
contact point at r = x − c with the surface's normal n (into the domain for a wall, ∇φ/|∇φ| of a static's or tool's
SDF φ) and the gap g = d − h/2, d the particle's distance from the surface ((x − wall)·n for a wall, φ(x) for a
static, φ(R_tᵀ(x − p_t)) for a tool at its end-of-substep pose (p_t, R_t)). Projected Gauss–Seidel over the points
(CONTACT_ITERS sweeps; Catto 2005, "Iterative dynamics with temporal coherence") applies normal impulses λ ≥ 0,
accumulated per point, so that each point's normal velocity relative to the surface's, v_n = (v + ω × r − u_s)·n
(u_s = 0 for walls and statics, the tool's lin + ang × (x − p_t)), is at least
    −g/Δt (g ≥ 0: close the gap this substep, no further)   or   −β g/Δt (g < 0: push out at β per substep),
with the effective mass 1/(1/M + (r × n)·I⁻¹(r × n)). Coulomb friction in the same sweeps: after a point's normal
impulse, a tangential impulse λ_t (a vector in the surface's plane, accumulated per point) cancels the point's
tangential velocity relative to the surface, v_t = v_rel − (v_rel·n) n, with the effective mass along it, and the
accumulated λ_t is clamped to the cone |λ_t| ≤ μ λ (Catto 2005). μ: the domain's `wall_friction` for the walls, the
static's `friction` (a sticky static holds without a limit), the tool's `friction`. The substep has already moved
the body with its velocity before the contact; it is moved by Δt times the contact's change of velocity (and turned
by Δt times that of ω) as well, so that x_(n+1) = x_n + Δt v_(n+1): without it a block held by friction on a 30°
slope crept at g sin θ Δt (4.9 mm/s at 1 ms substeps). Without the contact a 2000 kg/m³ cube at 16 cells rested 0.31 Δx into the floor (docs/engine.md, "The
walls' contact"); beside statics and tools, with the walls' contact alone, the same cube sank into a static shelf
at 3.5 mm/s and a paddle's face entered it (tests/test_projection.py).

Code: `RigidModel` holds what does not change (which body each particle belongs to, rest offsets, body
masses, the bodies' SDFs); `RigidProjection` holds a solver's per-substep body quantities and runs the
projection, as one kernel in a forward pass (`forward`) and as separate kernels, built from the same
per-particle and per-body functions, where Taichi's autodiff differentiates them (`kernels`, `write`).
"""

import numpy as np
import taichi as ti

from fluidlab_core.engine import svd as svd3

# The exclusion step is unrolled per body; past this many bodies it is skipped (compile time).
MAX_EXCLUDING_BODIES = 16
# The walls' contact (above): Gauss–Seidel sweeps per substep, and the share of an overlap pushed out per substep
CONTACT_ITERS = 20
CONTACT_BETA = 0.2
STICKY_MU = 1e6  # a sticky static's friction coefficient in the contact: no sliding


@ti.data_oriented
class RigidModel:
    """The rigid bodies' constant data: body of each particle, rest offsets, rest centres, masses, SDFs."""

    def __init__(self, body_index: np.ndarray, x_rest: np.ndarray, mass: np.ndarray, real, shapes=None,
                 dx: float = 0.0):
        """shapes: each body's Shape in its rest pose (world coordinates), for the exclusion step."""
        body_index = np.asarray(body_index)
        n_bodies = int(body_index.max()) + 1
        self.n_bodies = n_bodies
        n = len(body_index)
        np_real = np.float64 if real == ti.f64 else np.float32
        self.body = ti.field(ti.i32, shape=n)  # body of each particle, −1 for none
        self.rest_offset = ti.Vector.field(3, real, shape=n)  # q: rest position − rest centre of mass (m)
        self.rest_com = ti.Vector.field(3, real, shape=n_bodies)  # c⁰: centre of mass at rest (m)
        self.body_mass = ti.field(real, shape=n_bodies)  # M (kg)
        q = np.zeros_like(np.asarray(x_rest, dtype=np.float64))
        com = np.zeros((n_bodies, 3))
        masses = np.zeros(n_bodies)
        for b in range(n_bodies):
            sel = body_index == b
            com[b] = np.average(x_rest[sel], axis=0, weights=mass[sel])
            q[sel] = x_rest[sel] - com[b]
            masses[b] = mass[sel].astype(np_real).sum(dtype=np.float64)
        # uploaded by Model.upload once every field is allocated (model.py)
        self.uploads = [(self.body, body_index.astype(np.int32)), (self.rest_offset, q.astype(np_real)),
                        (self.rest_com, com.astype(np_real)), (self.body_mass, masses.astype(np_real))]
        self.sdfs, self.normals = [], []
        if shapes is not None and n_bodies <= MAX_EXCLUDING_BODIES:
            from fluidlab_core.engine import statics

            uploads = []
            self.sdfs = [statics.sdf_func(shape, real, 0.5 * dx, uploads) for shape in shapes]
            self.normals = [statics.sdf_normal(sdf, 0.01 * dx) for sdf in self.sdfs]
            self.uploads += uploads


@ti.data_oriented
class RigidProjection:
    """A solver's rigid-body projection: the G2P result before it (x_g, v_g, C_g), per-body sums and the
    projection's kernels (see the module docstring). F_model is the solver's field of F after the
    constitutive model, which the projection replaces for body particles."""

    def __init__(self, model, F_model, needs_grad: bool):
        self.model = model
        self.rigid = model.rigid
        self.F_model = F_model
        real, n, nb = model.real, model.n_particles, model.rigid.n_bodies
        g = needs_grad
        self.x_g = ti.Vector.field(3, real, shape=n, needs_grad=g)  # G2P result before the projection (m)
        self.v_g = ti.Vector.field(3, real, shape=n, needs_grad=g)  # (m/s)
        self.C_g = ti.Matrix.field(3, 3, real, shape=n, needs_grad=g)  # (1/s)
        self.com_sum = ti.Vector.field(3, real, shape=nb, needs_grad=g)  # Σ m x (kg m)
        self.momentum = ti.Vector.field(3, real, shape=nb, needs_grad=g)  # Σ m v (kg m/s)
        self.A = ti.Matrix.field(3, 3, real, shape=nb, needs_grad=g)  # Σ m (x − c) qᵀ
        self.A_n = ti.Matrix.field(3, 3, real, shape=nb, needs_grad=g)  # A / |A|
        self.L = ti.Vector.field(3, real, shape=nb, needs_grad=g)  # angular momentum about c (kg m²/s)
        self.U_b = ti.Matrix.field(3, 3, real, shape=nb, needs_grad=g)  # SVD of A_n
        self.sig_b = ti.Matrix.field(3, 3, real, shape=nb, needs_grad=g)
        self.V_b = ti.Matrix.field(3, 3, real, shape=nb, needs_grad=g)
        self.R = ti.Matrix.field(3, 3, real, shape=nb, needs_grad=g)  # rotation from rest
        self.inertia = ti.Matrix.field(3, 3, real, shape=nb, needs_grad=g)  # about c (kg m²)
        self.omega = ti.Vector.field(3, real, shape=nb, needs_grad=g)  # angular velocity (rad/s)
        self.backward_svd = svd3.make_backward_svd(1e-10 if real == ti.f64 else 1e-5)
        self.wall_contact = bool(getattr(model, "projection", False))  # the contact (module docstring)
        if self.wall_contact:
            # the surfaces: the six walls, then the statics, then the tools
            colliders = model.colliders
            self.first_tool = 6 + len(colliders)  # the first tool's surface index
            self.n_surfaces = self.first_tool + model.n_tools
            self._static_sdfs = [c.sdf for c in colliders]
            self._static_normals = [c.normal for c in colliders]
            # each surface's Coulomb coefficient (a sticky static: no limit)
            self._mu = [float(model.wall_friction)] * 6 + [STICKY_MU if c.sticky else c.friction for c in colliders] + \
                [float(t.spec.friction) for t in model.tools]
            # the contact points of the body being solved: particle, surface k, accumulated normal impulse (N s)
            m = self.n_surfaces * n
            self.contact_p = ti.field(ti.i32, shape=m)
            self.contact_k = ti.field(ti.i32, shape=m)
            self.contact_lambda = ti.field(real, shape=m)
            self.contact_lambda_t = ti.Vector.field(3, real, shape=m)  # accumulated tangential impulse (N s)
            self.contact_substeps = ti.field(ti.i32, shape=())  # substeps in which some body got an impulse

    # --- per body and per particle ------------------------------------------------------------------
    @ti.func
    def _clear(self, b):
        self.com_sum[b] = ti.Vector.zero(float, 3)
        self.momentum[b] = ti.Vector.zero(float, 3)
        self.A[b] = ti.Matrix.zero(float, 3, 3)
        self.L[b] = ti.Vector.zero(float, 3)
        self.inertia[b] = ti.Matrix.zero(float, 3, 3)

    @ti.func
    def _sums(self, p):
        """Σ m x and Σ m v."""
        b = self.rigid.body[p]
        if b >= 0:
            m = self.model.mass[p]
            self.com_sum[b] += m * self.x_g[p]
            self.momentum[b] += m * self.v_g[p]

    @ti.func
    def _moments(self, p):
        """A = Σ m (x − c) qᵀ and L = Σ m (x − c) × v."""
        b = self.rigid.body[p]
        if b >= 0:
            m = self.model.mass[p]
            r = self.x_g[p] - self.com_sum[b] / self.rigid.body_mass[b]
            self.A[b] += m * r.outer_product(self.rigid.rest_offset[p])
            self.L[b] += m * r.cross(self.v_g[p])

    @ti.func
    def _normalise(self, b):
        """A/|A|: order-one entries for the SVD (R is unchanged by the scale)."""
        self.A_n[b] = self.A[b] / ti.sqrt((self.A[b] * self.A[b]).sum())

    @ti.func
    def _rotation(self, b):
        """R = U Vᵀ, the polar rotation of A."""
        self.R[b] = self.U_b[b] @ self.V_b[b].transpose()

    @ti.func
    def _inertia(self, p):
        """I = Σ m (|r|² 1 − r rᵀ), r = R q."""
        b = self.rigid.body[p]
        if b >= 0:
            r = self.R[b] @ self.rigid.rest_offset[p]
            self.inertia[b] += self.model.mass[p] * (r.dot(r) * ti.Matrix.identity(float, 3) - r.outer_product(r))

    @ti.func
    def _omega(self, b):
        """ω = I⁻¹ L."""
        self.omega[b] = self.inertia[b].inverse() @ self.L[b]

    @ti.func
    def _write(self, state: ti.template(), s_out, p):
        """Slot s_out of particle p: on its body's rigid motion, and kept out of the other bodies."""
        own = self.rigid.body[p]
        xp, vp, Cp, Fp = self.x_g[p], self.v_g[p], self.C_g[p], self.F_model[p]
        if own >= 0:
            R = self.R[own]
            omega = self.omega[own]
            r = R @ self.rigid.rest_offset[p]
            xp = self.com_sum[own] / self.rigid.body_mass[own] + r
            vp = self.momentum[own] / self.rigid.body_mass[own] + omega.cross(r)
            J = self.F_model[p].determinant() * (1.0 + self.model.dt * self.C_g[p].trace())
            J = ti.min(ti.max(J, 0.5), 2.0)
            if ti.static(self.wall_contact):  # with the liquid projection the body carries no stress: J stays 1
                J = 1.0
            Fp = R * ti.pow(J, 1.0 / 3.0)
            Cp = ti.Matrix([[0.0, -omega[2], omega[1]], [omega[2], 0.0, -omega[0]], [-omega[1], omega[0], 0.0]])
        for b in ti.static(range(len(self.rigid.sdfs))):
            if own != b:
                R, c = self.R[b], self.com_sum[b] / self.rigid.body_mass[b]
                xl = R.transpose() @ (xp - c) + self.rigid.rest_com[b]
                phi = self.rigid.sdfs[b](xl)
                if phi < 0.0:
                    n = R @ self.rigid.normals[b](xl)
                    xp -= phi * n
                    v_body = self.momentum[b] / self.rigid.body_mass[b] + self.omega[b].cross(xp - c)
                    vn = (vp - v_body).dot(n)
                    if vn < 0.0:
                        vp -= vn * n
        state.x[s_out, p] = xp
        state.v[s_out, p] = vp
        state.C[s_out, p] = Cp
        state.F[s_out, p] = Fp

    @ti.func
    def _surface_gap(self, state: ti.template(), s, b, p, k, c):
        """Point p of body b against surface k (0-5: the walls −x, +x, −y, +y, −z, +z; then the statics; then the
        tools at their pose in slot s): its lever r, the surface's normal n (out of the solid), the gap g between
        the body's surface there (h/2 beyond the particle) and the surface, h, the surface's velocity there and its
        Coulomb coefficient."""
        r = self.R[b] @ self.rigid.rest_offset[p]
        x = c + r
        h = ti.pow(self.model.rest_volume[p], 1.0 / 3.0)
        n = ti.Vector.zero(float, 3)
        g = ti.cast(0.0, float)
        us = ti.Vector.zero(float, 3)
        mu = ti.cast(self._mu[0], float)  # the walls'
        if k < 6:
            d = k // 2
            side = ti.cast(1 - 2 * (k % 2), float)  # +1 for a lower wall, −1 for an upper one
            e = ti.Vector([ti.cast(d == 0, float), ti.cast(d == 1, float), ti.cast(d == 2, float)])
            wall = ti.select(k % 2 == 0, ti.Vector(self.model.lower).dot(e), ti.Vector(self.model.upper).dot(e))
            g = side * (x.dot(e) - wall) - 0.5 * h
            n = side * e
        for j in ti.static(range(len(self._static_sdfs))):
            if k == ti.static(6 + j):
                mu = ti.cast(self._mu[6 + j], float)
                g = self._static_sdfs[j](x) - 0.5 * h
                n = self._static_normals[j](x)
        for t in ti.static(range(self.model.n_tools)):
            if k == ti.static(self.first_tool + t):
                mu = ti.cast(self._mu[self.first_tool + t], float)
                pt, Rt = state.tool_p_real[t, s], state.tool_R_real[t, s]
                xl = Rt.transpose() @ (x - pt)
                g = self.model.tools[t].sdf_local(xl) - 0.5 * h
                n = Rt @ self.model.tools[t].normal_local(xl)
                us = state.tool_v_real[t, s] + state.tool_w_real[t, s].cross(x - pt)
        return r, n, g, h, us, mu

    @ti.func
    def _contact(self, state: ti.template(), s, b):
        """Projected Gauss–Seidel on body b's contact with the walls, the statics and the tools (module
        docstring); updates momentum[b] and omega[b]. The points within h of a surface are gathered once, then
        swept CONTACT_ITERS times."""
        M = self.rigid.body_mass[b]
        c = self.com_sum[b] / M
        I_inv = self.inertia[b].inverse()
        v = self.momentum[b] / M
        w = self.omega[b]
        dt = self.model.dt
        count = 0
        for p in range(self.model.n_particles):
            if self.rigid.body[p] == b:
                for k in range(self.n_surfaces):
                    r0, n0, g0, h0, u0, mu0 = self._surface_gap(state, s, b, p, k, c)
                    if g0 < h0:
                        self.contact_p[count] = p
                        self.contact_k[count] = k
                        self.contact_lambda[count] = 0.0
                        self.contact_lambda_t[count] = ti.Vector.zero(float, 3)
                        count += 1
        touched = 0
        for _ in range(CONTACT_ITERS):
            for i in range(count):
                r, n, g, h, us, mu = self._surface_gap(state, s, b, self.contact_p[i], self.contact_k[i], c)
                target = -g / dt if g >= 0.0 else -CONTACT_BETA * g / dt
                vn = (v + w.cross(r) - us).dot(n)
                rn = r.cross(n)
                k_eff = 1.0 / M + rn.dot(I_inv @ rn)
                lam_old = self.contact_lambda[i]
                lam = ti.max(lam_old + (target - vn) / k_eff, 0.0)
                dl = lam - lam_old
                self.contact_lambda[i] = lam
                v += dl / M * n
                w += I_inv @ (rn * dl)
                if lam > 0.0:
                    touched = 1
                if mu > 0.0:  # Coulomb friction: cancel the tangential slip, within the cone |λ_t| ≤ μ λ
                    rel = v + w.cross(r) - us
                    vt = rel - rel.dot(n) * n
                    vt_norm = vt.norm()
                    lt_old = self.contact_lambda_t[i]
                    lt = lt_old
                    if vt_norm > 1e-12:
                        tdir = vt / vt_norm
                        rt = r.cross(tdir)
                        lt = lt_old - vt_norm / (1.0 / M + rt.dot(I_inv @ rt)) * tdir
                    lt_norm = lt.norm()
                    if lt_norm > mu * lam:
                        lt *= mu * lam / lt_norm
                    d = lt - lt_old
                    self.contact_lambda_t[i] = lt
                    v += d / M
                    w += I_inv @ r.cross(d)
        if touched:  # untouched bodies keep their momentum bit for bit
            # the substep moved the body with its velocity before the contact: move it with the contact's change
            # as well (x = x_n + Δt v_(n+1)), or a body held by friction on a slope crept at the speed g sin θ Δt
            dv, dw = v - self.momentum[b] / M, w - self.omega[b]
            self.com_sum[b] += M * dt * dv
            self.R[b] = svd3.rotation_from_rotvec(dw * dt) @ self.R[b]
            self.momentum[b] = v * M
            self.omega[b] = w
            self.contact_substeps[None] += 1

    @ti.func
    def _pose_and_motion(self):
        """c, momentum, R, I and ω of every body from x_g and v_g (the top-level loops of `forward` and `prime`)."""
        ti.loop_config(serialize=True)
        for b in range(self.rigid.n_bodies):
            self._clear(b)
        for p in range(self.model.n_particles):
            self._sums(p)
        for p in range(self.model.n_particles):
            self._moments(p)
        ti.loop_config(serialize=True)
        for b in range(self.rigid.n_bodies):
            self._normalise(b)
            self.U_b[b], self.sig_b[b], self.V_b[b] = svd3.svd(self.A_n[b])
            self._rotation(b)
        for p in range(self.model.n_particles):
            self._inertia(p)
        ti.loop_config(serialize=True)
        for b in range(self.rigid.n_bodies):
            self._omega(b)

    @ti.kernel
    def prime(self, state: ti.template()):
        """The bodies' pose and motion (c, momentum, R, I, ω) from slot 0 of the state, without writing it: for the
        liquid projection (projection.py), whose first substep needs the body's pose before any rigid projection."""
        for p in range(self.model.n_particles):
            self.x_g[p] = state.x[0, p]
            self.v_g[p] = state.v[0, p]
        self._pose_and_motion()

    # --- the forward pass: one kernel -------------------------------------------------------------------
    @ti.kernel
    def forward(self, state: ti.template(), s_out: ti.i32):
        """The whole projection, writing slot s_out (one launch)."""
        self._pose_and_motion()
        if ti.static(self.wall_contact):
            ti.loop_config(serialize=True)
            for b in range(self.rigid.n_bodies):
                self._contact(state, s_out, b)
        for p in range(self.model.n_particles):
            self._write(state, s_out, p)

    # --- the same, kernel by kernel, for Taichi's autodiff (the differentiable solver) ------------------
    @ti.kernel
    def body_sums(self):
        ti.loop_config(serialize=True)
        for b in range(self.rigid.n_bodies):
            self._clear(b)
        for p in range(self.model.n_particles):
            self._sums(p)

    @ti.kernel
    def body_moments(self):
        for p in range(self.model.n_particles):
            self._moments(p)

    @ti.kernel
    def body_normalise(self):
        ti.loop_config(serialize=True)
        for b in range(self.rigid.n_bodies):
            self._normalise(b)

    @ti.kernel
    def body_svd_kernel(self):
        ti.loop_config(serialize=True)
        for b in range(self.rigid.n_bodies):
            self.U_b[b], self.sig_b[b], self.V_b[b] = svd3.svd(self.A_n[b])

    @ti.kernel
    def body_svd_grad_kernel(self):
        ti.loop_config(serialize=True)
        for b in range(self.rigid.n_bodies):
            self.A_n.grad[b] += self.backward_svd(self.U_b.grad[b], self.sig_b.grad[b], self.V_b.grad[b],
                                                  self.U_b[b], self.sig_b[b], self.V_b[b])

    @ti.ad.grad_replaced
    def body_svd(self):
        self.body_svd_kernel()

    @ti.ad.grad_for(body_svd)
    def body_svd_grad(self):
        self.body_svd_grad_kernel()

    @ti.kernel
    def body_rotation(self):
        ti.loop_config(serialize=True)
        for b in range(self.rigid.n_bodies):
            self._rotation(b)

    @ti.kernel
    def body_inertia(self):
        for p in range(self.model.n_particles):
            self._inertia(p)

    @ti.kernel
    def body_omega(self):
        ti.loop_config(serialize=True)
        for b in range(self.rigid.n_bodies):
            self._omega(b)

    @ti.kernel
    def write(self, state: ti.template(), s_out: ti.i32):
        for p in range(self.model.n_particles):
            self._write(state, s_out, p)

    def kernels(self):
        """The projection's kernels before the write, in order."""
        return [self.body_sums, self.body_moments, self.body_normalise, self.body_svd, self.body_rotation,
                self.body_inertia, self.body_omega]

    def backward(self, state, s_out: int):
        """Gradients through the projection of the substep writing slot s_out (its intermediates recomputed
        by `kernels()` beforehand), in reverse order."""
        self.write.grad(state, s_out)
        for kernel in reversed(self.kernels()):
            if kernel == self.body_svd:
                self.body_svd_grad()
            else:
                kernel.grad()

    @ti.kernel
    def clear_grads(self):
        """Zero the gradients that the projection's backward accumulates (before each substep's backward)."""
        for p in range(self.model.n_particles):
            self.F_model.grad[p] = ti.Matrix.zero(float, 3, 3)
            self.x_g.grad[p] = ti.Vector.zero(float, 3)
            self.v_g.grad[p] = ti.Vector.zero(float, 3)
            self.C_g.grad[p] = ti.Matrix.zero(float, 3, 3)
        ti.loop_config(serialize=True)
        for b in range(self.rigid.n_bodies):
            for f in ti.static((self.com_sum, self.momentum, self.L, self.omega)):
                f.grad[b] = ti.Vector.zero(float, 3)
            for f in ti.static((self.A, self.A_n, self.U_b, self.sig_b, self.V_b, self.R, self.inertia)):
                f.grad[b] = ti.Matrix.zero(float, 3, 3)
