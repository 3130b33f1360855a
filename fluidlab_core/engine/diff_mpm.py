"""The differentiable MLS-MPM substep: the forward solver's physics (mpm.py) on time-indexed particle state,
with gradients by Taichi's reverse-mode autodiff where it is cheap and by hand where it is not (the SVD, the
P2G scatter and the G2P gather).

State of substep s lives in slot s of a buffer of `n_slots` (one checkpoint segment): x[s, p], v[s, p],
C[s, p], F[s, p] and each tool's pose and held twist (tool_p, tool_R, tool_v, tool_w)[k, s]. A substep
reads slot s and writes slot s + 1, as kernels in physical order:

    U, Σ, V = svd((I + Δt C) F)            only for models that need it; backward by hand (svd.py), carried on
                                           to C and F by hand
    stress: (F_new, τ) = model((I + Δt C) F, C, U, Σ, V); autodiff, one kernel per model
    P2G:  scatter m and m v + A (x_i − x_p); backward by hand (a gather, p2g_grad_kernel)
    grid: v_i = (mv)_i / m_i + Δt g, then statics, tools at (tool_p, tool_R)[s], walls; then the tools move,
          p ← p + Δt v_tool, R ← exp([ω]× Δt) R; autodiff
    G2P:  gather v, C; x ← x + Δt v; backward by hand (g2p_gather_grad). Then the projection out of statics
          and walls; autodiff (g2p_project)
    rigid (when the scene has rigid bodies): shape matching as in rigid.py, in six kernels, the polar
          decomposition R = U Vᵀ of A/|A| by the same SVD backward; autodiff

Scatters (P2G forward, the gather's backward) go into one grid copy per CPU thread, summed afterwards, as in
the fast solver: no float atomics, and sums in a fixed order, so that gradients are the same run to run. On
a GPU (no copies) they are atomic.

The backward of substep s (`substep_grad`) needs the substep's intermediates. The forward keeps the grid
before and after its update, the stress τ and the gather's result per substep (`store_*`, 7 reals a node and
15 a particle, 24 with rigid bodies); the backward kernels read them where they are (the grid update's
backward finds its grid put back by the gather's backward), it re-runs only the SVD (and with rigid bodies the
stress and the projection's body sums), then runs the gradients in reverse order. Intermediate gradients are
assigned by the first kernel to write them, or zeroed by the last to read them, so no launch only clears.
Gradients accumulate in the `.grad` of the slot fields; the checkpointing driver (checkpoint.py) seeds them
from the loss and hands them across segment boundaries.

The forward runs as one kernel of three parallel loops (`forward_kernel`); the backward differentiates the
separate kernels above, built from the same functions. Each parallel loop is a pass over memory and a launch
(an empty one costs ~0.02 ms from Python here, measured), so tiny loops (tools, bodies) are serialised and
work is grouped into few kernels and few passes.

Differences from the forward solver (mpm.py), all within floating-point round-off of it: the polar
decomposition of the rigid projection goes through the SVD, and tool poses advance in the working precision
instead of float64 numpy.
"""

import numpy as np
import taichi as ti

from fluidlab_core.engine import constitutive
from fluidlab_core.engine import svd as svd3
from fluidlab_core.engine.svd import make_backward_svd


rotation_from_rotvec = svd3.rotation_from_rotvec  # exp([w]×), finite derivatives at w = 0


@ti.data_oriented
class DiffMPMSolver:
    """Time-indexed twin of an `MPMSolver` (whose constants, stencil and wall rules it shares)."""

    def __init__(self, fast, n_slots: int):
        self.fast = fast
        spec = fast.spec
        real = fast.real
        self.real = real
        n = fast.n_particles
        self.n_particles = n
        self.n_slots = int(n_slots)
        self.dt, self.dx, self.inv_dx = fast.dt, fast.dx, fast.inv_dx
        self.n_tools = len(spec.tools)
        self.tools = spec.tools
        self.colliders = spec.colliders
        shape = (self.n_slots, n)

        # particle state per substep of the segment
        self.x = ti.Vector.field(3, real, shape=shape, needs_grad=True)  # position (m)
        self.v = ti.Vector.field(3, real, shape=shape, needs_grad=True)  # velocity (m/s)
        self.C = ti.Matrix.field(3, 3, real, shape=shape, needs_grad=True)  # APIC affine velocity (1/s)
        self.F = ti.Matrix.field(3, 3, real, shape=shape, needs_grad=True)  # deformation gradient
        # per-substep intermediates, recomputed by the backward pass
        self.U = ti.Matrix.field(3, 3, real, shape=n, needs_grad=True)  # SVD of (I + Δt C) F: left rotation
        self.sig = ti.Matrix.field(3, 3, real, shape=n, needs_grad=True)  # singular values (diagonal)
        self.V = ti.Matrix.field(3, 3, real, shape=n, needs_grad=True)  # right rotation
        self.F_model = ti.Matrix.field(3, 3, real, shape=n, needs_grad=True)  # F after the model
        self.tau = ti.Matrix.field(3, 3, real, shape=n, needs_grad=True)  # Kirchhoff stress (Pa)
        # G2P's gather before the projection out of statics and walls (the two have separate backwards): the
        # projection reads the stored gather (store_x_pre, ...) plus these, which stay zero; their .grad is the
        # gradient of the gathered x + Δt v (m), v (m/s) and C (1/s, with rigid bodies), for the gather's backward
        self.x_pre = ti.Vector.field(3, real, shape=n, needs_grad=True)
        self.v_pre = ti.Vector.field(3, real, shape=n, needs_grad=True)
        self.C_pre = ti.Matrix.field(3, 3, real, shape=n, needs_grad=True)
        self.grid_m = ti.field(real, shape=fast.grid_shape, needs_grad=True)  # node mass (kg)
        self.grid_mv = ti.Vector.field(3, real, shape=fast.grid_shape, needs_grad=True)  # node momentum
        self.grid_v = ti.Vector.field(3, real, shape=fast.grid_shape, needs_grad=True)  # node velocity after BCs
        # what the backward of substep s reads, kept by the forward so that it need not re-run P2G, the grid
        # update and the gather: the grid before and after its update, and the gather's result
        n_sub = self.n_slots - 1
        self.store_m = ti.field(real, shape=(n_sub,) + tuple(fast.grid_shape))
        self.store_mv = ti.Vector.field(3, real, shape=(n_sub,) + tuple(fast.grid_shape))
        self.store_v = ti.Vector.field(3, real, shape=(n_sub,) + tuple(fast.grid_shape))
        self.store_x_pre = ti.Vector.field(3, real, shape=(n_sub, n))
        self.store_v_pre = ti.Vector.field(3, real, shape=(n_sub, n))
        self.store_tau = ti.Matrix.field(3, 3, real, shape=(n_sub, n))  # the stress, for P2G's backward
        if fast.rigid is not None:  # otherwise C_pre is C of slot s + 1
            self.store_C_pre = ti.Matrix.field(3, 3, real, shape=(n_sub, n))
        # per-thread copies of a grid gradient, for scatters without atomics (as MPMSolver's P2G)
        # (on a GPU, scatter_copies is 0: atomic scatters instead)
        self.private = fast.scatter_copies > 0
        self.copies = max(fast.scatter_copies, 1)
        self.chunk = -(-n // self.copies)
        if self.private:
            self.grid_private = ti.Vector.field(3, real, shape=(self.copies,) + tuple(fast.grid_shape))
            self.grid_private_m = ti.field(real, shape=(self.copies,) + tuple(fast.grid_shape))
        # tools: pose at each slot and the twist held over substep s (world frame)
        nt = max(self.n_tools, 1)
        self.tool_p = ti.Vector.field(3, real, shape=(nt, self.n_slots), needs_grad=True)  # origin (m)
        self.tool_R = ti.Matrix.field(3, 3, real, shape=(nt, self.n_slots), needs_grad=True)  # tool to world
        self.tool_v = ti.Vector.field(3, real, shape=(nt, self.n_slots), needs_grad=True)  # linear (m/s)
        self.tool_w = ti.Vector.field(3, real, shape=(nt, self.n_slots), needs_grad=True)  # angular (rad/s)

        self.models = [constitutive.MODELS[name] for name in fast.model_names]
        self.svd_models = [k for k, name in enumerate(fast.model_names) if name not in constitutive.NO_SVD]
        self.backward_svd = make_backward_svd(1e-10 if real == ti.f64 else 1e-5)

        self.rigid = fast.rigid
        self.has_rigid = fast.rigid is not None
        if self.rigid is not None:
            nb = self.rigid.n_bodies
            self.x_g = ti.Vector.field(3, real, shape=n, needs_grad=True)  # G2P result before the projection
            self.v_g = ti.Vector.field(3, real, shape=n, needs_grad=True)
            self.C_g = ti.Matrix.field(3, 3, real, shape=n, needs_grad=True)
            self.body_mass = ti.field(real, shape=nb)  # kg (constant)
            self.com_sum = ti.Vector.field(3, real, shape=nb, needs_grad=True)  # Σ m x (kg m)
            self.momentum = ti.Vector.field(3, real, shape=nb, needs_grad=True)  # Σ m v (kg m/s)
            self.A = ti.Matrix.field(3, 3, real, shape=nb, needs_grad=True)  # Σ m (x − c) qᵀ
            self.A_n = ti.Matrix.field(3, 3, real, shape=nb, needs_grad=True)  # A / |A|
            self.L = ti.Vector.field(3, real, shape=nb, needs_grad=True)  # angular momentum about c
            self.U_b = ti.Matrix.field(3, 3, real, shape=nb, needs_grad=True)  # SVD of A_n
            self.sig_b = ti.Matrix.field(3, 3, real, shape=nb, needs_grad=True)
            self.V_b = ti.Matrix.field(3, 3, real, shape=nb, needs_grad=True)
            self.R = ti.Matrix.field(3, 3, real, shape=nb, needs_grad=True)  # rotation from rest
            self.inertia = ti.Matrix.field(3, 3, real, shape=nb, needs_grad=True)  # about c (kg m²)
            self.omega = ti.Vector.field(3, real, shape=nb, needs_grad=True)  # angular velocity (rad/s)
            self._set_body_mass()
        # NaN watch on gradients: bits 1 x, 2 v, 4 C, 8 F, 16 tools (GRAD_FIELDS)
        self.bad = ti.field(ti.i32, shape=())

    @ti.kernel
    def _set_body_mass(self):
        for p in range(self.n_particles):
            b = self.rigid.body[p]
            if b >= 0:
                self.body_mass[b] += self.fast.mass[p]

    # --- host access --------------------------------------------------------------------------------
    @property
    def np_real(self):
        return np.float64 if self.real == ti.f64 else np.float32

    @ti.kernel
    def _write_slot(self, s: ti.i32, x: ti.types.ndarray(), v: ti.types.ndarray(), C: ti.types.ndarray(),
                    F: ti.types.ndarray()):
        for p in range(self.n_particles):
            for i in ti.static(range(3)):
                self.x[s, p][i] = x[p, i]
                self.v[s, p][i] = v[p, i]
                for j in ti.static(range(3)):
                    self.C[s, p][i, j] = C[p, i, j]
                    self.F[s, p][i, j] = F[p, i, j]

    @ti.kernel
    def _read_slot(self, s: ti.i32, x: ti.types.ndarray(), v: ti.types.ndarray(), C: ti.types.ndarray(),
                   F: ti.types.ndarray(), grad: ti.i32):
        for p in range(self.n_particles):
            for i in ti.static(range(3)):
                if grad:
                    x[p, i] = self.x.grad[s, p][i]
                    v[p, i] = self.v.grad[s, p][i]
                else:
                    x[p, i] = self.x[s, p][i]
                    v[p, i] = self.v[s, p][i]
                for j in ti.static(range(3)):
                    if grad:
                        C[p, i, j] = self.C.grad[s, p][i, j]
                        F[p, i, j] = self.F.grad[s, p][i, j]
                    else:
                        C[p, i, j] = self.C[s, p][i, j]
                        F[p, i, j] = self.F[s, p][i, j]

    @ti.kernel
    def _add_slot_grad(self, s: ti.i32, x: ti.types.ndarray(), v: ti.types.ndarray(), C: ti.types.ndarray(),
                       F: ti.types.ndarray()):
        for p in range(self.n_particles):
            for i in ti.static(range(3)):
                self.x.grad[s, p][i] += x[p, i]
                self.v.grad[s, p][i] += v[p, i]
                for j in ti.static(range(3)):
                    self.C.grad[s, p][i, j] += C[p, i, j]
                    self.F.grad[s, p][i, j] += F[p, i, j]

    def write_state(self, s: int, state: dict):
        """Put a particle state {x, v, C, F} and tool poses {tool_position, tool_rotation} into slot s."""
        r = self.np_real
        self._write_slot(s, *(np.ascontiguousarray(state[k], dtype=r) for k in ("x", "v", "C", "F")))
        if self.n_tools:
            self.write_tool_pose(s, state["tool_position"], state["tool_rotation"])

    def read_state(self, s: int, grad: bool = False) -> dict:
        """Particle state (or its gradient) of slot s as numpy arrays, tool poses included."""
        n, r = self.n_particles, self.np_real
        out = {"x": np.zeros((n, 3), r), "v": np.zeros((n, 3), r), "C": np.zeros((n, 3, 3), r),
               "F": np.zeros((n, 3, 3), r)}
        self._read_slot(s, out["x"], out["v"], out["C"], out["F"], int(grad))
        if self.n_tools:
            p = (self.tool_p.grad if grad else self.tool_p).to_numpy()[: self.n_tools, s]
            R = (self.tool_R.grad if grad else self.tool_R).to_numpy()[: self.n_tools, s]
            out["tool_position"], out["tool_rotation"] = p.astype(np.float64), R.astype(np.float64)
        return out

    def add_state_grad(self, s: int, grad: dict):
        """Add gradients {x, v, C, F, tool_position, tool_rotation} (any subset) into slot s."""
        if grad.get("C") is None and grad.get("F") is None:
            self.add_steps_grad([s], [grad])
            return
        n, r = self.n_particles, self.np_real

        def array(key, shape):
            g = grad.get(key)
            return np.zeros(shape, r) if g is None else np.ascontiguousarray(g, dtype=r)

        self._add_slot_grad(s, array("x", (n, 3)), array("v", (n, 3)), array("C", (n, 3, 3)), array("F", (n, 3, 3)))
        self.add_steps_grad([s], [{k: grad[k] for k in ("tool_position", "tool_rotation") if k in grad}])

    @ti.kernel
    def _write_tool_pose(self, s: ti.i32, p: ti.types.ndarray(), R: ti.types.ndarray()):
        ti.loop_config(serialize=True)
        for k in range(self.n_tools):
            for i in ti.static(range(3)):
                self.tool_p[k, s][i] = p[k, i]
                for j in ti.static(range(3)):
                    self.tool_R[k, s][i, j] = R[k, i, j]

    def write_tool_pose(self, s: int, position, rotation):
        r = self.np_real
        self._write_tool_pose(s, np.ascontiguousarray(position, dtype=r), np.ascontiguousarray(rotation, dtype=r))

    @ti.kernel
    def _write_twists(self, twist: ti.types.ndarray(), substeps: ti.i32):
        ti.loop_config(serialize=True)
        for j, k, i in ti.ndrange(twist.shape[0], self.n_tools, substeps):
            for d in ti.static(range(3)):
                self.tool_v[k, j * substeps + i][d] = twist[j, k, d]
                self.tool_w[k, j * substeps + i][d] = twist[j, k, 3 + d]

    def write_twists(self, twists: np.ndarray, substeps: int):
        """Hold the twists (K, n_tools, 6) of K steps over their substeps, from slot 0 on (one launch)."""
        if self.n_tools and len(twists):
            self._write_twists(np.ascontiguousarray(twists, dtype=self.np_real), substeps)

    @ti.kernel
    def _read_steps(self, slots: ti.types.ndarray(), x: ti.types.ndarray(), v: ti.types.ndarray(),
                    tp: ti.types.ndarray(), tR: ti.types.ndarray()):
        for j, p in ti.ndrange(slots.shape[0], self.n_particles):
            s = slots[j]
            for i in ti.static(range(3)):
                x[j, p, i] = self.x[s, p][i]
                v[j, p, i] = self.v[s, p][i]
        ti.loop_config(serialize=True)
        for j, k in ti.ndrange(slots.shape[0], self.n_tools):
            s = slots[j]
            for i in ti.static(range(3)):
                tp[j, k, i] = self.tool_p[k, s][i]
                for d in ti.static(range(3)):
                    tR[j, k, i, d] = self.tool_R[k, s][i, d]

    def read_steps(self, slots):
        """Positions, velocities, tool origins and rotations of several slots in one launch: arrays with a
        leading axis over `slots`, in the working precision (the loss takes float64 rows of them)."""
        slots = np.ascontiguousarray(slots, dtype=np.int32)
        m, n, r, nt = len(slots), self.n_particles, self.np_real, self.n_tools
        x, v = np.zeros((m, n, 3), r), np.zeros((m, n, 3), r)
        tp, tR = np.zeros((m, max(nt, 1), 3), r), np.zeros((m, max(nt, 1), 3, 3), r)
        if m:
            self._read_steps(slots, x, v, tp, tR)
        return x, v, tp[:, :nt], tR[:, :nt]

    @ti.kernel
    def _add_steps_xv_grad(self, slots: ti.types.ndarray(), x: ti.types.ndarray(), v: ti.types.ndarray()):
        for j, p in ti.ndrange(slots.shape[0], self.n_particles):
            s = slots[j]
            self.x.grad[s, p] += ti.Vector([x[j, p, 0], x[j, p, 1], x[j, p, 2]])
            self.v.grad[s, p] += ti.Vector([v[j, p, 0], v[j, p, 1], v[j, p, 2]])

    @ti.kernel
    def _add_steps_tool_grad(self, slots: ti.types.ndarray(), p: ti.types.ndarray(), R: ti.types.ndarray()):
        ti.loop_config(serialize=True)
        for j, k in ti.ndrange(slots.shape[0], self.n_tools):
            s = slots[j]
            self.tool_p.grad[k, s] += ti.Vector([p[j, k, i] for i in ti.static(range(3))])
            self.tool_R.grad[k, s] += ti.Matrix([[R[j, k, i, d] for d in ti.static(range(3))]
                                                 for i in ti.static(range(3))])

    def add_steps_grad(self, slots, grads: list):
        """Add loss gradients {x, v, tool_position, tool_rotation} (any subset, losses.GRAD_KEYS), one dict per
        slot, into those slots: one launch for the particles and one for the tools, whatever the number of
        slots (a launch per step cost as much as a substep's gather at small sizes)."""
        slots = np.ascontiguousarray(slots, dtype=np.int32)
        m, n, r, nt = len(slots), self.n_particles, self.np_real, self.n_tools

        def stacked(key, shape):
            out = np.zeros((m,) + shape, r)
            for j, g in enumerate(grads):
                if g.get(key) is not None:
                    out[j] = g[key]
            return out

        if any(g.get("x") is not None or g.get("v") is not None for g in grads):
            self._add_steps_xv_grad(slots, stacked("x", (n, 3)), stacked("v", (n, 3)))
        if nt and any(g.get("tool_position") is not None or g.get("tool_rotation") is not None for g in grads):
            self._add_steps_tool_grad(slots, stacked("tool_position", (nt, 3)), stacked("tool_rotation", (nt, 3, 3)))

    @ti.kernel
    def _step_grad_end(self, s0: ti.i32, s1: ti.i32, out: ti.types.ndarray()):
        self.bad[None] = 0
        for p in range(self.n_particles):
            bits = 0
            if not (ti.abs(self.x.grad[s0, p]).max() < 1e30):
                bits |= 1
            if not (ti.abs(self.v.grad[s0, p]).max() < 1e30):
                bits |= 2
            if not (ti.abs(self.C.grad[s0, p]).max() < 1e30):
                bits |= 4
            if not (ti.abs(self.F.grad[s0, p]).max() < 1e30):
                bits |= 8
            if bits > 0:
                ti.atomic_or(self.bad[None], bits)
        ti.loop_config(serialize=True)
        for k in range(self.n_tools):
            if not (ti.abs(self.tool_p.grad[k, s0]).max() < 1e30 and ti.abs(self.tool_R.grad[k, s0]).max() < 1e30):
                self.bad[None] |= 16
            for i in ti.static(range(6)):
                out[k * 6 + i] = 0.0
            for s in range(s0, s1):
                for i in ti.static(range(3)):
                    out[k * 6 + i] += self.tool_v.grad[k, s][i]
                    out[k * 6 + 3 + i] += self.tool_w.grad[k, s][i]
        out[self.n_tools * 6] = self.bad[None]

    GRAD_FIELDS = ("positions (x)", "velocities (v)", "affine velocities (C)", "deformation gradients (F)",
                   "tool poses")

    def step_grad_end(self, s0: int, s1: int):
        """After the backward of the substeps s0 … s1 − 1: the (n_tools, 6) gradient of the twists held over them,
        and the names of the slot-s0 gradient fields holding a NaN or infinity (one launch)."""
        out = np.zeros(self.n_tools * 6 + 1, self.np_real)
        self._step_grad_end(s0, s1, out)
        bits = int(out[-1])
        bad = [name for i, name in enumerate(self.GRAD_FIELDS) if bits & (1 << i)]
        return out[:-1].reshape(self.n_tools, 6).astype(np.float64), bad

    @ti.kernel
    def _twist_grads(self, substeps: ti.i32, out: ti.types.ndarray()):
        ti.loop_config(serialize=True)
        for j, k in ti.ndrange(out.shape[0], self.n_tools):
            for i in ti.static(range(6)):
                out[j, k, i] = 0.0
            for s in range(j * substeps, (j + 1) * substeps):
                for i in ti.static(range(3)):
                    out[j, k, i] += self.tool_v.grad[k, s][i]
                    out[j, k, 3 + i] += self.tool_w.grad[k, s][i]

    def twist_grads(self, n_steps: int, substeps: int) -> np.ndarray:
        """(n_steps, n_tools, 6) gradients of the twists held over each step of the buffer (one launch)."""
        out = np.zeros((n_steps, self.n_tools, 6), self.np_real)
        if self.n_tools and n_steps:
            self._twist_grads(substeps, out)
        return out.astype(np.float64)

    def nonfinite_grad_fields(self, s: int) -> list[str]:
        """Names of the slot-s gradient fields holding a NaN or infinity (one launch)."""
        return self.step_grad_end(s, s)[1]

    @ti.kernel
    def _copy_slot(self, src: ti.i32, dst: ti.i32):
        for p in range(self.n_particles):
            self.x[dst, p] = self.x[src, p]
            self.v[dst, p] = self.v[src, p]
            self.C[dst, p] = self.C[src, p]
            self.F[dst, p] = self.F[src, p]
        ti.loop_config(serialize=True)
        for k in range(self.n_tools):
            self.tool_p[k, dst] = self.tool_p[k, src]
            self.tool_R[k, dst] = self.tool_R[k, src]

    def copy_slot(self, src: int, dst: int):
        self._copy_slot(src, dst)

    def clear_grads(self):
        """Zero the gradients of every slot, and of the intermediates that the backward kernels zero after use
        (x_pre, v_pre, C_pre, U, Σ, V: in case an earlier backward stopped half-way)."""
        for f in (self.x, self.v, self.C, self.F, self.tool_p, self.tool_R, self.tool_v, self.tool_w, self.x_pre,
                  self.v_pre, self.C_pre, self.U, self.sig, self.V):
            f.grad.fill(0.0)

    @ti.kernel
    def restore_rigid(self):
        """With rigid bodies, before a substep's backward: zero the gradients that the rigid projection's backward
        accumulates (the other intermediates are read from the stores, and their gradients zeroed by the kernel
        that reads them last)."""
        for p in range(self.n_particles):
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

    @ti.func
    def _strain(self, s, p):
        """F_trial = (I + Δt C) F, the deformation gradient before the constitutive model."""
        return (ti.Matrix.identity(float, 3) + self.dt * self.C[s, p]) @ self.F[s, p]

    @ti.kernel
    def svd_kernel(self, s: ti.i32):
        """U Σ Vᵀ = F_trial for particles whose model needs it (re-run before each substep's backward, so it also
        zeroes the gradients of U, Σ, V that the stress's backward accumulates)."""
        for p in range(self.n_particles):
            for k in ti.static(self.svd_models):
                if self.fast.model[p] == k:
                    self.U[p], self.sig[p], self.V[p] = svd3.svd(self._strain(s, p))
                    self.U.grad[p] = ti.Matrix.zero(float, 3, 3)
                    self.sig.grad[p] = ti.Matrix.zero(float, 3, 3)
                    self.V.grad[p] = ti.Matrix.zero(float, 3, 3)

    @ti.kernel
    def svd_grad_kernel(self, s: ti.i32):
        """Gradient of F_trial from those of U, Σ, V (svd.py), on to C and F: with G = ∂L/∂F_trial,
        ∂L/∂C += Δt G Fᵀ and ∂L/∂F += (I + Δt C)ᵀ G."""
        for p in range(self.n_particles):
            for k in ti.static(self.svd_models):
                if self.fast.model[p] == k:
                    G = self.backward_svd(self.U.grad[p], self.sig.grad[p], self.V.grad[p], self.U[p], self.sig[p],
                                          self.V[p])
                    # one thread per particle: plain read-modify-writes, not atomic adds
                    self.C.grad[s, p] = self.C.grad[s, p] + self.dt * G @ self.F[s, p].transpose()
                    self.F.grad[s, p] = (self.F.grad[s, p]
                                         + (ti.Matrix.identity(float, 3) + self.dt * self.C[s, p]).transpose() @ G)

    @ti.ad.grad_replaced
    def svd(self, s: int):
        self.svd_kernel(s)

    @ti.ad.grad_for(svd)
    def svd_grad(self, s: int):
        self.svd_grad_kernel(s)

    @ti.kernel
    def stress(self, s: ti.i32, k: ti.template()):
        """(F_new, τ) of constitutive model k for its particles: one kernel per model, so that each gradient
        kernel stays small (all models in one reverse kernel took 11 minutes to compile)."""
        for p in range(self.n_particles):
            if self.fast.model[p] == k:
                prm = self.fast.material_params[self.fast.material[p]]
                self.F_model[p], self.tau[p] = self.models[k](self._strain(s, p), self.C[s, p], prm, self.U[p],
                                                               self.sig[p], self.V[p])

    @ti.func
    def _p2g_terms(self, s, p):
        """A particle's P2G inputs: stencil, mass, momentum m v and affine momentum A = k τ + m C with
        k = −Δt V⁰ 4/Δx² (mpm.py)."""
        base, fx, w = self.fast._stencil(self.x[s, p])
        mp = self.fast.mass[p]
        k_tau = -self.dt * self.fast.rest_volume[p] * 4.0 * self.inv_dx * self.inv_dx
        affine = k_tau * self.store_tau[s, p] + mp * self.C[s, p]
        return base, fx, w, mp, k_tau, mp * self.v[s, p], affine

    @ti.kernel
    def p2g_grad_kernel(self, s: ti.i32):
        """Backward of P2G by hand (Taichi's reverse adds atomically into every particle gradient at every node).
        With d_i = (offset − f) Δx, G_i = ∂L/∂(mv)_i and g_i = ∂L/∂m_i:
            ḡ = Σ_i w G_i,  ∂L/∂v += m ḡ,  ∂L/∂A = Σ_i w G_i d_iᵀ → ∂L/∂τ += k ∂L/∂A, ∂L/∂C += m ∂L/∂A
            ∂L/∂f = Σ_i (G_i·(m v + A d_i) + m g_i) ∇_f w − Δx Aᵀ ḡ,  ∂L/∂x += ∂L/∂f / Δx
        and F of slot s + 1 is F_model (without rigid bodies). τ is the stored one (store_tau)."""
        for p in range(self.n_particles):
            base, fx, w, mp, k_tau, momentum, affine = self._p2g_terms(s, p)
            dw = [fx - 1.5, -2.0 * (fx - 1.0), fx - 0.5]
            # the stencil loop nested by axis, with d_i = (offset − f) Δx split into a per-particle part and the
            # integer offset: m v + A d_i = q + Δx A offset with q = m v − Δx A f, and
            # Σ_i w G_i d_iᵀ = Δx (Σ_i w G_i offsetᵀ − ḡ fᵀ). Measured 20 % faster than the flat loop.
            A_dx = self.dx * affine
            q = momentum - A_dx @ fx
            g_mom = ti.Vector.zero(float, 3)
            g_off = ti.Matrix.zero(float, 3, 3)  # Σ_i w G_i offsetᵀ
            g_f = ti.Vector.zero(float, 3)
            for a in ti.static(range(3)):
                q_a = q + a * A_dx[:, 0]
                for b in ti.static(range(3)):
                    w_ab = w[a][0] * w[b][1]
                    dw_a, dw_b = dw[a][0] * w[b][1], w[a][0] * dw[b][1]
                    q_ab = q_a + b * A_dx[:, 1]
                    for c in ti.static(range(3)):
                        I = base + ti.Vector([a, b, c])
                        G = self.grid_mv.grad[I]
                        wG = (w_ab * w[c][2]) * G
                        g_mom += wG
                        for d, o in ti.static(enumerate((a, b, c))):
                            if ti.static(o > 0):
                                g_off[:, d] += o * wG
                        g_weight = G.dot(q_ab + c * A_dx[:, 2]) + self.grid_m.grad[I] * mp
                        g_f += g_weight * ti.Vector([dw_a * w[c][2], dw_b * w[c][2], w_ab * dw[c][2]])
            g_A = self.dx * (g_off - g_mom.outer_product(fx))
            g_f -= self.dx * (affine.transpose() @ g_mom)
            # one thread per particle: plain read-modify-write (Taichi makes `+=` on a field an atomic add)
            self.x.grad[s, p] = self.x.grad[s, p] + self.inv_dx * g_f
            self.v.grad[s, p] = self.v.grad[s, p] + mp * g_mom
            self.C.grad[s, p] = self.C.grad[s, p] + mp * g_A
            self.tau.grad[p] = k_tau * g_A  # the first to write these in a substep's backward
            if ti.static(not self.has_rigid):
                self.F_model.grad[p] = self.F.grad[s + 1, p]

    @ti.kernel
    def grid_update(self, s: ti.i32):
        """Node velocities: gravity, statics, tools at their slot-s pose, walls; then the tools move to their slot
        s + 1 pose: p ← p + Δt v, R ← exp([ω]× Δt) R."""
        for I in ti.grouped(self.grid_m):
            self.grid_v[I] = self._node_velocity(I, self.grid_m[I], self.grid_mv[I], s)
        ti.loop_config(serialize=True)  # as _advance_tools: a ti.func call at top level cannot be differentiated
        for k in range(self.n_tools):
            self.tool_p[k, s + 1] = self.tool_p[k, s] + self.dt * self.tool_v[k, s]
            self.tool_R[k, s + 1] = rotation_from_rotvec(self.tool_w[k, s] * self.dt) @ self.tool_R[k, s]

    @ti.func
    def _node_velocity(self, I, m, mv, s):
        """Velocity of node I from its mass and momentum: gravity, statics, tools, walls."""
        vn = ti.Vector.zero(float, 3)
        if m > self.fast.mass_floor:  # see MPMSolver.mass_floor
            vn = mv / m + self.dt * ti.Vector(self.fast.gravity)
            xn = ti.Vector(self.fast.origin) + I * self.dx
            for k in ti.static(range(len(self.colliders))):
                vn = self.colliders[k].grid(xn, vn)
            for k in ti.static(range(self.n_tools)):
                vn = self.tools[k].contact_at(xn, vn, self.tool_p[k, s], self.tool_R[k, s], self.tool_v[k, s],
                                              self.tool_w[k, s])
            vn = self.fast._walls(xn, vn)
        return vn

    @ti.func
    def _advance_tools(self, s):
        """p ← p + Δt v, R ← exp([ω]× Δt) R (the forward kernel's; grid_update repeats it inline)."""
        ti.loop_config(serialize=True)
        for k in range(self.n_tools):
            self.tool_p[k, s + 1] = self.tool_p[k, s] + self.dt * self.tool_v[k, s]
            self.tool_R[k, s + 1] = rotation_from_rotvec(self.tool_w[k, s] * self.dt) @ self.tool_R[k, s]

    @ti.func
    def _project(self, xp, new_v):
        """Out of statics and back from past the walls."""
        for k in ti.static(range(len(self.colliders))):
            xp, new_v = self.colliders[k].particle(xp, new_v)
        return self.fast._clamp_to_walls(xp, new_v)

    @ti.func
    def _scatter_particle(self, c, s, p, keep: ti.template()):
        """P2G of particle p: strain update, constitutive model (its SVD inline), scatter into grid copy c (or
        atomically into the grid)."""
        Cp = self.C[s, p]
        Fp = self._strain(s, p)
        tau = ti.Matrix.zero(float, 3, 3)
        prm = self.fast.material_params[self.fast.material[p]]
        for k in ti.static(range(len(self.fast.models))):
            if self.fast.model[p] == k:
                Fp, tau = self.fast.models[k](Fp, Cp, prm)
        if ti.static(self.has_rigid):
            self.F_model[p] = Fp
        else:
            self.F[s + 1, p] = Fp
        if ti.static(keep):
            self.store_tau[s, p] = tau
        base, fx, w = self.fast._stencil(self.x[s, p])
        mp = self.fast.mass[p]
        affine = (-self.dt * self.fast.rest_volume[p] * 4.0 * self.inv_dx * self.inv_dx) * tau + mp * Cp
        momentum = mp * self.v[s, p]
        for offset in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
            dpos = (offset - fx) * self.dx
            weight = w[offset[0]][0] * w[offset[1]][1] * w[offset[2]][2]
            if ti.static(self.private):
                i, j, k = base[0] + offset[0], base[1] + offset[1], base[2] + offset[2]
                self.grid_private[c, i, j, k] = self.grid_private[c, i, j, k] + weight * (momentum + affine @ dpos)
                self.grid_private_m[c, i, j, k] = self.grid_private_m[c, i, j, k] + weight * mp
            else:
                self.grid_mv[base + offset] += weight * (momentum + affine @ dpos)
                self.grid_m[base + offset] += weight * mp

    @ti.kernel
    def forward_kernel(self, s: ti.i32, keep: ti.template()):
        """One substep's forward in three parallel loops (a parallel launch is the main cost at small sizes):
        particles (strain, stress, P2G), nodes (sum of the grid copies, grid update, the stores), then, after
        the tools move, particles again (G2P gather, projection). The backward differentiates the separate
        kernels (stress, grid_update, g2p_project) and the hand-written ones, on the same functions. Without
        `keep`, nothing is stored for a backward (a pass whose substeps are run again before their backward)."""
        if ti.static(self.private):
            ti.loop_config(block_dim=1)
            for c in range(self.copies):
                for p in range(c * self.chunk, ti.min((c + 1) * self.chunk, self.n_particles)):
                    self._scatter_particle(c, s, p, keep)
        else:
            for I in ti.grouped(self.grid_m):
                self.grid_m[I] = 0.0
                self.grid_mv[I] = ti.Vector.zero(float, 3)
            for p in range(self.n_particles):
                self._scatter_particle(0, s, p, keep)
        for I in ti.grouped(self.grid_m):
            m = 0.0
            mv = ti.Vector.zero(float, 3)
            if ti.static(self.private):
                for c in range(self.copies):
                    m += self.grid_private_m[c, I[0], I[1], I[2]]
                    mv += self.grid_private[c, I[0], I[1], I[2]]
                    self.grid_private_m[c, I[0], I[1], I[2]] = 0.0
                    self.grid_private[c, I[0], I[1], I[2]] = ti.Vector.zero(float, 3)
            else:
                m, mv = self.grid_m[I], self.grid_mv[I]
            vn = self._node_velocity(I, m, mv, s)
            self.grid_v[I] = vn
            if ti.static(keep):
                self.store_m[s, I], self.store_mv[s, I], self.store_v[s, I] = m, mv, vn
        self._advance_tools(s)
        for p in range(self.n_particles):
            new_v, new_C = self.fast._gather(self.grid_v, self.x[s, p])
            xp = self.x[s, p] + self.dt * new_v
            if ti.static(keep):
                self.store_x_pre[s, p], self.store_v_pre[s, p] = xp, new_v  # for the backward (g2p_project)
                if ti.static(self.has_rigid):
                    self.store_C_pre[s, p] = new_C
            xp, new_v = self._project(xp, new_v)
            self._store_g2p(p, s, xp, new_v, new_C)

    @ti.func
    def _store_g2p(self, p, s, xp, vp, Cp):
        """Into slot s + 1, or with rigid bodies into x_g, v_g, C_g for the rigid projection."""
        if ti.static(self.has_rigid):
            self.x_g[p], self.v_g[p], self.C_g[p] = xp, vp, Cp
        else:
            self.x[s + 1, p], self.v[s + 1, p], self.C[s + 1, p] = xp, vp, Cp

    @ti.kernel
    def g2p_project(self, s: ti.i32):
        """The projection alone, of the stored gather (plus x_pre, v_pre, C_pre, zero, whose gradients Taichi's
        reverse of this kernel fills: g2p_grad). Without rigid bodies C of slot s + 1 is the gathered C, which
        the forward wrote, and its gradient goes straight to the gather's backward."""
        for p in range(self.n_particles):
            xp, vp = self._project(self.store_x_pre[s, p] + self.x_pre[p], self.store_v_pre[s, p] + self.v_pre[p])
            if ti.static(self.has_rigid):
                self.x_g[p], self.v_g[p], self.C_g[p] = xp, vp, self.store_C_pre[s, p] + self.C_pre[p]
            else:
                self.x[s + 1, p], self.v[s + 1, p] = xp, vp

    @ti.kernel
    def g2p_gather_grad(self, s: ti.i32):
        """Backward of the gather and advection, by hand (Taichi's reverse of the unrolled gather costs ~5x its
        forward). With X = (x − origin)/Δx, f = X − base, weights w = w₀(f₀) w₁(f₁) w₂(f₂) and d = offset − f:
            x_pre = x + Δt v,  v = Σ w g_i,  C = (4/Δx) Σ w g_i dᵀ
        so, with ḡv = ∂L/∂v + Δt ∂L/∂x_pre and Ḡ = ∂L/∂C:
            ∂L/∂g_i += w (ḡv + (4/Δx) Ḡ d)
            ∂L/∂f   += Σ_i [g_i·(ḡv + (4/Δx) Ḡ d) ∇_f w − (4/Δx) w Ḡᵀ g_i]
            ∂L/∂x   += ∂L/∂x_pre + ∂L/∂f / Δx
        with the quadratic B-spline derivatives w₀' = f − 1.5, w₁' = −2(f − 1), w₂' = f − 0.5.
        The node velocities g_i are the stored ones (store_v). The kernel's grid loop also puts the substep's grid
        back for grid_update's backward (grid_m, grid_mv from the stores, their gradients zero): no separate
        restore launch."""
        if ti.static(self.private):
            ti.loop_config(block_dim=1)
            for c in range(self.copies):
                for p in range(c * self.chunk, ti.min((c + 1) * self.chunk, self.n_particles)):
                    self._gather_grad_particle(c, s, p)
            for I in ti.grouped(self.grid_m):
                g = ti.Vector.zero(float, 3)
                for c in range(self.copies):
                    g += self.grid_private[c, I[0], I[1], I[2]]
                    self.grid_private[c, I[0], I[1], I[2]] = ti.Vector.zero(float, 3)
                self._restore_node(s, I, g)
        else:
            for I in ti.grouped(self.grid_m):
                self._restore_node(s, I, ti.Vector.zero(float, 3))
            for p in range(self.n_particles):
                self._gather_grad_particle(0, s, p)

    @ti.func
    def _restore_node(self, s, I, g_v):
        """Node I as substep s's grid update found it, with ∂L/∂v_i = g_v and zero mass and momentum gradients."""
        self.grid_m[I] = self.store_m[s, I[0], I[1], I[2]]
        self.grid_mv[I] = self.store_mv[s, I[0], I[1], I[2]]
        self.grid_v.grad[I] = g_v
        self.grid_m.grad[I] = 0.0
        self.grid_mv.grad[I] = ti.Vector.zero(float, 3)

    @ti.func
    def _gather_grad_particle(self, c, s, p):
        """Particle p's part of g2p_gather_grad, its grid gradient into copy c (or atomically into the grid)."""
        xp = self.x[s, p]
        gx = self.x_pre.grad[p]
        gv = self.v_pre.grad[p] + self.dt * gx
        gC = self.C.grad[s + 1, p]
        if ti.static(self.has_rigid):
            gC = self.C_pre.grad[p]
            self.C_pre.grad[p] = ti.Matrix.zero(float, 3, 3)
        self.x_pre.grad[p] = ti.Vector.zero(float, 3)  # read once: zero for the next substep's projection
        self.v_pre.grad[p] = ti.Vector.zero(float, 3)
        base, fx, w = self.fast._stencil(xp)
        dw = [fx - 1.5, -2.0 * (fx - 1.0), fx - 0.5]
        # nested by axis as p2g_grad_kernel, with h = ḡv + (4/Δx) Ḡ (offset − f) built up axis by axis
        gC4 = 4.0 * self.inv_dx * gC
        h0 = gv - gC4 @ fx
        gf = ti.Vector.zero(float, 3)
        for a in ti.static(range(3)):
            h_a = h0 + a * gC4[:, 0]
            for b in ti.static(range(3)):
                w_ab = w[a][0] * w[b][1]
                dw_a, dw_b = dw[a][0] * w[b][1], w[a][0] * dw[b][1]
                h_ab = h_a + b * gC4[:, 1]
                for cc in ti.static(range(3)):
                    h = h_ab + cc * gC4[:, 2]
                    i, j, k = base[0] + a, base[1] + b, base[2] + cc
                    g_i = self.store_v[s, i, j, k]
                    weight = w_ab * w[cc][2]
                    if ti.static(self.private):
                        self.grid_private[c, i, j, k] = self.grid_private[c, i, j, k] + weight * h
                    else:
                        self.grid_v.grad[i, j, k] += weight * h
                    gf += g_i.dot(h) * ti.Vector([dw_a * w[cc][2], dw_b * w[cc][2], w_ab * dw[cc][2]])
        gf -= gC4.transpose() @ self.store_v_pre[s, p]  # Σ_i w g_i = v
        # one thread per particle: a plain read-modify-write (`+=` on a field is an atomic add)
        self.x.grad[s, p] = self.x.grad[s, p] + gx + self.inv_dx * gf

    def g2p_grad(self, s: int):
        self.g2p_project.grad(s)
        self.g2p_gather_grad(s)

    # --- rigid projection (rigid.py), differentiable ------------------------------------------------
    @ti.kernel
    def body_sums(self):
        """Σ m x and Σ m v per body (the sums cleared first)."""
        ti.loop_config(serialize=True)
        for b in range(self.rigid.n_bodies):
            self.com_sum[b] = ti.Vector.zero(float, 3)
            self.momentum[b] = ti.Vector.zero(float, 3)
            self.A[b] = ti.Matrix.zero(float, 3, 3)
            self.L[b] = ti.Vector.zero(float, 3)
            self.inertia[b] = ti.Matrix.zero(float, 3, 3)
        for p in range(self.n_particles):
            b = self.rigid.body[p]
            if b >= 0:
                m = self.fast.mass[p]
                self.com_sum[b] += m * self.x_g[p]
                self.momentum[b] += m * self.v_g[p]

    @ti.kernel
    def body_moments(self):
        """A = Σ m (x − c) qᵀ and L = Σ m (x − c) × v."""
        for p in range(self.n_particles):
            b = self.rigid.body[p]
            if b >= 0:
                m = self.fast.mass[p]
                r = self.x_g[p] - self.com_sum[b] / self.body_mass[b]
                self.A[b] += m * r.outer_product(self.rigid.rest_offset[p])
                self.L[b] += m * r.cross(self.v_g[p])

    @ti.kernel
    def body_normalise(self):
        """A/|A|: order-one entries for the SVD (R is unchanged by the scale)."""
        ti.loop_config(serialize=True)
        for b in range(self.rigid.n_bodies):
            self.A_n[b] = self.A[b] / ti.sqrt((self.A[b] * self.A[b]).sum())

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
        """R = U Vᵀ, the polar rotation of A."""
        ti.loop_config(serialize=True)
        for b in range(self.rigid.n_bodies):
            self.R[b] = self.U_b[b] @ self.V_b[b].transpose()

    @ti.kernel
    def body_inertia(self):
        """I = Σ m (|r|² 1 − r rᵀ), r = R q."""
        for p in range(self.n_particles):
            b = self.rigid.body[p]
            if b >= 0:
                r = self.R[b] @ self.rigid.rest_offset[p]
                self.inertia[b] += self.fast.mass[p] * (r.dot(r) * ti.Matrix.identity(float, 3) - r.outer_product(r))

    @ti.kernel
    def body_omega(self):
        """ω = I⁻¹ L."""
        ti.loop_config(serialize=True)
        for b in range(self.rigid.n_bodies):
            self.omega[b] = self.inertia[b].inverse() @ self.L[b]

    @ti.kernel
    def rigid_write(self, s: ti.i32):
        """Slot s + 1: body particles on their rigid motion, every particle kept out of the other bodies."""
        for p in range(self.n_particles):
            own = self.rigid.body[p]
            xp, vp, Cp, Fp = self.x_g[p], self.v_g[p], self.C_g[p], self.F_model[p]
            if own >= 0:
                R = self.R[own]
                omega = self.omega[own]
                r = R @ self.rigid.rest_offset[p]
                xp = self.com_sum[own] / self.body_mass[own] + r
                vp = self.momentum[own] / self.body_mass[own] + omega.cross(r)
                J = self.F_model[p].determinant() * (1.0 + self.dt * self.C_g[p].trace())
                J = ti.min(ti.max(J, 0.5), 2.0)
                Fp = R * ti.pow(J, 1.0 / 3.0)
                Cp = ti.Matrix([[0.0, -omega[2], omega[1]], [omega[2], 0.0, -omega[0]], [-omega[1], omega[0], 0.0]])
            for b in ti.static(range(len(self.rigid.sdfs))):
                if own != b:
                    R, c = self.R[b], self.com_sum[b] / self.body_mass[b]
                    xl = R.transpose() @ (xp - c) + self.rigid.rest_com[b]
                    phi = self.rigid.sdfs[b](xl)
                    if phi < 0.0:
                        n = R @ self.rigid.normals[b](xl)
                        xp -= phi * n
                        v_body = self.momentum[b] / self.body_mass[b] + self.omega[b].cross(xp - c)
                        vn = (vp - v_body).dot(n)
                        if vn < 0.0:
                            vp -= vn * n
            self.x[s + 1, p] = xp
            self.v[s + 1, p] = vp
            self.C[s + 1, p] = Cp
            self.F[s + 1, p] = Fp

    # --- one substep, forward and backward ----------------------------------------------------------
    def _rigid_kernels(self):
        return [self.body_sums, self.body_moments, self.body_normalise, self.body_svd, self.body_rotation,
                self.body_inertia, self.body_omega]

    @ti.ad.grad_replaced
    def substep(self, s: int):
        """Slot s → slot s + 1, keeping what its backward reads (`store_*`)."""
        self._forward(s, True)

    def substep_no_store(self, s: int):
        """Slot s → slot s + 1 without the stores: for a forward pass whose substeps are run again before their
        backward (checkpointing's first pass over all but the last segment), or that has none."""
        self._forward(s, True, keep=False)

    def _forward(self, s: int, whole: bool, keep: bool = True):
        """The substep's forward. Without `whole` (before its backward), only what the backward reads and the
        forward did not keep: the SVD (the stress's backward reads it), the stress's F_new only with rigid
        bodies (the rigid projection reads it), the stress, grid and gather restored from the stores, and with
        rigid bodies the projection's body sums (not the slot s + 1 writes)."""
        if whole:
            self.forward_kernel(s, keep)
        else:
            if self.svd_models:
                self.svd(s)  # SVD of F_trial
            if self.rigid is not None:
                self.restore_rigid()
                for k in range(len(self.models)):
                    self.stress(s, k)  # constitutive models
                self.g2p_project(s)
        if self.rigid is not None:
            for kernel in self._rigid_kernels():  # rigid projection
                kernel()
            if whole:
                self.rigid_write(s)

    @ti.ad.grad_for(substep)
    def substep_grad(self, s: int):
        """Add the gradients of slot s from those of slot s + 1: restore or re-run the substep's intermediates,
        then the gradients of its kernels in reverse order."""
        self._forward(s, False)
        if self.rigid is not None:
            self.rigid_write.grad(s)
            for kernel in reversed(self._rigid_kernels()):
                if kernel == self.body_svd:
                    self.body_svd_grad()
                else:
                    kernel.grad()
        self.g2p_grad(s)
        self.grid_update.grad(s)
        self.p2g_grad_kernel(s)
        for k in reversed(range(len(self.models))):
            self.stress.grad(s, k)
        if self.svd_models:
            self.svd_grad(s)
