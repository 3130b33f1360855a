"""Particle emitters: nozzles that add fluid to a running scene (a milk jug, an ice-cream machine, a water jet).

A nozzle is a disc (radius r) or a rectangle (width × height) in the xy plane of its own frame, facing +z: fluid
leaves it along the frame's z axis. Its pose is fixed in the world or carried by a tool (given in the tool's
frame), and it runs at a volumetric flow rate Q (m³/s) with an exit speed u (m/s) while it is on.

Lattice (SI units): the nozzle's cross-section is covered by a square lattice of the scene's particle spacing s
(the `row`, n_row points); every particle stands for the rest volume s³ and carries the mass ρ s³ of its
material, like the particles a body is sampled with. A row of V_row = n_row s³ leaves the nozzle every
T_row = V_row / Q seconds of on-time; row r (0-based) leaves at on-time τ_r = (r + ½) T_row, so that the volume
emitted after an on-time T is Q T to within half a row. At the end of the substep in which it is born a particle
of row r sits at
    x = P + R (o_q + u (T − τ_r) e_z),    v = u R e_z + v_nozzle(x)
with (P, R) the nozzle's pose at the end of the substep (for a tool-carried nozzle: the tool's pose advanced over
the substep, composed with the nozzle's pose in the tool frame), o_q its lattice offset in the cross-section,
T the on-time at the end of the substep and v_nozzle(x) = v_tool + ω_tool × (x − p_tool) (zero for a fixed
nozzle). Its affine velocity C is zero and its deformation gradient F the identity. Rows leave at spacing u T_row
along the axis: the stream leaves at its rest density when u = Q / (n_row s²), i.e. u = Q / A for the lattice's
area A; `EmitterSpec` refuses a stream more than twice as dense or sparse as that.

The pool: the particles an emitter can emit are allocated at build (`pool`, a whole number of rows), so that
every array and gradient buffer keeps its shape. Pool particle j (0-based, in emission order) is active once the
emitter has emitted more than j particles; inactive particles are skipped by P2G and G2P (parked where they
are, F = I, C = 0), are left out of every reader (`Simulator.positions`, losses, rendering, observations), and
get no gradient. The emission schedule (how many particles each emitter has emitted after each substep, and
its on-time) depends only on the on/off control and the start state, so it is computed on the host in float64
before a step or a checkpoint segment runs (`schedule`), like the tools' workspace clipping.

Gradients flow through emission into the nozzle's pose (fixed nozzle: `grad_emitter_position/rotation` of the
rollout result; tool-carried: into the tool's pose and twists, hence the actions). The emission counts are
integers and carry none.
"""

import math
from dataclasses import dataclass, field

import numpy as np
import taichi as ti
from scipy.spatial.transform import Rotation

from fluidlab_core.engine.tools import advance_pose

SHAPES = ("disc", "rectangle")
DENSITY_RATIO_LIMIT = 2.0  # the stream may leave at most this much denser or sparser than rest


def nozzle_lattice(shape: str, size, spacing: float) -> np.ndarray:
    """(n_row, 2) offsets (m) of the lattice points of a nozzle cross-section, centred on its axis: a disc of
    radius size (points within the radius), or a rectangle of size (width, height) along the nozzle's x and y."""
    if shape == "disc":
        r = float(size)
        k = int(math.floor(r / spacing))
        grid = np.arange(-k, k + 1) * spacing
        # the lattice is shifted by half a spacing when that fits more points (e.g. small discs)
        best = None
        for shift in (0.0, 0.5 * spacing):
            g = grid + shift
            xx, yy = np.meshgrid(g, g, indexing="ij")
            pts = np.stack([xx.ravel(), yy.ravel()], axis=1)
            pts = pts[np.sum(pts ** 2, axis=1) <= r * r + 1e-12]
            pts = pts - pts.mean(axis=0) if len(pts) else pts
            if best is None or len(pts) > len(best):
                best = pts
        return best
    w, h = (float(v) for v in size)
    nx, ny = max(1, int(round(w / spacing))), max(1, int(round(h / spacing)))
    gx = (np.arange(nx) - 0.5 * (nx - 1)) * spacing
    gy = (np.arange(ny) - 0.5 * (ny - 1)) * spacing
    xx, yy = np.meshgrid(gx, gy, indexing="ij")
    return np.stack([xx.ravel(), yy.ravel()], axis=1)


@dataclass
class EmitterSpec:
    """An emitter as the scene describes it (`Scene.add_emitter`), in SI units."""

    name: str
    material: object  # fluidlab_core.materials.Material
    shape: str  # "disc" or "rectangle"
    size: object  # disc: radius (m); rectangle: (width, height) (m)
    rate: float  # volumetric flow rate Q (m³/s)
    speed: float | None  # exit speed u (m/s); None: Q / A, the stream at rest density
    position: np.ndarray  # nozzle frame origin in the parent frame (world, or the tool's frame) (m)
    quaternion: np.ndarray  # nozzle frame orientation in the parent frame (x, y, z, w)
    tool: int | None  # index of the carrying tool, or None for a nozzle fixed in the world
    spacing: float  # particle lattice spacing s (m)
    pool: int = 0  # particles allocated (a whole number of rows)
    lattice: np.ndarray = field(default=None)  # (n_row, 2) offsets (m)

    def __post_init__(self):
        if self.shape not in SHAPES:
            raise ValueError(f"emitter {self.name!r}: nozzle must be one of {SHAPES}, got {self.shape!r}")
        sizes = np.atleast_1d(np.asarray(self.size, dtype=float))
        if sizes.shape != ((1,) if self.shape == "disc" else (2,)) or not np.all(sizes > 0) \
                or not np.all(np.isfinite(sizes)):
            want = "a radius (m)" if self.shape == "disc" else "(width, height) in m"
            raise ValueError(f"emitter {self.name!r}: a {self.shape} nozzle's size is {want}, got {self.size!r}")
        self.size = float(sizes[0]) if self.shape == "disc" else (float(sizes[0]), float(sizes[1]))
        if not (self.rate is not None and self.rate > 0 and math.isfinite(self.rate)):
            raise ValueError(f"emitter {self.name!r}: the flow rate must be a positive number of m³/s, got "
                             f"{self.rate!r}")
        if self.lattice is None:
            self.lattice = nozzle_lattice(self.shape, self.size, self.spacing)
        if len(self.lattice) == 0:
            raise ValueError(f"emitter {self.name!r}: the nozzle ({self.shape} {self.size} m) holds no particle at "
                             f"the scene's spacing {self.spacing:.4g} m; make it larger")
        if self.speed is None:
            self.speed = self.natural_speed
        if not (self.speed > 0 and math.isfinite(self.speed)):
            raise ValueError(f"emitter {self.name!r}: the exit speed must be a positive number of m/s, got "
                             f"{self.speed!r}")
        ratio = self.natural_speed / self.speed
        if not (1.0 / DENSITY_RATIO_LIMIT <= ratio <= DENSITY_RATIO_LIMIT):
            raise ValueError(
                f"emitter {self.name!r}: at {self.rate:.4g} m³/s through {self.n_row} lattice points "
                f"({self.area:.4g} m²) the stream would leave {ratio:.2f}x as dense as the liquid at rest with "
                f"the exit speed {self.speed:.4g} m/s; the flow rate and the nozzle's area give "
                f"u = Q/A = {self.natural_speed:.4g} m/s (allowed: {self.natural_speed / DENSITY_RATIO_LIMIT:.4g} "
                f"to {self.natural_speed * DENSITY_RATIO_LIMIT:.4g} m/s)")

    @property
    def n_row(self) -> int:
        return len(self.lattice)

    @property
    def particle_volume(self) -> float:
        return self.spacing ** 3

    @property
    def row_volume(self) -> float:
        return self.n_row * self.particle_volume

    @property
    def row_period(self) -> float:
        """Seconds of on-time per row."""
        return self.row_volume / self.rate

    @property
    def area(self) -> float:
        return self.n_row * self.spacing ** 2

    @property
    def natural_speed(self) -> float:
        """The exit speed at which the stream leaves at rest density: Q / A."""
        return self.rate / self.area

    @property
    def max_rows(self) -> int:
        return self.pool // self.n_row

    def local_points(self, depth: float = 0.0) -> np.ndarray:
        """(n_row, 3) lattice points of the nozzle cross-section at distance `depth` along its axis, in the
        nozzle frame."""
        return np.hstack([self.lattice, np.full((self.n_row, 1), depth)])

    def rotation(self) -> np.ndarray:
        return Rotation.from_quat(self.quaternion).as_matrix()


def pool_for(spec: EmitterSpec, duration: float) -> int:
    """Particles of the rows an emitter running for `duration` seconds emits, rounded up to whole rows."""
    rows = math.ceil(spec.rate * duration / spec.row_volume - 0.5 + 1e-9)
    return max(rows, 1) * spec.n_row


def schedule(specs, emitted, on_time, on, substeps: int, sub_dt: float):
    """The emission of K steps of `substeps` substeps each, from `emitted` (E,) particles and on-time `on_time`
    (E,) s, with the emitters switched on per step by `on` (K, E) bools. Returns
        counts (K·substeps + 1, E) int64: particles emitted before each substep (the last row: after the last),
        times  (K·substeps + 1, E) float64: on-time (s) likewise,
        exhausted (E,) bool: the pool ran out (rows that were due were not emitted).
    Row r of emitter e leaves at on-time (r + ½) T_row (module docstring)."""
    n_e = len(specs)
    K = len(on)
    counts = np.zeros((K * substeps + 1, n_e), dtype=np.int64)
    times = np.zeros((K * substeps + 1, n_e), dtype=np.float64)
    exhausted = np.zeros(n_e, dtype=bool)
    if n_e == 0:
        return counts, times, exhausted
    n = np.asarray(emitted, dtype=np.int64).copy()
    t = np.asarray(on_time, dtype=np.float64).copy()
    period = np.array([s.row_period for s in specs])
    n_row = np.array([s.n_row for s in specs])
    max_rows = np.array([s.max_rows for s in specs])
    counts[0], times[0] = n, t
    for k in range(K):
        step_on = np.asarray(on[k], dtype=bool)
        for i in range(substeps):
            t = np.where(step_on, t + sub_dt, t)
            due = np.floor(t / period + 0.5).astype(np.int64)  # rows with (r + ½) T_row <= t
            exhausted |= due > max_rows
            n = np.maximum(n, np.minimum(due, max_rows) * n_row)
            j = k * substeps + i + 1
            counts[j], times[j] = n, t
    return counts, times, exhausted


def nozzle_world_points(spec: EmitterSpec, tool_position=None, tool_rotation=None, depth: float = 0.0):
    """(n_row, 3) exit lattice points of a nozzle in the world (for a tool-carried nozzle: with the tool at the
    given pose)."""
    pts = spec.local_points(depth) @ spec.rotation().T + spec.position
    if spec.tool is not None:
        pts = pts @ np.asarray(tool_rotation).T + np.asarray(tool_position)
    return pts


def blocked_reason(spec: EmitterSpec, statics, lower, upper, dx: float, tool_position=None, tool_rotation=None):
    """Why this nozzle cannot emit at this pose (its exit lattice, and one row in front of it, inside a static or
    outside the domain's walls, with half a cell of margin), or '' when it can."""
    pts = np.vstack([nozzle_world_points(spec, tool_position, tool_rotation, d) for d in (0.0, spec.spacing)])
    margin = 0.5 * dx
    lo, hi = np.asarray(lower) + margin, np.asarray(upper) - margin
    outside = np.any((pts < lo) | (pts > hi), axis=1)
    if outside.any():
        p = pts[np.argmax(outside)]
        return (f"its exit at {tuple(np.round(p, 4))} m is outside the domain's walls {tuple(np.round(lo, 4))}.."
                f"{tuple(np.round(hi, 4))} m (half a cell inside)")
    for st in statics:
        d = st.shape.sdf(pts)
        if np.any(d < margin):
            p = pts[np.argmin(d)]
            return f"its exit at {tuple(np.round(p, 4))} m is inside (or within half a cell of) static {st.name!r}"
    return ""


# --- the Taichi side -----------------------------------------------------------------------------------
@ti.data_oriented
class EmitterModel:
    """The emitters' constant data on the device: each particle's emitter and pool index, the nozzles' lattices,
    and their poses in the parent frame (with gradients: the rollout reports dL/d pose)."""

    def __init__(self, specs, emitter_of: np.ndarray, pool_index: np.ndarray, real, uploads: list):
        self.specs = list(specs)
        self.n = len(self.specs)
        n = len(emitter_of)
        np_real = np.float64 if real == ti.f64 else np.float32
        self.emitter = ti.field(ti.i32, shape=n)  # emitter of each particle, −1 for the scene's own bodies
        self.pool_index = ti.field(ti.i32, shape=n)  # its place in the emitter's emission order
        starts = np.cumsum([0] + [s.n_row for s in self.specs])
        self.row_start = [int(v) for v in starts[:-1]]  # first lattice point of each emitter (static)
        self.tool_of = [-1 if s.tool is None else int(s.tool) for s in self.specs]  # carrying tool (static)
        self.lattice = ti.Vector.field(2, real, shape=max(int(starts[-1]), 1))  # cross-section offsets (m)
        ne = max(self.n, 1)
        self.position = ti.Vector.field(3, real, shape=ne, needs_grad=True)  # nozzle origin, parent frame (m)
        self.rotation = ti.Matrix.field(3, 3, real, shape=ne, needs_grad=True)  # nozzle to parent frame
        lattice = np.zeros((max(int(starts[-1]), 1), 2))
        for s, a in zip(self.specs, self.row_start):
            lattice[a:a + s.n_row] = s.lattice
        pos = np.zeros((ne, 3))
        rot = np.tile(np.eye(3), (ne, 1, 1))
        for e, s in enumerate(self.specs):
            pos[e], rot[e] = s.position, s.rotation()
        uploads += [(self.emitter, emitter_of.astype(np.int32)), (self.pool_index, pool_index.astype(np.int32)),
                    (self.lattice, lattice.astype(np_real)), (self.position, pos.astype(np_real)),
                    (self.rotation, rot.astype(np_real))]

    def clear_grads(self):
        self.position.grad.fill(0.0)
        self.rotation.grad.fill(0.0)

    def pose_grads(self):
        """(dL/d position (E, 3), dL/d rotation matrix (E, 3, 3)) accumulated by the last backward pass."""
        return (self.position.grad.to_numpy()[: self.n].astype(np.float64),
                self.rotation.grad.to_numpy()[: self.n].astype(np.float64))

    @ti.func
    def active(self, state: ti.template(), s, p):
        """Whether particle p takes part in slot s (the scene's own bodies always do)."""
        out = True
        e = self.emitter[p]
        if e >= 0:
            out = self.pool_index[p] < state.emit_n[e, s]
        return out

    @ti.func
    def newborn(self, model: ti.template(), state: ti.template(), s_in, p, t_after):
        """(x, v) of pool particle p born in the substep from slot s_in, the emitter's on-time at its end being
        t_after (module docstring)."""
        x = ti.Vector.zero(float, 3)
        v = ti.Vector.zero(float, 3)
        e_p = self.emitter[p]
        for e in ti.static(range(self.n)):
            if e_p == e:
                n_row, period, speed = ti.static(self.specs[e].n_row, self.specs[e].row_period, self.specs[e].speed)
                j = self.pool_index[p]
                r = j // n_row
                q = j - r * n_row
                tau = (ti.cast(r, float) + 0.5) * period
                depth = ti.max(speed * (ti.cast(t_after, float) - tau), 0.0)
                off = self.lattice[ti.static(self.row_start[e]) + q]
                local = ti.Vector([off[0], off[1], depth])
                axis = ti.Vector([0.0, 0.0, speed])
                P, R = self.position[e], self.rotation[e]
                if ti.static(self.tool_of[e] >= 0):
                    k = ti.static(self.tool_of[e])
                    dt = ti.cast(model.tool_dt[None], float)
                    lin, ang = state.tool_v_real[k, s_in], state.tool_w_real[k, s_in]
                    pt, Rt = advance_pose(state.tool_p_real[k, s_in], state.tool_R_real[k, s_in], lin, ang, dt)
                    x = pt + Rt @ (P + R @ local)
                    v = Rt @ (R @ axis) + lin + ang.cross(x - pt)
                else:
                    x = P + R @ local
                    v = R @ axis
        return x, v


def plan(specs, statics, lower, upper, dx: float, tool_rotations, tool_positions, on):
    """Switch off, step by step, the tool-carried nozzles whose exit lies in a static or past a wall at the end
    of the step (a nozzle never emits into a solid). tool_positions (N + 1, T, 3) and tool_rotations
    (N + 1, T, 3, 3): the tools' poses at the step boundaries (tools.plan_poses); on (N, E) bools. Returns the
    emitters' on/off (N, E) and {emitter index: (first blocked step, reason)}."""
    on = np.array(on, dtype=bool, copy=True)
    blocked = {}
    for e, spec in enumerate(specs):
        if spec.tool is None:
            continue  # a fixed nozzle was checked at build
        for g in range(len(on)):
            if on[g, e]:
                why = blocked_reason(spec, statics, lower, upper, dx, tool_positions[g + 1, spec.tool],
                                     tool_rotations[g + 1, spec.tool])
                if why:
                    on[g, e] = False
                    blocked.setdefault(e, (g, why))
    return on, blocked


def exhausted(specs, emitted, on_time) -> np.ndarray:
    """(E,) bools: the pool is used up and rows were due that it could not emit."""
    return np.array([n >= s.pool and np.floor(t / s.row_period + 0.5) > s.max_rows
                     for s, n, t in zip(specs, emitted, on_time)], dtype=bool)


@ti.func
def takes_part(model: ti.template(), state: ti.template(), s, p):
    """Whether particle p takes part in slot s: always without emitters; with them, an emitter's pool particle
    only once emitted (a parked one keeps its slot's copy and is neither scattered, gathered nor moved)."""
    out = True
    if ti.static(model.has_emitters):
        out = model.emitters.active(state, s, p)
    return out
