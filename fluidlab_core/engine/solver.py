"""The MLS-MPM substep on a StateBuffer, and the fast (in-place, forward-only) solver.

One substep (formulas in transfer.py, grid.py, constitutive.py, tools.py, rigid.py), as kernels in physical
order:

    P2G          strain update, constitutive model, scatter of mass and momentum (into two velocity fields,
                 the fluids' and the solids', and the particles' volume, when a scene has both: grid.py)
    grid update  gravity, statics, tools, walls
    tools        poses advance: p ← p + Δt v, R ← exp([ω]× Δt) R
    G2P          gather of velocity and affine velocity, advection, projection out of statics and walls
    rigid        projection of rigid bodies to their best rigid motion (only with rigid bodies)

`Solver.mpm_substep` runs the first four as three parallel loops in one launch (a parallel launch is the main
cost at small sizes): particles (P2G), nodes (sum of the per-thread grid copies and the grid update), then
particles again (G2P); the tools' twists from the host and their advance ride in the first and last loop
(a serial part of a kernel costs a task launch, about 40 µs here). It reads slot s_in of a StateBuffer and
writes slot s_out: the fast solver (`FastSolver`) steps a one-slot buffer in place (s_in = s_out = 0); the
differentiable solver (diff_solver.py, a subclass) writes slot s + 1 from slot s and, with `keep`, stores
what its backward reads. Each calls it from a kernel of its own: the physics is written once.

With `Scene(pressure="projection")` (projection.py) the fast solver splits the substep in two launches around the
liquid's pressure solve: P2G and the grid update (the liquid's field with gravity only), the projection, G2P (the
liquid's particles from the solve's faces), the position correction, the rigid projection and the body's push
(`FastSolver.projected_substep`).

Solvers hold no state of their own beyond their buffers (the grid, its per-thread copies, the stress and
rigid-body intermediates): the fast solver steps the StateBuffer passed in, the constants are the Model.
"""

import numpy as np
import taichi as ti

from fluidlab_core.engine import grid, transfer
from fluidlab_core.engine.rigid import RigidProjection
from fluidlab_core.engine.control import Control
from fluidlab_core.engine.emitters import schedule, takes_part
from fluidlab_core.engine.state import StateBuffer
from fluidlab_core.engine.tools import advance_pose
from fluidlab_core.runtime import compiled_fast


@ti.data_oriented
class Solver:
    """Buffers and the forward substep, shared by the fast and the differentiable solver.

    scatter_copies: per-thread grid copies for the P2G scatter (CPU); 0 scatters atomically (GPU)."""

    def __init__(self, model, scatter_copies: int = 0, needs_grad: bool = False):
        self.model = model
        real, n = model.real, model.n_particles
        self.real = real
        self.n_particles = n
        g = needs_grad
        self.grid_m = ti.field(real, shape=model.grid_shape, needs_grad=g)  # node mass (kg)
        self.grid_mv = ti.Vector.field(3, real, shape=model.grid_shape, needs_grad=g)  # node momentum (kg m/s)
        self.grid_v = ti.Vector.field(3, real, shape=model.grid_shape, needs_grad=g)  # node velocity after BCs
        self.scatter_copies = int(scatter_copies)
        self.private = self.scatter_copies > 0
        self.copies = max(self.scatter_copies, 1)
        self.chunk = -(-n // self.copies)
        self.two_fields = model.two_fields
        if self.two_fields:  # the fluids' velocity field (grid.py); grid_m, grid_mv, grid_v are the solids'
            self.grid_m_f = ti.field(real, shape=model.grid_shape, needs_grad=g)  # fluids' node mass (kg)
            self.grid_mv_f = ti.Vector.field(3, real, shape=model.grid_shape, needs_grad=g)  # (kg m/s)
            self.grid_v_f = ti.Vector.field(3, real, shape=model.grid_shape, needs_grad=g)  # after BCs (m/s)
            self.grid_vol = ti.field(real, shape=model.grid_shape)  # all particles' volume at the node (m³)
        if self.private:
            shape = (self.copies,) + tuple(model.grid_shape)
            self.copies_m = ti.field(real, shape=shape)  # per-thread node mass (kg)
            self.copies_mv = ti.Vector.field(3, real, shape=shape)  # per-thread node momentum, or its gradient
            if self.two_fields:
                self.copies_m_f = ti.field(real, shape=shape)  # the same for the fluids' field
                self.copies_mv_f = ti.Vector.field(3, real, shape=shape)
                self.copies_vol = ti.field(real, shape=shape)  # per-thread particle volume (m³)
        self.has_flip = model.has_flip
        if self.has_flip:  # AFLIP (transfer.py): the liquids' transfer momentum without stress, and its velocity
            self.grid_v0 = ti.Vector.field(3, real, shape=model.grid_shape)  # v⁰_i (m/s), the liquids' field
            if self.private:
                self.copies_mv0 = ti.Vector.field(3, real, shape=(self.copies,) + tuple(model.grid_shape))
            else:
                self.grid_mv0 = ti.Vector.field(3, real, shape=model.grid_shape)  # (kg m/s)
            self.mv0_source = self.copies_mv0 if self.private else self.grid_mv0  # (_transfer_velocity)
        self.has_jbar = model.has_jbar
        if self.has_jbar:  # J-bar (transfer.py): the liquids' mass-weighted J at the nodes
            self.grid_J = ti.field(real, shape=model.grid_shape)  # J_i
            if model.jbar_affine:  # weighted least-squares fit J ≈ c₀ + c·(x − x_i)/Δx at each node
                self.grid_A = ti.Matrix.field(4, 4, real, shape=model.grid_shape)  # Σ w m φ φᵀ
                self.grid_r = ti.Vector.field(4, real, shape=model.grid_shape)  # Σ w m J φ
                self.grid_c = ti.Vector.field(4, real, shape=model.grid_shape)  # the fit (c₀, c)
            elif self.private:  # the plain mean's sums
                self.copies_mJ = ti.field(real, shape=(self.copies,) + tuple(model.grid_shape))  # Σ w m J (kg)
                self.copies_mliq = ti.field(real, shape=(self.copies,) + tuple(model.grid_shape))  # Σ w m (kg)
            else:
                self.grid_mJ = ti.field(real, shape=model.grid_shape)
                self.grid_mliq = ti.field(real, shape=model.grid_shape)
        self.projection = model.projection
        if self.projection:  # the liquid field's velocity before gravity and the projection (projection.py, AFLIP)
            self.grid_v0 = ti.Vector.field(3, real, shape=model.grid_shape)
            # and the volume of the particles in that field (m³), whose mass over it is the mixture's density
            self.grid_vol_f = ti.field(real, shape=model.grid_shape)
            if self.private:
                self.copies_vol_f = ti.field(real, shape=(self.copies,) + tuple(model.grid_shape))
        # AFLIP on the projection beside deformable solids (projection.py, the faces): the solids' transfer
        # momentum without their stress, whose velocity v⁰ is what a face the solids share had before the substep
        self.soft_flip = model.projection_soft and model.flip > 0.0 and len(model.fluid_models) > 0
        if self.soft_flip:
            self.grid_v0_s = ti.Vector.field(3, real, shape=model.grid_shape)  # v⁰ of the solids' field (m/s)
            if self.private:
                self.copies_mv0_s = ti.Vector.field(3, real, shape=(self.copies,) + tuple(model.grid_shape))
            else:
                self.grid_mv0_s = ti.Vector.field(3, real, shape=model.grid_shape)  # (kg m/s)
            self.mv0_s_source = self.copies_mv0_s if self.private else self.grid_mv0_s
        self.rigid = None
        self.has_rigid = model.has_rigid
        if model.has_rigid:
            self.F_model = ti.Matrix.field(3, 3, real, shape=n, needs_grad=g)  # F after the model, before projection
            self.rigid = RigidProjection(model, self.F_model, needs_grad)

    @property
    def np_real(self):
        return self.model.np_real

    @ti.func
    def mpm_substep(self, state: ti.template(), s_in, s_out, keep: ti.template(), twist: ti.template(),
                    host_twist: ti.template(), emit: ti.template(), host_emit: ti.template()):
        """One substep from slot s_in to slot s_out (see the module docstring), called at the top of a kernel (its
        loops are the kernel's parallel loops). With `host_twist`, the tools' twists come from the kernel's
        array `twist` (n_tools, 6); with `host_emit`, the emission of the substep from the array `emit`
        (n_emitters, 3: emitted before, emitted after, on-time after; emitters.schedule), otherwise from the
        state's slots s_in and s_out; with `keep`, the differentiable solver's stores are filled. Each solver's
        kernel takes only the arguments it needs: at small sizes Taichi's handling of a launch's arguments (an
        array, a template) costs as much as a tenth of the substep."""
        if ti.static(self.model.jbar_affine):  # affine J-bar: exact for J linear in x, also where the liquid ends
            for I in ti.grouped(self.grid_J):
                self.grid_A[I] = ti.Matrix.zero(float, 4, 4)
                self.grid_r[I] = ti.Vector.zero(float, 4)
            for p in range(self.n_particles):
                if takes_part(self.model, state, s_in, p) and transfer.is_fluid(self.model, p):
                    base, fx, w = grid.stencil(self.model, state.x[s_in, p])
                    mp = self.model.mass[p]
                    J = state.F[s_in, p].determinant()
                    for offset in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
                        d = fx - offset  # (x_p − x_i)/Δx
                        phi = ti.Vector([1.0, d[0], d[1], d[2]])
                        weight = w[offset[0]][0] * w[offset[1]][1] * w[offset[2]][2] * mp
                        self.grid_A[base + offset] += weight * phi.outer_product(phi)
                        self.grid_r[base + offset] += weight * J * phi
            for I in ti.grouped(self.grid_J):
                A = self.grid_A[I]
                cfit = ti.Vector([1.0, 0.0, 0.0, 0.0])
                if A[0, 0] > self.model.mass_floor:
                    cfit = ti.Vector([self.grid_r[I][0] / A[0, 0], 0.0, 0.0, 0.0])
                    A64 = A.cast(ti.f64) / ti.cast(A[0, 0], ti.f64)  # solved in float64, scaled to A₀₀ = 1
                    if ti.abs(A64.determinant()) > 1e-6:
                        cfit = ti.cast(A64.inverse() @ (self.grid_r[I].cast(ti.f64) / ti.cast(A[0, 0], ti.f64)),
                                       self.real)
                self.grid_c[I] = cfit
        elif ti.static(self.has_jbar):  # J-bar: the liquids' J averaged at the nodes, read back in P2G
            if ti.static(self.private):
                ti.loop_config(block_dim=1)
                for c in range(self.copies):
                    for p in range(c * self.chunk, ti.min((c + 1) * self.chunk, self.n_particles)):
                        self._scatter_J(state, s_in, c, p)
            else:
                for I in ti.grouped(self.grid_J):
                    self.grid_mJ[I] = 0.0
                    self.grid_mliq[I] = 0.0
                for p in range(self.n_particles):
                    self._scatter_J(state, s_in, 0, p)
            for I in ti.grouped(self.grid_J):
                mJ, ml = 0.0, 0.0
                if ti.static(self.private):
                    mJ = transfer.reduce_scalar_copies(self.copies_mJ, self.copies, I)
                    ml = transfer.reduce_scalar_copies(self.copies_mliq, self.copies, I)
                else:
                    mJ, ml = self.grid_mJ[I], self.grid_mliq[I]
                J_node = 1.0
                if ml > self.model.mass_floor:
                    J_node = mJ / ml
                self.grid_J[I] = J_node
        self._p2g_and_grid(state, s_in, s_out, keep, twist, host_twist)
        self._g2p_loop(state, s_in, s_out, keep, emit, host_emit)

    @ti.func
    def _p2g_and_grid(self, state: ti.template(), s_in, s_out, keep: ti.template(), twist: ti.template(),
                      host_twist: ti.template()):
        """The substep's P2G and grid update (two of mpm_substep's parallel loops)."""
        # P2G (and the tools' twists from the host: nothing reads them before the grid update; a serial part of
        # its own would cost a task launch, about 40 µs here)
        if ti.static(self.private):
            # each thread scatters its share of particles into its own grid copy, without atomics (the copies
            # are zero: allocated so, and zeroed again as they are summed)
            ti.loop_config(block_dim=1)
            for c in range(self.copies):
                if ti.static(host_twist):
                    if c == 0:
                        self._twists_from_host(state, s_in, twist)
                for p in range(c * self.chunk, ti.min((c + 1) * self.chunk, self.n_particles)):
                    self._p2g(state, s_in, s_out, keep, c, p)
        else:
            for I in ti.grouped(self.grid_m):
                self.grid_m[I] = 0.0
                self.grid_mv[I] = ti.Vector.zero(float, 3)
                if ti.static(self.two_fields):
                    self.grid_m_f[I] = 0.0
                    self.grid_mv_f[I] = ti.Vector.zero(float, 3)
                    self.grid_vol[I] = 0.0
                if ti.static(self.projection):
                    self.grid_vol_f[I] = 0.0
                if ti.static(self.has_flip):
                    self.grid_mv0[I] = ti.Vector.zero(float, 3)
                if ti.static(self.soft_flip):
                    self.grid_mv0_s[I] = ti.Vector.zero(float, 3)
            for p in range(self.n_particles):
                if ti.static(host_twist):
                    if p == 0:
                        self._twists_from_host(state, s_in, twist)
                self._p2g(state, s_in, s_out, keep, 0, p)
        # grid update
        for I in ti.grouped(self.grid_m):
            m = 0.0
            mv = ti.Vector.zero(float, 3)
            if ti.static(self.private):
                m, mv = transfer.reduce_copies(self.copies_m, self.copies_mv, self.copies, I)
            else:
                m, mv = self.grid_m[I], self.grid_mv[I]
            if ti.static(self.two_fields):
                m_f, mv_f, vol = 0.0, ti.Vector.zero(float, 3), 0.0
                if ti.static(self.private):
                    m_f, mv_f = transfer.reduce_copies(self.copies_m_f, self.copies_mv_f, self.copies, I)
                    vol = transfer.reduce_scalar_copies(self.copies_vol, self.copies, I)
                else:
                    m_f, mv_f, vol = self.grid_m_f[I], self.grid_mv_f[I], self.grid_vol[I]
                c = 0.0
                if ti.static(not self.projection):  # the projection's liquid never shares the body's field
                    c = grid.in_contact(self.model, I, m, m_f, vol)  # once per node, for both fields
                vn = grid.field_velocity(self.model, I, 0, c, m, mv, m_f, mv_f, state, s_in)
                vn_f = ti.Vector.zero(float, 3)
                if ti.static(self.projection):  # u* (gravity only; the walls come after the projection) and v⁰
                    self.grid_v0[I] = ti.Vector.zero(float, 3)
                    if m_f > self.model.mass_floor:
                        vn_f = mv_f / m_f + self.model.dt * ti.Vector(self.model.gravity)
                        self.grid_v0[I] = mv_f / m_f
                    self.grid_vol[I] = vol
                    if ti.static(self.private):
                        self.grid_vol_f[I] = transfer.reduce_scalar_copies(self.copies_vol_f, self.copies, I)
                    if ti.static(self.soft_flip):
                        self.grid_v0_s[I] = self._transfer_velocity(self.mv0_s_source, I, m)
                else:
                    vn_f = grid.field_velocity(self.model, I, 1, c, m, mv, m_f, mv_f, state, s_in)
                self.grid_m[I] = m
                self.grid_v[I] = vn
                self.grid_m_f[I] = m_f
                self.grid_v_f[I] = vn_f
                if ti.static(keep):
                    self.store_m[s_in, I], self.store_mv[s_in, I], self.store_v[s_in, I] = m, mv, vn
                    self.store_m_f[s_in, I], self.store_mv_f[s_in, I], self.store_v_f[s_in, I] = m_f, mv_f, vn_f
                    self.store_vol[s_in, I] = vol
            else:
                vn = grid.node_velocity(self.model, I, m, mv, state, s_in)
                self.grid_m[I] = m
                self.grid_v[I] = vn
                if ti.static(keep):
                    self.store_m[s_in, I], self.store_mv[s_in, I], self.store_v[s_in, I] = m, mv, vn
            if ti.static(self.has_flip):
                m_liquid = m
                if ti.static(self.two_fields):
                    m_liquid = self.grid_m_f[I]
                self.grid_v0[I] = self._transfer_velocity(self.mv0_source, I, m_liquid)

    @ti.func
    def _transfer_velocity(self, source: ti.template(), I, m):
        """AFLIP's v⁰ at node I: the transfer momentum without stress (scatter_momentum) over the node mass m, from
        `source`, the grid copies (summed, and zeroed for the next substep) or the atomic field."""
        mv0 = ti.Vector.zero(float, 3)
        if ti.static(self.private):
            mv0 = transfer.reduce_vector_copies(source, self.copies, I)
        else:
            mv0 = source[I]
        v0 = ti.Vector.zero(float, 3)
        if m > self.model.mass_floor:
            v0 = mv0 / m
        return v0

    @ti.func
    def _g2p_loop(self, state: ti.template(), s_in, s_out, keep: ti.template(), emit: ti.template(),
                  host_emit: ti.template()):
        """The substep's G2P (the last of mpm_substep's parallel loops), and the tools' advance."""
        # G2P (and the tools' advance: nothing reads their poses after the grid update, except a nozzle that a
        # tool carries or a tool that keeps particles out, whose particles then read slot s_in: the advance then
        # waits for the end of the loop)
        for p in range(self.n_particles):
            if ti.static(not self.model.advance_after_g2p):
                if p == 0:
                    for k in ti.static(range(self.model.n_tools)):
                        self._advance_tool(state, s_in, s_out, k)
            if ti.static(self.model.has_emitters):
                self._g2p_emitting(state, s_in, s_out, keep, p, emit, host_emit)
            else:
                self._g2p(state, s_in, s_out, keep, p)
        if ti.static(self.model.advance_after_g2p or (self.model.has_emitters and host_emit)):
            ti.loop_config(serialize=True)
            for _ in range(1):
                if ti.static(self.model.advance_after_g2p):
                    for k in ti.static(range(self.model.n_tools)):
                        self._advance_tool(state, s_in, s_out, k)
                if ti.static(host_emit):  # the fast solver's slot keeps its emission up to date
                    for e in ti.static(range(self.model.n_emitters)):
                        state.emit_n[e, s_out] = ti.cast(emit[e, 1], ti.i32)
                        state.emit_t[e, s_out] = emit[e, 2]

    @ti.func
    def _g2p(self, state: ti.template(), s_in, s_out, keep: ti.template(), p):
        """G2P of particle p: gather, advection, projection out of statics and walls."""
        new_v, new_C = ti.Vector.zero(float, 3), ti.Matrix.zero(float, 3, 3)
        if ti.static(self.two_fields):
            if transfer.is_fluid(self.model, p):
                if ti.static(self.projection):  # from the projection's faces (a staggered grid)
                    new_v, new_C = self.proj.gather_faces(self.proj.uf, state.x[s_in, p])
                else:
                    new_v, new_C = transfer.gather(self.model, self.grid_v_f, state.x[s_in, p])
            else:
                new_v, new_C = transfer.gather(self.model, self.grid_v, state.x[s_in, p])
        else:
            new_v, new_C = transfer.gather(self.model, self.grid_v, state.x[s_in, p])
        xp = state.x[s_in, p] + self.model.dt * new_v
        if ti.static(self.has_flip):  # AFLIP: advected by v_PIC, keeps α of its own velocity's detail
            if transfer.is_fluid(self.model, p):
                new_v += self.model.flip * (state.v[s_in, p] - transfer.gather_velocity(
                    self.model, self.grid_v0, state.x[s_in, p]))
        if ti.static(self.projection and self.model.flip > 0):  # AFLIP, v⁰ from the pre-gravity faces
            if transfer.is_fluid(self.model, p):
                v0, _ = self.proj.gather_faces(self.proj.uf0, state.x[s_in, p])
                new_v += self.model.flip * (state.v[s_in, p] - v0)
        if ti.static(keep):
            self.store_x_pre[s_in, p], self.store_v_pre[s_in, p] = xp, new_v  # for the backward (g2p_project)
            if ti.static(self.has_rigid):
                self.store_C_pre[s_in, p] = new_C
        xp, new_v = grid.project(self.model, xp, new_v, state, s_in)
        self._store_g2p(state, s_out, p, xp, new_v, new_C)

    @ti.func
    def emission(self, state: ti.template(), s_in, s_out, e, emit: ti.template(), host_emit: ti.template()):
        """(emitted before the substep, emitted after it, on-time after it) of emitter e ≥ 0."""
        before, after, t_after = 0, 0, ti.cast(0.0, ti.f64)
        if ti.static(host_emit):
            before, after, t_after = ti.cast(emit[e, 0], ti.i32), ti.cast(emit[e, 1], ti.i32), emit[e, 2]
        else:
            before, after, t_after = state.emit_n[e, s_in], state.emit_n[e, s_out], state.emit_t[e, s_out]
        return before, after, t_after

    @ti.func
    def _g2p_emitting(self, state: ti.template(), s_in, s_out, keep: ti.template(), p, emit: ti.template(),
                      host_emit: ti.template()):
        """G2P in a scene with emitters: particles already emitted as usual; pool particles born in this substep
        leave their nozzle (emitters.py); the others stay parked."""
        em = self.model.emitters
        e = em.emitter[p]
        if e < 0:
            self._g2p(state, s_in, s_out, keep, p)
        else:
            before, after, t_after = self.emission(state, s_in, s_out, e, emit, host_emit)
            j = em.pool_index[p]
            if j < before:
                self._g2p(state, s_in, s_out, keep, p)
            elif j < after:
                xp, vp = em.newborn(self.model, state, s_in, p, t_after)
                self._store_g2p(state, s_out, p, xp, vp, ti.Matrix.zero(float, 3, 3))
            else:
                self._store_g2p(state, s_out, p, state.x[s_in, p], state.v[s_in, p], ti.Matrix.zero(float, 3, 3))

    @ti.func
    def _scatter_J(self, state: ti.template(), s_in, c, p):
        """J-bar's scatter of a liquid particle's m J and m (an emitter's parked particles take no part)."""
        active = takes_part(self.model, state, s_in, p)
        if active and transfer.is_fluid(self.model, p):
            mp = self.model.mass[p]
            J = state.F[s_in, p].determinant()
            if ti.static(self.private):
                transfer.scatter_scalar(self.model, self.copies_mJ, c, True, state.x[s_in, p], mp * J)
                transfer.scatter_scalar(self.model, self.copies_mliq, c, True, state.x[s_in, p], mp)
            else:
                transfer.scatter_scalar(self.model, self.grid_mJ, c, False, state.x[s_in, p], mp * J)
                transfer.scatter_scalar(self.model, self.grid_mliq, c, False, state.x[s_in, p], mp)

    @ti.func
    def _p2g(self, state: ti.template(), s_in, s_out, keep: ti.template(), c, p):
        """P2G of particle p: strain update, constitutive model (its SVD inline), scatter into grid copy c (or
        atomically into the grid)."""
        active = takes_part(self.model, state, s_in, p)
        Cp = state.C[s_in, p]
        F_in = state.F[s_in, p]
        if ti.static(self.has_jbar):
            if active and transfer.is_fluid(self.model, p):
                J = F_in.determinant()
                J_bar = 0.0
                if ti.static(self.model.jbar_affine):
                    base, fx, w = grid.stencil(self.model, state.x[s_in, p])
                    for offset in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
                        d = fx - offset
                        cfit = self.grid_c[base + offset]
                        J_bar += w[offset[0]][0] * w[offset[1]][1] * w[offset[2]][2] * (
                            cfit[0] + cfit[1] * d[0] + cfit[2] * d[1] + cfit[3] * d[2])
                else:
                    J_bar = transfer.gather_scalar(self.model, self.grid_J, state.x[s_in, p])
                F_in = ti.pow(J_bar / J, 1.0 / 3.0) * F_in
        Fp = ti.Matrix.identity(float, 3)
        tau = ti.Matrix.zero(float, 3, 3)
        if active:
            Fp, tau = transfer.stress(self.model, p, transfer.trial_strain(self.model, Cp, F_in), Cp)
        if ti.static(self.projection):
            if transfer.is_fluid(self.model, p):  # incompressible: the projection gives the pressure
                Fp = ti.Matrix.identity(float, 3)
                tau = tau - tau.trace() / 3.0 * ti.Matrix.identity(float, 3)
            elif ti.static(self.has_rigid):  # a rigid body carries no stress: the projections hold it (a
                if self.model.rigid.body[p] >= 0:  # deformable solid keeps its own)
                    tau = ti.Matrix.zero(float, 3, 3)
        if ti.static(self.has_rigid):
            self.F_model[p] = Fp
        else:
            state.F[s_out, p] = Fp
        if ti.static(keep):
            self.store_tau[s_in, p] = tau
        if active:  # a pool particle not yet emitted adds nothing to the grid (F = I, τ = 0 until it leaves)
            if ti.static(self.two_fields):
                vol = self.model.rest_volume[p] * F_in.determinant()
                if ti.static(self.private):
                    transfer.scatter_volume(self.model, self.copies_vol, c, True, state.x[s_in, p], vol)
                    if transfer.is_fluid(self.model, p):
                        if ti.static(self.projection):
                            transfer.scatter_volume(self.model, self.copies_vol_f, c, True, state.x[s_in, p], vol)
                        transfer.scatter(self.model, self.copies_m_f, self.copies_mv_f, c, True, state.x[s_in, p],
                                         state.v[s_in, p], Cp, tau, p)
                    else:
                        transfer.scatter(self.model, self.copies_m, self.copies_mv, c, True, state.x[s_in, p],
                                         state.v[s_in, p], Cp, tau, p)
                else:
                    transfer.scatter_volume(self.model, self.grid_vol, c, False, state.x[s_in, p], vol)
                    if transfer.is_fluid(self.model, p):
                        if ti.static(self.projection):
                            transfer.scatter_volume(self.model, self.grid_vol_f, c, False, state.x[s_in, p], vol)
                        transfer.scatter(self.model, self.grid_m_f, self.grid_mv_f, c, False, state.x[s_in, p],
                                         state.v[s_in, p], Cp, tau, p)
                    else:
                        transfer.scatter(self.model, self.grid_m, self.grid_mv, c, False, state.x[s_in, p],
                                         state.v[s_in, p], Cp, tau, p)
            elif ti.static(self.private):
                transfer.scatter(self.model, self.copies_m, self.copies_mv, c, True, state.x[s_in, p],
                                 state.v[s_in, p], Cp, tau, p)
            else:
                transfer.scatter(self.model, self.grid_m, self.grid_mv, c, False, state.x[s_in, p],
                                 state.v[s_in, p], Cp, tau, p)
            if ti.static(self.soft_flip):  # the solids' transfer momentum beside the projection (AFLIP's v⁰)
                if not transfer.is_fluid(self.model, p):
                    transfer.scatter_momentum(self.model, self.mv0_s_source, c, self.private, state.x[s_in, p],
                                              state.v[s_in, p], Cp, p)
            if ti.static(self.has_flip):
                if transfer.is_fluid(self.model, p):
                    transfer.scatter_momentum(self.model, self.mv0_source, c, self.private, state.x[s_in, p],
                                              state.v[s_in, p], Cp, p)

    @ti.func
    def _twists_from_host(self, state: ti.template(), s, twist: ti.template()):
        for k in ti.static(range(self.model.n_tools)):
            state.tool_v[k, s] = ti.Vector([twist[k, i] for i in ti.static(range(3))])
            state.tool_w[k, s] = ti.Vector([twist[k, 3 + i] for i in ti.static(range(3))])
            state.sync_real(k, s)

    @ti.func
    def _advance_tool(self, state: ti.template(), s_in, s_out, k):
        """Tool k's pose over the substep, in the precision of the state's tool fields."""
        dt = ti.cast(self.model.tool_dt[None], state.pose_real)
        state.tool_p[k, s_out], state.tool_R[k, s_out] = advance_pose(
            state.tool_p[k, s_in], state.tool_R[k, s_in], state.tool_v[k, s_in], state.tool_w[k, s_in], dt)
        state.sync_real(k, s_out)

    @ti.func
    def _store_g2p(self, state: ti.template(), s_out, p, xp, vp, Cp):
        """Into slot s_out, or with rigid bodies into the projection's input (x_g, v_g, C_g)."""
        if ti.static(self.has_rigid):
            self.rigid.x_g[p], self.rigid.v_g[p], self.rigid.C_g[p] = xp, vp, Cp
        else:
            state.x[s_out, p], state.v[s_out, p], state.C[s_out, p] = xp, vp, Cp


class FastSolver(Solver):
    """The forward solver: steps a one-slot StateBuffer in place (`Model.state()`), no gradients."""

    def __init__(self, model, scatter_copies: int = 0):
        super().__init__(model, scatter_copies)
        self.proj = None
        if model.projection:
            from fluidlab_core.engine.projection import LiquidProjection

            self.proj = LiquidProjection(self)

    @ti.kernel
    def projection_p2g_kernel(self, state: ti.template()):
        """P2G and the grid update of a substep with the liquid projection (projection.py)."""
        self._p2g_and_grid(state, 0, 0, False, 0, False)

    @ti.kernel
    def projection_p2g_kernel_tools(self, state: ti.template(), twist: ti.types.ndarray()):
        """The same, with the tools' twists (n_tools, 6) from the host."""
        self._p2g_and_grid(state, 0, 0, False, twist, True)

    @ti.kernel
    def projection_g2p_kernel(self, state: ti.template()):
        """G2P of a substep with the liquid projection, after the projection."""
        self._g2p_loop(state, 0, 0, False, 0, False)

    @ti.kernel
    def projection_g2p_kernel_emitting(self, state: ti.template(), emit: ti.types.ndarray()):
        """The same in a scene with emitters, the substep's emission (n_emitters, 3) from the host: the pool
        particles born in the substep leave their nozzles after the projection, as in substep_kernel_emitting."""
        self._g2p_loop(state, 0, 0, False, emit, True)

    def projected_substep(self, state: StateBuffer, twist=None, emit=None):
        """One substep with the liquid's pressure by projection (projection.py's module docstring has the order),
        with the tools' twists (n_tools, 6) where the scene has tools and the substep's emission (n_emitters, 3:
        emitted before, emitted after, on-time after; emitters.schedule) where it has emitters. P2G and the
        projection see the particles emitted before the substep (the pool's others add nothing to the grid)."""
        if self.model.n_tools:
            self.projection_p2g_kernel_tools(state, twist)
        else:
            self.projection_p2g_kernel(state)
        self.proj.project(state)
        if emit is not None:
            self.projection_g2p_kernel_emitting(state, emit)
        else:
            self.projection_g2p_kernel(state)
        self.proj.displace(state)
        if self.rigid is not None:
            self.rigid.forward(state, 0)
            self.proj.push(state)

    @ti.kernel
    def substep_kernel(self, state: ti.template(), twist: ti.types.ndarray()):
        """One substep in place, with the tools' twists (n_tools, 6) from the host."""
        self.mpm_substep(state, 0, 0, False, twist, True, 0, False)

    @ti.kernel
    def substep_kernel_without_tools(self, state: ti.template()):
        """One substep in place, in a scene without tools (no array argument to handle)."""
        self.mpm_substep(state, 0, 0, False, 0, False, 0, False)

    @ti.kernel
    def substep_kernel_emitting(self, state: ti.template(), twist: ti.types.ndarray(), emit: ti.types.ndarray()):
        """One substep in place in a scene with emitters: the tools' twists (n_tools, 6, unused without tools)
        and the substep's emission (n_emitters, 3) from the host."""
        self.mpm_substep(state, 0, 0, False, twist, ti.static(self.model.n_tools > 0), emit, True)

    @compiled_fast
    def step(self, state: StateBuffer, control: Control):
        """Advance `state` in place by one step (the model's substeps) with the tools' twists of `control`
        (already clipped to the workspaces: tools.plan) and its emitters switched on or off."""
        model = self.model
        if model.has_emitters:
            on = control.emitting(model.n_emitters)[None]
            counts, times, _ = schedule(model.emitter_specs, *state.emission, on, model.substeps, model.dt)
            twist = control.twists if model.n_tools else np.zeros((1, 6))
        for i in range(model.substeps):
            emit = None
            if model.has_emitters:
                emit = np.stack([counts[i], counts[i + 1], times[i + 1]], axis=1).astype(np.float64)
            if self.proj is not None:
                self.projected_substep(state, control.twists if model.n_tools else None, emit)
                continue
            if model.has_emitters:
                self.substep_kernel_emitting(state, twist, emit)
            elif model.n_tools:
                self.substep_kernel(state, control.twists)
            else:
                self.substep_kernel_without_tools(state)
            if self.rigid is not None:
                self.rigid.forward(state, 0)
        if model.has_emitters:
            state.emission = (counts[-1].copy(), times[-1].copy())

    @ti.kernel
    def _stresses(self, state: ti.template(), out: ti.types.ndarray()):
        for p in range(self.n_particles):
            Fp = state.F[0, p]
            _, tau = transfer.stress(self.model, p, Fp, state.C[0, p])
            sigma = tau / Fp.determinant()
            for i, j in ti.static(ti.ndrange(3, 3)):
                out[p, i, j] = sigma[i, j]

    def stresses(self, state: StateBuffer) -> np.ndarray:
        """(N, 3, 3) Cauchy stress σ = τ/J of every particle of the state, from its model at its current F and C
        (Pa)."""
        out = np.zeros((self.n_particles, 3, 3), self.np_real)
        self._stresses(state, out)
        return out.astype(np.float64)
