"""What changes during a rollout: the particles and the tool poses.

Two forms of the same thing:

* `State`, on the host: one typed snapshot (numpy arrays, SI units, world frame) that round-trips exactly
  through `Simulator.get_state()` / `set_state()`, is what checkpoints keep, and is what a rollout starts from
  and ends in. The same type carries a gradient with respect to a state (`read(slot, grad=True)`).
* `StateBuffer`, on the device: Taichi fields holding the state at `n_slots` time slots,
      x[s, p], v[s, p], C[s, p], F[s, p]           particle p at slot s
      tool_p[k, s], tool_R[k, s]                   tool k's pose at slot s
      tool_v[k, s], tool_w[k, s]                   the twist tool k holds over substep s
      emit_n[e, s], emit_t[e, s]                   emitter e's particles emitted, and its on-time (s), at
                                                   slot s (emitters.py; written by the host's schedule)
  The fast solver steps a buffer of one slot in place; the differentiable solver keeps one slot per substep
  of a checkpoint segment (slot s + 1 is substep s's result) and the gradients beside them (`needs_grad`).
  Both run the same substep (solver.py): the two storages differ only in the length of the time axis.

Tool poses in the fast solver's buffer are float64 whatever the working precision, so that a tool driven by a
clipped twist stops exactly at its workspace bound (the workspace clipping is computed on the host in
float64, tools.plan). The grid update reads them in the working precision from `tool_*_real`, a copy that the
kernels keep in step (the same fields where the two precisions agree): a cast per grid node cost 15 % of a
substep.
"""

import dataclasses
from dataclasses import dataclass

import numpy as np
import taichi as ti

class NonFiniteStateError(FloatingPointError):
    """A particle field became NaN or infinite during a step."""


GRAD_FIELD_NAMES = ("positions (x)", "velocities (v)", "affine velocities (C)", "deformation gradients (F)",
                    "tool poses")


@dataclass
class State:
    """A snapshot of the simulation: positions x (N, 3) in m, velocities v (N, 3) in m/s, affine velocities
    C (N, 3, 3) in 1/s, deformation gradients F (N, 3, 3), tool origins (T, 3) in m and rotations (T, 3, 3)
    (tool frame to world), the number of steps since the start, and per emitter the particles it has emitted
    (E,) and its on-time (E,) in s. Particle arrays are in the solver's precision (every row, emitted or not),
    tool poses and on-times in float64."""

    x: np.ndarray
    v: np.ndarray
    C: np.ndarray
    F: np.ndarray
    tool_position: np.ndarray
    tool_rotation: np.ndarray
    step: int = 0
    emitted: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    emit_time: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))

    PARTICLE_FIELDS = ("x", "v", "C", "F")

    def copy(self) -> "State":
        return dataclasses.replace(self, **{f.name: np.array(getattr(self, f.name), copy=True)
                                            for f in dataclasses.fields(self) if f.name != "step"})

    def replace(self, **changes) -> "State":
        """A copy with some fields replaced (e.g. `state.replace(v=state.v + dv)`)."""
        return dataclasses.replace(self.copy(), **changes)

    @property
    def n_particles(self) -> int:
        return len(self.x)

    def arrays(self) -> dict:
        """The fields as a {name: array} dict (for .npz checkpoints)."""
        out = {f.name: np.asarray(getattr(self, f.name)) for f in dataclasses.fields(self)}
        return out

    @classmethod
    def from_arrays(cls, arrays) -> "State":
        return cls(**{f.name: (int(arrays[f.name]) if f.name == "step" else np.asarray(arrays[f.name]))
                      for f in dataclasses.fields(cls)})

    def nonfinite_fields(self) -> list[str]:
        """Names of the particle fields holding a NaN or infinity."""
        return [k for k in self.PARTICLE_FIELDS if not np.all(np.isfinite(getattr(self, k)))]

    def check_shapes(self, n_particles: int, n_tools: int, n_emitters: int = 0):
        """Refuse a state of another scene, naming the field."""
        for key in self.PARTICLE_FIELDS:
            arr = np.asarray(getattr(self, key))
            if arr.ndim == 0 or arr.shape[0] != n_particles:
                rows = arr.shape[0] if arr.ndim else 0
                raise ValueError(f"state.{key} has {rows} rows, this scene has {n_particles} particles")
            want = (n_particles, 3) if key in ("x", "v") else (n_particles, 3, 3)
            if arr.shape != want:
                raise ValueError(f"state.{key} has shape {arr.shape}, expected {want}")
        for key, want in (("tool_position", (n_tools, 3)), ("tool_rotation", (n_tools, 3, 3))):
            arr = np.asarray(getattr(self, key))
            if arr.shape != want:
                raise ValueError(f"state.{key} has shape {arr.shape}, this scene has {n_tools} tool(s): expected "
                                 f"{want}")
        for key in ("emitted", "emit_time"):
            arr = np.asarray(getattr(self, key))
            if arr.shape != (n_emitters,):
                raise ValueError(f"state.{key} has shape {arr.shape}, this scene has {n_emitters} emitter(s)")


@ti.data_oriented
class StateBuffer:
    """Particle and tool state at `n_slots` time slots on the device (see the module docstring)."""

    def __init__(self, n_particles: int, n_tools: int, n_slots: int, real, pose_real=None, needs_grad=False,
                 n_emitters: int = 0):
        self.n_particles, self.n_tools, self.n_slots = int(n_particles), int(n_tools), int(n_slots)
        self.n_emitters = int(n_emitters)
        self.real = real
        self.pose_real = pose_real or real
        self.needs_grad = bool(needs_grad)
        shape = (self.n_slots, self.n_particles)
        self.x = ti.Vector.field(3, real, shape=shape, needs_grad=needs_grad)  # position (m)
        self.v = ti.Vector.field(3, real, shape=shape, needs_grad=needs_grad)  # velocity (m/s)
        self.C = ti.Matrix.field(3, 3, real, shape=shape, needs_grad=needs_grad)  # APIC affine velocity (1/s)
        self.F = ti.Matrix.field(3, 3, real, shape=shape, needs_grad=needs_grad)  # deformation gradient
        nt = max(self.n_tools, 1)
        pr = self.pose_real
        self.tool_p = ti.Vector.field(3, pr, shape=(nt, self.n_slots), needs_grad=needs_grad)  # tool origin (m)
        self.tool_R = ti.Matrix.field(3, 3, pr, shape=(nt, self.n_slots), needs_grad=needs_grad)  # tool to world
        self.tool_v = ti.Vector.field(3, pr, shape=(nt, self.n_slots), needs_grad=needs_grad)  # linear (m/s)
        self.tool_w = ti.Vector.field(3, pr, shape=(nt, self.n_slots), needs_grad=needs_grad)  # angular (rad/s)
        # the same in the working precision, for the grid update (aliases when the precisions agree)
        self.wide_poses = self.pose_real != real
        if self.wide_poses:
            self.tool_p_real = ti.Vector.field(3, real, shape=(nt, self.n_slots))
            self.tool_R_real = ti.Matrix.field(3, 3, real, shape=(nt, self.n_slots))
            self.tool_v_real = ti.Vector.field(3, real, shape=(nt, self.n_slots))
            self.tool_w_real = ti.Vector.field(3, real, shape=(nt, self.n_slots))
        else:
            self.tool_p_real, self.tool_R_real = self.tool_p, self.tool_R
            self.tool_v_real, self.tool_w_real = self.tool_v, self.tool_w
        # emission (emitters.py): particles emitted and on-time per emitter and slot; for a one-slot buffer the
        # host keeps slot 0's values too (`emission`), which the fast solver's schedule starts from
        ne = max(self.n_emitters, 1)
        self.emit_n = ti.field(ti.i32, shape=(ne, self.n_slots))
        self.emit_t = ti.field(ti.f64, shape=(ne, self.n_slots))
        self.emission = (np.zeros(self.n_emitters, dtype=np.int64), np.zeros(self.n_emitters))
        # NaN / infinity watch: which fields (bits 1 x, 2 v, 4 C, 8 F, 16 tools) and the first particle found
        self.bad = ti.field(ti.i32, shape=())
        self.bad_particle = ti.field(ti.i32, shape=())

    @property
    def np_real(self):
        return np.float64 if self.real == ti.f64 else np.float32

    @property
    def np_pose_real(self):
        return np.float64 if self.pose_real == ti.f64 else np.float32

    # --- whole slots ------------------------------------------------------------------------------------
    @ti.kernel
    def _write_particles(self, s: ti.i32, x: ti.types.ndarray(), v: ti.types.ndarray(), C: ti.types.ndarray(),
                         F: ti.types.ndarray()):
        for p in range(self.n_particles):
            for i in ti.static(range(3)):
                self.x[s, p][i] = x[p, i]
                self.v[s, p][i] = v[p, i]
                for j in ti.static(range(3)):
                    self.C[s, p][i, j] = C[p, i, j]
                    self.F[s, p][i, j] = F[p, i, j]

    @ti.kernel
    def _read_particles(self, s: ti.i32, x: ti.types.ndarray(), v: ti.types.ndarray(), C: ti.types.ndarray(),
                        F: ti.types.ndarray(), grad: ti.template()):
        for p in range(self.n_particles):
            for i in ti.static(range(3)):
                if ti.static(grad):
                    x[p, i] = self.x.grad[s, p][i]
                    v[p, i] = self.v.grad[s, p][i]
                else:
                    x[p, i] = self.x[s, p][i]
                    v[p, i] = self.v[s, p][i]
                for j in ti.static(range(3)):
                    if ti.static(grad):
                        C[p, i, j] = self.C.grad[s, p][i, j]
                        F[p, i, j] = self.F.grad[s, p][i, j]
                    else:
                        C[p, i, j] = self.C[s, p][i, j]
                        F[p, i, j] = self.F[s, p][i, j]

    @ti.kernel
    def _add_particle_grad(self, s: ti.i32, x: ti.types.ndarray(), v: ti.types.ndarray(), C: ti.types.ndarray(),
                           F: ti.types.ndarray()):
        for p in range(self.n_particles):
            for i in ti.static(range(3)):
                self.x.grad[s, p][i] += x[p, i]
                self.v.grad[s, p][i] += v[p, i]
                for j in ti.static(range(3)):
                    self.C.grad[s, p][i, j] += C[p, i, j]
                    self.F.grad[s, p][i, j] += F[p, i, j]

    @ti.kernel
    def _write_tools(self, s: ti.i32, p: ti.types.ndarray(), R: ti.types.ndarray()):
        ti.loop_config(serialize=True)
        for k in range(self.n_tools):
            for i in ti.static(range(3)):
                self.tool_p[k, s][i] = p[k, i]
                for j in ti.static(range(3)):
                    self.tool_R[k, s][i, j] = R[k, i, j]
            self.sync_real(k, s)

    @ti.func
    def sync_real(self, k, s):
        """Tool k's pose and twist at slot s into the working-precision copy (nothing where they are one)."""
        if ti.static(self.wide_poses):
            self.tool_p_real[k, s] = ti.cast(self.tool_p[k, s], self.real)
            self.tool_R_real[k, s] = ti.cast(self.tool_R[k, s], self.real)
            self.tool_v_real[k, s] = ti.cast(self.tool_v[k, s], self.real)
            self.tool_w_real[k, s] = ti.cast(self.tool_w[k, s], self.real)

    def write(self, s: int, state: State):
        """Put a State's particles, tool poses and emission into slot s."""
        r = self.np_real
        self._write_particles(s, *(np.ascontiguousarray(getattr(state, k), dtype=r) for k in State.PARTICLE_FIELDS))
        if self.n_tools:
            pr = self.np_pose_real
            self._write_tools(s, np.ascontiguousarray(state.tool_position, dtype=pr),
                              np.ascontiguousarray(state.tool_rotation, dtype=pr))
        if self.n_emitters:
            n = np.asarray(state.emitted, dtype=np.int64)
            t = np.asarray(state.emit_time, dtype=np.float64)
            self.write_emission(s, n[None], t[None])
            if s == 0:
                self.emission = (n.copy(), t.copy())

    def read(self, s: int, grad: bool = False, step: int = 0) -> State:
        """Slot s (or its gradient) as a State; tool poses in float64."""
        n, r = self.n_particles, self.np_real
        x, v = np.zeros((n, 3), r), np.zeros((n, 3), r)
        C, F = np.zeros((n, 3, 3), r), np.zeros((n, 3, 3), r)
        self._read_particles(s, x, v, C, F, bool(grad))
        tp, tR = self.read_tools(s, grad)
        emitted, emit_time = self.read_emission(s)
        return State(x, v, C, F, tp, tR, step, emitted, emit_time)

    # --- emission (emitters.py) ---------------------------------------------------------------------------
    @ti.kernel
    def _write_emission(self, s0: ti.i32, n: ti.types.ndarray(), t: ti.types.ndarray()):
        for j, e in ti.ndrange(n.shape[0], self.n_emitters):
            self.emit_n[e, s0 + j] = ti.cast(n[j, e], ti.i32)
            self.emit_t[e, s0 + j] = t[j, e]

    def write_emission(self, s0: int, counts: np.ndarray, times: np.ndarray):
        """Emitted particles (K, E) and on-times (K, E) into slots s0 … s0 + K − 1 (one launch)."""
        if self.n_emitters and len(counts):
            self._write_emission(s0, np.ascontiguousarray(counts, dtype=np.int64),
                                 np.ascontiguousarray(times, dtype=np.float64))

    def read_emission(self, s: int):
        """(emitted (E,) int64, on-times (E,) float64) at slot s."""
        if not self.n_emitters:
            return np.zeros(0, dtype=np.int64), np.zeros(0)
        return (self.emit_n.to_numpy()[: self.n_emitters, s].astype(np.int64),
                self.emit_t.to_numpy()[: self.n_emitters, s].astype(np.float64))

    def read_tools(self, s: int, grad: bool = False):
        """(tool origins (T, 3), rotations (T, 3, 3)) of slot s (or their gradients), float64."""
        if not self.n_tools:
            return np.zeros((0, 3)), np.zeros((0, 3, 3))
        p = (self.tool_p.grad if grad else self.tool_p).to_numpy()[: self.n_tools, s]
        R = (self.tool_R.grad if grad else self.tool_R).to_numpy()[: self.n_tools, s]
        return p.astype(np.float64), R.astype(np.float64)

    def add_grad(self, s: int, grad):
        """Add gradients {x, v, C, F, tool_position, tool_rotation} (any subset, or a State of gradients) into
        slot s."""
        if isinstance(grad, State):
            grad = {k: v for k, v in grad.arrays().items() if k != "step"}
        if grad.get("C") is None and grad.get("F") is None:
            self.add_steps_grad([s], [grad])
            return
        n, r = self.n_particles, self.np_real

        def array(key, shape):
            g = grad.get(key)
            return np.zeros(shape, r) if g is None else np.ascontiguousarray(g, dtype=r)

        self._add_particle_grad(s, array("x", (n, 3)), array("v", (n, 3)), array("C", (n, 3, 3)),
                                array("F", (n, 3, 3)))
        self.add_steps_grad([s], [{k: grad[k] for k in ("tool_position", "tool_rotation") if k in grad}])

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
        for e in range(self.n_emitters):
            self.emit_n[e, dst] = self.emit_n[e, src]
            self.emit_t[e, dst] = self.emit_t[e, src]

    def copy_slot(self, src: int, dst: int):
        self._copy_slot(src, dst)

    # --- several slots at once (losses) -----------------------------------------------------------------
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
        """Positions and velocities (working precision) and tool origins and rotations (float64) of several
        slots in one launch: arrays with a leading axis over `slots`."""
        slots = np.ascontiguousarray(slots, dtype=np.int32)
        m, n, r, nt = len(slots), self.n_particles, self.np_real, self.n_tools
        x, v = np.zeros((m, n, 3), r), np.zeros((m, n, 3), r)
        tp, tR = np.zeros((m, max(nt, 1), 3)), np.zeros((m, max(nt, 1), 3, 3))
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

        def stacked(key, shape, dtype):
            out = np.zeros((m,) + shape, dtype)
            for j, g in enumerate(grads):
                if g.get(key) is not None:
                    out[j] = g[key]
            return out

        if any(g.get("x") is not None or g.get("v") is not None for g in grads):
            self._add_steps_xv_grad(slots, stacked("x", (n, 3), r), stacked("v", (n, 3), r))
        if nt and any(g.get("tool_position") is not None or g.get("tool_rotation") is not None for g in grads):
            pr = self.np_pose_real
            self._add_steps_tool_grad(slots, stacked("tool_position", (nt, 3), pr),
                                      stacked("tool_rotation", (nt, 3, 3), pr))

    # --- tool twists --------------------------------------------------------------------------------------
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
            self._write_twists(np.ascontiguousarray(twists, dtype=self.np_pose_real), substeps)

    @ti.kernel
    def _add_twist_grad(self, s: ti.i32, g: ti.types.ndarray()):
        ti.loop_config(serialize=True)
        for k in range(self.n_tools):
            for i in ti.static(range(3)):
                self.tool_v.grad[k, s][i] += g[k, i]
                self.tool_w.grad[k, s][i] += g[k, 3 + i]

    def add_twist_grad(self, s: int, grad: np.ndarray):
        """Add (n_tools, 6) to the gradient of the twist held over substep s (what else the step's twist moved:
        the gas of a coupled scene)."""
        if self.n_tools:
            self._add_twist_grad(s, np.ascontiguousarray(grad, dtype=self.np_pose_real))

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
        out = np.zeros((n_steps, self.n_tools, 6), self.np_pose_real)
        if self.n_tools and n_steps:
            self._twist_grads(substeps, out)
        return out.astype(np.float64)

    # --- NaN watch ----------------------------------------------------------------------------------------
    @ti.kernel
    def _find_nonfinite(self, s: ti.i32, grad: ti.template()) -> ti.i32:
        self.bad[None] = 0
        self.bad_particle[None] = self.n_particles
        for p in range(self.n_particles):
            bits = 0
            if ti.static(grad):
                bits = _nonfinite_bits(self.x.grad[s, p], self.v.grad[s, p], self.C.grad[s, p], self.F.grad[s, p])
            else:
                bits = _nonfinite_bits(self.x[s, p], self.v[s, p], self.C[s, p], self.F[s, p])
            if bits > 0:
                ti.atomic_or(self.bad[None], bits)
                ti.atomic_min(self.bad_particle[None], p)
        ti.loop_config(serialize=True)
        for k in range(self.n_tools):
            if ti.static(grad):
                if not (ti.abs(self.tool_p.grad[k, s]).max() < 1e30 and ti.abs(self.tool_R.grad[k, s]).max() < 1e30):
                    self.bad[None] |= 16
        return self.bad[None]

    def nonfinite(self, s: int, grad: bool = False) -> tuple[list[str], int]:
        """(names of the fields of slot s, or of their gradients, holding a NaN or infinity; the first particle
        with one, or n_particles)."""
        bits = int(self._find_nonfinite(s, bool(grad)))
        return [name for i, name in enumerate(GRAD_FIELD_NAMES) if bits & (1 << i)], int(self.bad_particle[None])

    @ti.kernel
    def _step_grad_end(self, s0: ti.i32, s1: ti.i32, out: ti.types.ndarray()):
        ti.loop_config(serialize=True)
        for k in range(self.n_tools):
            for i in ti.static(range(6)):
                out[k * 6 + i] = 0.0
            for s in range(s0, s1):
                for i in ti.static(range(3)):
                    out[k * 6 + i] += self.tool_v.grad[k, s][i]
                    out[k * 6 + 3 + i] += self.tool_w.grad[k, s][i]

    def step_grad_end(self, s0: int, s1: int):
        """After the backward of the substeps s0 … s1 − 1: the (n_tools, 6) gradient of the twists held over
        them, and the names of the slot-s0 gradient fields holding a NaN or infinity."""
        out = np.zeros(max(self.n_tools, 1) * 6, self.np_pose_real)
        if self.n_tools:
            self._step_grad_end(s0, s1, out)
        bad, _ = self.nonfinite(s0, grad=True)
        return out[: self.n_tools * 6].reshape(self.n_tools, 6).astype(np.float64), bad

    def clear_grads(self):
        for f in (self.x, self.v, self.C, self.F, self.tool_p, self.tool_R, self.tool_v, self.tool_w):
            f.grad.fill(0.0)


@ti.func
def _nonfinite_bits(x, v, C, F):
    """Bits 1, 2, 4, 8 for a NaN or infinity (or a magnitude over 1e30) in x, v, C, F."""
    bits = 0
    if not (ti.abs(x).max() < 1e30):
        bits |= 1
    if not (ti.abs(v).max() < 1e30):
        bits |= 2
    if not (ti.abs(C).max() < 1e30):
        bits |= 4
    if not (ti.abs(F).max() < 1e30):
        bits |= 8
    return bits
