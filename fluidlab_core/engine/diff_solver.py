"""The differentiable solver: the substep of solver.py on time-indexed state, and its backward.

State of substep s lives in slot s of a StateBuffer of `n_slots` (one checkpoint segment, state.py); a substep
reads slot s and writes slot s + 1 with the same forward substep as the fast solver (`Solver.mpm_substep`).
Its gradient is Taichi's reverse-mode autodiff where that is cheap, and by hand where it is not: the SVD
(svd.py, carried on to C and F by hand), the P2G scatter and the G2P gather (transfer.py). The backward of
substep s (`substep_grad`) runs these kernels, built from the same functions as the forward, in reverse order:

    F_trial = (I + Δt C) F; U, Σ, V = svd(F_trial)   the SVD only for models that need it; backward by hand
    stress: (F_new, τ) = model(...)         by hand for the built-in models (constitutive.backward_of), Taichi's
                                           autodiff for a model registered without one: one kernel per model
                                           (all models in one reverse kernel took 11 minutes to compile)
    P2G                                    backward by hand (transfer.p2g_backward)
    grid update                            autodiff (grid_update)
    the tools' advance                     backward by hand (tools.advance_pose_adjoint)
    G2P gather and advection               backward by hand (transfer.gather_backward)
    projection out of statics and walls    autodiff (g2p_project)
    rigid projection                       autodiff of rigid.py's kernels, the polar SVD by hand

What the backward reads, the forward keeps per substep (`store_*`): the grid before and after its update
(7 reals a node), the stress τ and the gather's result (15 reals a particle, 24 with rigid bodies). The backward
re-runs only the SVD (and with rigid bodies the stress and the projection's body sums). Intermediate
gradients are assigned by the first kernel to write them, or zeroed by the last to read them, so no launch
only clears. Gradients accumulate in the `.grad` of the slot fields; the checkpointing driver (checkpoint.py)
seeds them from the loss and hands them across segment boundaries.

Scatters (P2G forward, the gather's backward) go into one grid copy per CPU thread, summed afterwards: no
float atomics, and sums in a fixed order, so that gradients are the same run to run. On a GPU (no copies)
they are atomic.
"""

import numpy as np
import taichi as ti

from fluidlab_core.engine import grid, tools, transfer
from fluidlab_core.engine import svd as svd3
from fluidlab_core.engine.emitters import takes_part
from fluidlab_core.engine.solver import Solver
from fluidlab_core.engine.state import StateBuffer
from fluidlab_core.runtime import compiled_fast, fast_compilation


def slot_bytes(model) -> int:
    """Device memory of one slot of the differentiable solver, with the stores of one substep: x, v, C, F and
    their gradients per particle and slot, the tools' slot fields, and what the forward keeps for the backward
    (the grid before and after its update, 7 reals a node, 15 with two velocity fields; the stress and the
    gather's result, 15 reals a particle, 24 with rigid bodies)."""
    real_bytes = np.dtype(model.np_real).itemsize
    n = model.n_particles
    out = 2 * real_bytes * (24 * n + 24 * max(model.n_tools, 1))
    per_node = 15 if model.two_fields else 7  # two velocity fields: both fields' grids and the particle volume
    out += real_bytes * (per_node * int(np.prod(model.grid_shape)) + (24 if model.has_rigid else 15) * n)
    return out


def buffer_steps(model, grad_memory: float, grad_max_steps: int) -> int:
    """Whole steps the gradient buffer holds within `grad_memory` bytes, at most `grad_max_steps`; refuses a
    memory that holds none."""
    per_slot = slot_bytes(model)
    steps = int(min(grad_max_steps, (grad_memory // per_slot - 1) // model.substeps))
    if steps < 1:
        raise ValueError(f"grad_memory={grad_memory:.3g} bytes holds no whole step of {model.substeps} substeps "
                         f"({per_slot * (model.substeps + 1):.3g} bytes for {model.n_particles} particles); raise it")
    return steps


@ti.data_oriented
class DiffSolver(Solver):
    """The time-indexed, differentiable solver (see the module docstring); its state is `self.state`."""

    def __init__(self, model, n_slots: int, scatter_copies: int = 0):
        if model.has_flip:
            raise ValueError("the differentiable solver transfers by APIC: AFLIP (Model.flip > 0) has no backward")
        if model.has_jbar:
            raise ValueError("the J-bar average (Model.jbar) has no backward in the differentiable solver")
        if model.projection:
            raise ValueError("the liquid projection (Scene(pressure='projection')) has no differentiable solver yet")
        super().__init__(model, scatter_copies, needs_grad=True)
        real, n = model.real, model.n_particles
        self.n_slots = int(n_slots)
        self.state = StateBuffer(n, model.n_tools, self.n_slots, real, needs_grad=True, n_emitters=model.n_emitters)
        # advance_tools_grad has no adjoint of sync_real: the poses must be in the working precision here
        assert not self.state.wide_poses, "the differentiable solver's tool poses must be in the working precision"
        # per-substep intermediates, recomputed by the backward pass
        # F_trial = (I + Δt C) F, kept for the stress kernels: computed there, it made each stress gradient kernel
        # compile 2-3× longer (Taichi's simplification grows faster than a kernel; a fixed-corotated stress
        # kernel's gradient took 41 s in float64 with it inline); its gradient goes on to C and F by hand
        self.F_trial = ti.Matrix.field(3, 3, real, shape=n, needs_grad=True)
        self.U = ti.Matrix.field(3, 3, real, shape=n, needs_grad=True)  # SVD of F_trial: left rotation
        self.sig = ti.Matrix.field(3, 3, real, shape=n, needs_grad=True)  # singular values (diagonal)
        self.V = ti.Matrix.field(3, 3, real, shape=n, needs_grad=True)  # right rotation
        if self.rigid is None:
            self.F_model = ti.Matrix.field(3, 3, real, shape=n, needs_grad=True)  # F after the model
        self.tau = ti.Matrix.field(3, 3, real, shape=n, needs_grad=True)  # Kirchhoff stress (Pa)
        # G2P's gather before the projection out of statics and walls (the two have separate backwards): the
        # projection reads the stored gather (store_x_pre, ...) plus these, which stay zero; their .grad is the
        # gradient of the gathered x + Δt v (m), v (m/s) and C (1/s, with rigid bodies), for the gather's backward
        self.x_pre = ti.Vector.field(3, real, shape=n, needs_grad=True)
        self.v_pre = ti.Vector.field(3, real, shape=n, needs_grad=True)
        self.C_pre = ti.Matrix.field(3, 3, real, shape=n, needs_grad=True)
        # what the backward of substep s reads, kept by the forward: the grid before and after its update, the
        # stress and the gather's result
        n_sub = self.n_slots - 1
        shape = (n_sub,) + tuple(model.grid_shape)
        self.store_m = ti.field(real, shape=shape)
        self.store_mv = ti.Vector.field(3, real, shape=shape)
        self.store_v = ti.Vector.field(3, real, shape=shape)
        if self.two_fields:  # the fluids' field and the particle volume (grid.py)
            self.store_m_f = ti.field(real, shape=shape)
            self.store_mv_f = ti.Vector.field(3, real, shape=shape)
            self.store_v_f = ti.Vector.field(3, real, shape=shape)
            self.store_vol = ti.field(real, shape=shape)
        self.store_x_pre = ti.Vector.field(3, real, shape=(n_sub, n))
        self.store_v_pre = ti.Vector.field(3, real, shape=(n_sub, n))
        self.store_tau = ti.Matrix.field(3, 3, real, shape=(n_sub, n))  # the stress, for P2G's backward
        if self.rigid is not None:  # otherwise C_pre is C of slot s + 1
            self.store_C_pre = ti.Matrix.field(3, 3, real, shape=(n_sub, n))
        self.backward_svd = svd3.make_backward_svd(1e-10 if real == ti.f64 else 1e-5)
        # where the gather's backward scatters ∂L/∂v_i: the per-thread copies (summed afterwards) or the grid
        self._gather_target = self.copies_mv if self.private else self.grid_v.grad
        if self.two_fields:
            self._gather_target_f = self.copies_mv_f if self.private else self.grid_v_f.grad

    @property
    def substeps(self) -> int:
        return self.model.substeps

    @property
    def capacity_steps(self) -> int:
        """Whole steps the buffer holds (one checkpoint segment at most)."""
        return (self.n_slots - 1) // self.model.substeps

    def clear_grads(self):
        """Zero the gradients of every slot, and of the intermediates that the backward kernels zero after use
        (x_pre, v_pre, C_pre, U, Σ, V: in case an earlier backward stopped half-way)."""
        self.state.clear_grads()
        for f in (self.x_pre, self.v_pre, self.C_pre, self.F_trial, self.U, self.sig, self.V):
            f.grad.fill(0.0)

    # --- one substep, forward and backward ----------------------------------------------------------
    @ti.ad.grad_replaced
    def substep(self, s: int):
        """Slot s → slot s + 1, keeping what its backward reads (`store_*`)."""
        self._forward(s, True)

    def substep_no_store(self, s: int):
        """Slot s → slot s + 1 without the stores: for a forward pass whose substeps are run again before their
        backward (checkpointing's first pass over all but the last segment), or that has none."""
        self._forward(s, True, keep=False)

    @compiled_fast
    def _forward(self, s: int, whole: bool, keep: bool = True):
        """The substep's forward. Without `whole` (before its backward), only what the backward reads and the
        forward did not keep: the SVD (the stress's backward reads it), with rigid bodies the stress's F_new
        (the rigid projection reads it) and the projection's body sums (not the slot s + 1 writes)."""
        if whole:
            self.forward_kernel(s, keep)
            if self.rigid is not None:
                self.rigid.forward(self.state, s + 1)
            return
        self.svd(s)  # F_trial, and its SVD for the models that need it
        if self.rigid is not None:
            self.rigid.clear_grads()
            for k in range(len(self.model.constitutive)):
                self.stress(s, k)  # constitutive models
            self.g2p_project(s)
            for kernel in self.rigid.kernels():  # rigid projection's body sums
                kernel()

    @ti.ad.grad_for(substep)
    def substep_grad(self, s: int):
        """Add the gradients of slot s from those of slot s + 1: restore or re-run the substep's intermediates,
        then the gradients of its kernels in reverse order."""
        self._forward(s, False)
        if self.rigid is not None:
            self.rigid.backward(self.state, s + 1)
        # the hand-written backwards are plain kernels, which compile fast under fast compilation like the forward
        # ones; Taichi's reverse-mode kernels (.grad) keep the default level (runtime.fast_compilation)
        self.g2p_project.grad(s)
        with fast_compilation():
            self.g2p_gather_grad(s)
            if self.model.n_tools:
                self.advance_tools_grad(s)
        self.grid_update.grad(s)
        with fast_compilation():
            self.p2g_grad_kernel(s)
        for k in reversed(range(len(self.model.constitutive))):
            if self.model.constitutive[k].backward is not None:
                with fast_compilation():
                    self.stress_backward(s, k)
            else:
                self.stress.grad(s, k)
        with fast_compilation():
            self.svd_grad(s)

    @ti.kernel
    def forward_kernel(self, s: ti.i32, keep: ti.template()):
        """Slot s → slot s + 1 (Solver.mpm_substep), with the stores when `keep`."""
        self.mpm_substep(self.state, s, s + 1, keep, 0, False, 0, False)

    # --- SVD and stress -------------------------------------------------------------------------------
    @ti.kernel
    def svd_kernel(self, s: ti.i32):
        """F_trial = (I + Δt C) F, and U Σ Vᵀ = F_trial for particles whose model needs it (re-run before each
        substep's backward, so it also zeroes the gradients of F_trial, U, Σ, V that the stress's backward
        accumulates)."""
        for p in range(self.n_particles):
            F_tr = transfer.trial_strain(self.model, self.state.C[s, p], self.state.F[s, p])
            self.F_trial[p] = F_tr
            self.F_trial.grad[p] = ti.Matrix.zero(float, 3, 3)
            if transfer.needs_svd(self.model, p):  # one SVD call site, whatever the number of models
                self.U[p], self.sig[p], self.V[p] = svd3.svd(F_tr)
                self.U.grad[p] = ti.Matrix.zero(float, 3, 3)
                self.sig.grad[p] = ti.Matrix.zero(float, 3, 3)
                self.V.grad[p] = ti.Matrix.zero(float, 3, 3)

    @ti.kernel
    def svd_grad_kernel(self, s: ti.i32):
        """Gradient of F_trial: the stress kernels' (F_trial.grad) plus, for models with an SVD, that from U, Σ, V
        (svd.py); on to C and F: with G = ∂L/∂F_trial, ∂L/∂C += Δt G Fᵀ and ∂L/∂F += (I + Δt C)ᵀ G."""
        for p in range(self.n_particles):
            G = self.F_trial.grad[p]
            if transfer.needs_svd(self.model, p):
                G = G + self.backward_svd(self.U.grad[p], self.sig.grad[p], self.V.grad[p], self.U[p], self.sig[p],
                                          self.V[p])
            # one thread per particle: plain read-modify-writes, not atomic adds
            self.state.C.grad[s, p] = self.state.C.grad[s, p] + self.model.dt * G @ self.state.F[s, p].transpose()
            self.state.F.grad[s, p] = (self.state.F.grad[s, p] + (
                ti.Matrix.identity(float, 3) + self.model.dt * self.state.C[s, p]).transpose() @ G)

    @ti.ad.grad_replaced
    def svd(self, s: int):
        self.svd_kernel(s)

    @ti.ad.grad_for(svd)
    def svd_grad(self, s: int):
        self.svd_grad_kernel(s)

    @ti.kernel
    def stress(self, s: ti.i32, k: ti.template()):
        """(F_new, τ) of constitutive model k for its particles, from the SVD above: one kernel per model, so that
        each gradient kernel stays small."""
        for p in range(self.n_particles):
            if self.model.model[p] == k:
                if self._active(s, p):
                    prm = self.model.params[k][self.model.material[p]]
                    self.F_model[p], self.tau[p] = self.model.constitutive[k].func(
                        self.F_trial[p], self.state.C[s, p], prm, self.U[p], self.sig[p], self.V[p])
                else:  # a pool particle not yet emitted: F = I, τ = 0, whatever its slot holds
                    self.F_model[p], self.tau[p] = ti.Matrix.identity(float, 3), ti.Matrix.zero(float, 3, 3)

    @ti.kernel
    def stress_backward(self, s: ti.i32, k: ti.template()):
        """The gradient of `stress` for model k by its hand-written backward (constitutive.backward_of): from
        ∂L/∂F_new and ∂L/∂τ into those of F_trial, C of slot s and the SVD's U, Σ, V, as stress.grad would add
        them (a plain kernel: it compiles like a forward one)."""
        for p in range(self.n_particles):
            if self.model.model[p] == k:
                if self._active(s, p):  # a pool particle not yet emitted gave constants
                    prm = self.model.params[k][self.model.material[p]]
                    g_F, g_C, g_U, g_sig, g_V = self.model.constitutive[k].backward(
                        self.F_trial[p], self.state.C[s, p], prm, self.U[p], self.sig[p], self.V[p],
                        self.F_model.grad[p], self.tau.grad[p])
                    # one thread per particle: plain read-modify-writes, not atomic adds
                    self.F_trial.grad[p] = self.F_trial.grad[p] + g_F
                    self.state.C.grad[s, p] = self.state.C.grad[s, p] + g_C
                    if ti.static(self.model.constitutive[k].needs_svd):
                        self.U.grad[p] = self.U.grad[p] + g_U
                        self.sig.grad[p] = self.sig.grad[p] + g_sig
                        self.V.grad[p] = self.V.grad[p] + g_V

    @ti.func
    def _active(self, s, p):
        """Whether particle p takes part in substep s (always, without emitters)."""
        return takes_part(self.model, self.state, s, p)

    # --- P2G, grid update, G2P: backward ------------------------------------------------------------
    @ti.kernel
    def p2g_grad_kernel(self, s: ti.i32):
        """Backward of P2G (transfer.p2g_backward) with the stored stress; F of slot s + 1 is F_model (without
        rigid bodies)."""
        for p in range(self.n_particles):
            gtau = ti.Matrix.zero(float, 3, 3)
            if self._active(s, p):  # a pool particle not yet emitted scattered nothing
                gx, gv, gC, gtau_p = ti.Vector.zero(float, 3), ti.Vector.zero(float, 3), \
                    ti.Matrix.zero(float, 3, 3), ti.Matrix.zero(float, 3, 3)
                if ti.static(self.two_fields):
                    if transfer.is_fluid(self.model, p):
                        gx, gv, gC, gtau_p = transfer.p2g_backward(
                            self.model, self.grid_m_f.grad, self.grid_mv_f.grad, self.state.x[s, p],
                            self.state.v[s, p], self.state.C[s, p], self.store_tau[s, p], p)
                    else:
                        gx, gv, gC, gtau_p = transfer.p2g_backward(
                            self.model, self.grid_m.grad, self.grid_mv.grad, self.state.x[s, p], self.state.v[s, p],
                            self.state.C[s, p], self.store_tau[s, p], p)
                else:
                    gx, gv, gC, gtau_p = transfer.p2g_backward(self.model, self.grid_m.grad, self.grid_mv.grad,
                                                               self.state.x[s, p], self.state.v[s, p],
                                                               self.state.C[s, p], self.store_tau[s, p], p)
                # one thread per particle: plain read-modify-write (Taichi makes `+=` on a field an atomic add)
                self.state.x.grad[s, p] = self.state.x.grad[s, p] + gx
                self.state.v.grad[s, p] = self.state.v.grad[s, p] + gv
                self.state.C.grad[s, p] = self.state.C.grad[s, p] + gC
                gtau = gtau_p
            self.tau.grad[p] = gtau  # the first to write these in a substep's backward
            if ti.static(not self.has_rigid):
                self.F_model.grad[p] = self.state.F.grad[s + 1, p]

    @ti.kernel
    def grid_update(self, s: ti.i32):
        """Node velocities at the slot-s tool poses (for autodiff; the forward's grid update is mpm_substep's, and
        the tools' advance that follows it has its own backward, advance_tools_grad)."""
        if ti.static(self.two_fields):
            # both fields in one loop over (field, node): one inlined copy of the boundary conditions, whose
            # gradient dominates this kernel's compile time
            for f, i, j, k in ti.ndrange(2, *self.model.grid_shape):
                I = ti.Vector([i, j, k])
                c = grid.in_contact(self.model, I, self.grid_m[I], self.grid_m_f[I], self.grid_vol[I])
                v = grid.field_velocity(self.model, I, f, c, self.grid_m[I], self.grid_mv[I], self.grid_m_f[I],
                                        self.grid_mv_f[I], self.state, s)
                if f == 0:
                    self.grid_v[I] = v
                else:
                    self.grid_v_f[I] = v
        else:
            for I in ti.grouped(self.grid_m):
                self.grid_v[I] = grid.node_velocity(self.model, I, self.grid_m[I], self.grid_mv[I], self.state, s)

    @ti.kernel
    def advance_tools_grad(self, s: ti.i32):
        """Backward of the tools' advance from slot s to s + 1 (Solver._advance_tool): the gradients of the slot-s
        pose and twist from those of the slot-s + 1 pose, by hand (tools.advance_pose_adjoint; Taichi's reverse
        of it was three quarters of grid_update's reverse compile). This buffer's poses are in the working
        precision (no float64 copies to sync), and like Taichi's reverse it leaves the slot-s + 1 gradients."""
        ti.loop_config(serialize=True)
        for k in range(self.model.n_tools):
            st = self.state
            dt = ti.cast(self.model.tool_dt[None], st.pose_real)
            g_p, g_R, g_v, g_w = tools.advance_pose_adjoint(st.tool_R[k, s], st.tool_w[k, s], dt,
                                                            st.tool_p.grad[k, s + 1], st.tool_R.grad[k, s + 1])
            st.tool_p.grad[k, s] += g_p
            st.tool_R.grad[k, s] += g_R
            st.tool_v.grad[k, s] += g_v
            st.tool_w.grad[k, s] += g_w

    @ti.kernel
    def g2p_project(self, s: ti.i32):
        """The projection alone, of the stored gather (plus x_pre, v_pre, C_pre, zero, whose gradients Taichi's
        reverse of this kernel fills: substep_grad). Without rigid bodies C of slot s + 1 is the gathered C, which
        the forward wrote, and its gradient goes straight to the gather's backward."""
        for p in range(self.n_particles):
            xp, vp = grid.project(self.model, self.store_x_pre[s, p] + self.x_pre[p],
                                  self.store_v_pre[s, p] + self.v_pre[p], self.state, s)
            Cp = ti.Matrix.zero(float, 3, 3)
            if ti.static(self.has_rigid):
                Cp = self.store_C_pre[s, p] + self.C_pre[p]
            if ti.static(self.model.has_emitters):
                # pool particles: born in this substep (from the nozzle, whose pose carries the gradient), or
                # parked (slot s + 1 a copy of slot s that nothing downstream reads: its gradient is zero)
                e = self.model.emitters.emitter[p]
                if e >= 0:
                    j = self.model.emitters.pool_index[p]
                    if j >= self.state.emit_n[e, s + 1]:
                        xp, vp, Cp = self.state.x[s, p], self.state.v[s, p], ti.Matrix.zero(float, 3, 3)
                    elif j >= self.state.emit_n[e, s]:
                        xp, vp = self.model.emitters.newborn(self.model, self.state, s, p, self.state.emit_t[e, s + 1])
                        Cp = ti.Matrix.zero(float, 3, 3)
            if ti.static(self.has_rigid):
                self.rigid.x_g[p], self.rigid.v_g[p] = xp, vp
                self.rigid.C_g[p] = Cp
            else:
                self.state.x[s + 1, p], self.state.v[s + 1, p] = xp, vp

    @ti.kernel
    def g2p_gather_grad(self, s: ti.i32):
        """Backward of the gather and advection (transfer.gather_backward) with the stored node velocities. The
        kernel's grid loop also puts the substep's grid back for grid_update's backward (grid_m, grid_mv from
        the stores, their gradients zero): no separate restore launch."""
        if ti.static(self.private):
            ti.loop_config(block_dim=1)
            for c in range(self.copies):
                for p in range(c * self.chunk, ti.min((c + 1) * self.chunk, self.n_particles)):
                    self._gather_grad_particle(c, s, p)
            for I in ti.grouped(self.grid_m):
                g = ti.Vector.zero(float, 3)
                g_f = ti.Vector.zero(float, 3)
                for c in range(self.copies):
                    g += self.copies_mv[c, I[0], I[1], I[2]]
                    self.copies_mv[c, I[0], I[1], I[2]] = ti.Vector.zero(float, 3)
                    if ti.static(self.two_fields):
                        g_f += self.copies_mv_f[c, I[0], I[1], I[2]]
                        self.copies_mv_f[c, I[0], I[1], I[2]] = ti.Vector.zero(float, 3)
                self._restore_node(s, I, g, g_f)
        else:
            for I in ti.grouped(self.grid_m):
                self._restore_node(s, I, ti.Vector.zero(float, 3), ti.Vector.zero(float, 3))
            for p in range(self.n_particles):
                self._gather_grad_particle(0, s, p)

    @ti.func
    def _restore_node(self, s, I, g_v, g_v_f):
        """Node I as substep s's grid update found it, with ∂L/∂v_i = g_v (g_v_f for the fluids' field) and zero
        mass and momentum gradients."""
        self.grid_m[I] = self.store_m[s, I[0], I[1], I[2]]
        self.grid_mv[I] = self.store_mv[s, I[0], I[1], I[2]]
        self.grid_v.grad[I] = g_v
        self.grid_m.grad[I] = 0.0
        self.grid_mv.grad[I] = ti.Vector.zero(float, 3)
        if ti.static(self.two_fields):
            self.grid_m_f[I] = self.store_m_f[s, I[0], I[1], I[2]]
            self.grid_mv_f[I] = self.store_mv_f[s, I[0], I[1], I[2]]
            self.grid_vol[I] = self.store_vol[s, I[0], I[1], I[2]]
            self.grid_v_f.grad[I] = g_v_f
            self.grid_m_f.grad[I] = 0.0
            self.grid_mv_f.grad[I] = ti.Vector.zero(float, 3)

    @ti.func
    def _gather_grad_particle(self, c, s, p):
        """Particle p's part of g2p_gather_grad, its grid gradient into copy c (or atomically into the grid); a
        pool particle not yet emitted at slot s gathered nothing."""
        if self._active(s, p):
            self._gather_grad_active(c, s, p)
        else:
            self.x_pre.grad[p] = ti.Vector.zero(float, 3)
            self.v_pre.grad[p] = ti.Vector.zero(float, 3)
            if ti.static(self.has_rigid):
                self.C_pre.grad[p] = ti.Matrix.zero(float, 3, 3)

    @ti.func
    def _gather_grad_active(self, c, s, p):
        gx = self.x_pre.grad[p]
        gv = self.v_pre.grad[p]
        gC = self.state.C.grad[s + 1, p]
        if ti.static(self.has_rigid):
            gC = self.C_pre.grad[p]
            self.C_pre.grad[p] = ti.Matrix.zero(float, 3, 3)
        self.x_pre.grad[p] = ti.Vector.zero(float, 3)  # read once: zero for the next substep's projection
        self.v_pre.grad[p] = ti.Vector.zero(float, 3)
        gf = ti.Vector.zero(float, 3)
        if ti.static(self.two_fields):
            if transfer.is_fluid(self.model, p):
                gf = transfer.gather_backward(self.model, self.store_v_f, s, self._gather_target_f, c, self.private,
                                              self.state.x[s, p], self.store_v_pre[s, p], gx, gv, gC)
            else:
                gf = transfer.gather_backward(self.model, self.store_v, s, self._gather_target, c, self.private,
                                              self.state.x[s, p], self.store_v_pre[s, p], gx, gv, gC)
        else:
            gf = transfer.gather_backward(self.model, self.store_v, s, self._gather_target, c, self.private,
                                          self.state.x[s, p], self.store_v_pre[s, p], gx, gv, gC)
        # one thread per particle: a plain read-modify-write (`+=` on a field is an atomic add)
        self.state.x.grad[s, p] = self.state.x.grad[s, p] + gx + gf

