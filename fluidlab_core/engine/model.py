"""The Model: everything about a scene that does not change during a rollout.

A Model is made once by `Scene.build()` and shared by both solvers (in the manner of NVIDIA Warp's
`warp.sim.Model`): the grid's geometry and time step, each particle's mass, rest volume and material, the
materials' parameters, the statics and the tools' shapes as Taichi functions, and the rigid bodies' rest
configuration. What changes (particles, tool poses) is a State (state.py); what drives a step (tool twists)
is a Control (control.py).

Grid (SI units): Δx = the scene's cell size; nodes sit at origin + k Δx with origin = lower − PAD Δx, so that
a row of nodes lies on each domain wall at `lower` and `upper` (the walls' slip condition acts there and
beyond, grid.py), and PAD cells of grid outside the walls keep every particle's 3×3×3 stencil on the grid.
Until 2026-11 the nodes sat half a cell off the walls and the condition acted on the first row inside the
domain, half a cell from the wall, where a flow along the wall still moves into it: that row braked every
liquid's wall layer (docs/engine.md, "wall placement"). Particle rest volume V⁰ = s³ for a
lattice spacing s, mass m = ρ V⁰.

Allocation before data: the Model, the solvers and the states allocate their Taichi fields first and the data
goes in afterwards (`Model.upload`, `Scene.build`). A field allocated after Taichi has run a kernel (a
from_numpy is one) starts a new SNode tree, and the substep kernels, which read fields of every object, ran
4–7 % slower across four trees than within one (measured in one process, interleaved, on the bench_grad
scene).

Mass floor: nodes lighter than a millionth of the lightest particle are treated as empty. A node at the edge
of a particle's stencil can get a weight of 1e-20 or less; its mass squared underflows in float32 and the
gradient of v = mv/m (−mv/m²) overflows to infinity, then NaN. The floor drops only nodes whose velocity
reaches particles with weights under 1e-6.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import taichi as ti

from fluidlab_core.engine import constitutive, grid, statics
from fluidlab_core.engine.emitters import EmitterModel
from fluidlab_core.engine.rigid import RigidModel
from fluidlab_core.engine.state import State, StateBuffer
from fluidlab_core.engine.tools import Tool

PAD = 3  # grid cells outside the domain walls on every side


@dataclass
class ModelSpec:
    """What `Scene.build` hands to the Model, in SI units (world frame)."""

    lower: np.ndarray  # domain walls (m)
    upper: np.ndarray
    dx: float  # grid spacing (m)
    dt: float  # substep (s)
    substeps: int  # substeps per step
    gravity: np.ndarray  # m/s²
    wall_friction: float
    x: np.ndarray  # (N, 3) initial positions (m)
    v: np.ndarray  # (N, 3) initial velocities (m/s)
    material_index: np.ndarray  # (N,) index into `materials`
    body_index: np.ndarray  # (N,) rigid body index or -1
    rest_volume: np.ndarray  # (N,) m³
    materials: list  # Material objects
    statics: list = field(default_factory=list)  # scene.StaticHandle: shape, friction, sticky
    tools: list = field(default_factory=list)  # tools.ToolSpec
    body_shapes: list = field(default_factory=list)  # each rigid body's Shape at rest (world frame)
    emitters: list = field(default_factory=list)  # emitters.EmitterSpec
    emitter_of: np.ndarray | None = None  # (N,) the emitter whose pool a particle belongs to, or -1
    pool_index: np.ndarray | None = None  # (N,) its place in that emitter's emission order
    contact_fill: float = 0.97  # node volume fill at which fluids and solids share a velocity (grid.py)
    flip: float = 0.0  # FLIP share α of the liquids' velocity update (transfer.py, "AFLIP"); 0: APIC
    jbar: bool = False  # the liquids' J averaged through the grid before each substep (transfer.py, "J-bar")
    pressure: str = "state"  # the liquids' pressure: "state" (equation of state) or "projection" (projection.py)


@ti.data_oriented
class Model:
    """The constant part of a scene on the device (see the module docstring)."""

    def __init__(self, spec: ModelSpec, real):
        self.spec = spec
        self.real = real
        n = len(spec.x)
        self.n_particles = n
        self.dx = float(spec.dx)
        self.inv_dx = 1.0 / self.dx
        self.dt = float(spec.dt)  # substep (s)
        self.substeps = int(spec.substeps)
        self.step_dt = self.dt * self.substeps
        self.origin = tuple(float(v) for v in spec.lower - PAD * self.dx)
        self.lower = tuple(float(v) for v in spec.lower)
        self.upper = tuple(float(v) for v in spec.upper)
        self.grid_shape = tuple(int(np.ceil((spec.upper[d] - spec.lower[d]) / self.dx - 1e-9)) + 2 * PAD + 1
                                for d in range(3))
        self.gravity = tuple(float(g) for g in spec.gravity)
        self.wall_friction = float(spec.wall_friction)
        density = np.array([m.density for m in spec.materials], dtype=np.float64)
        mass = np.asarray(spec.rest_volume, dtype=np.float64) * density[spec.material_index]
        self.mass_floor = float(1e-6 * mass.min()) if n else 0.0

        # constitutive models present, unrolled statically by the kernels; one parameter struct field each
        names = sorted({m.model for m in spec.materials})
        self.constitutive = [constitutive.get(name) for name in names]
        self.svd_models = [k for k, m in enumerate(self.constitutive) if m.needs_svd]
        # fluids and solids each have a velocity field on the grid when a scene has both (grid.field_velocity)
        self.fluid_models = [k for k, m in enumerate(self.constitutive) if m.fluid]
        self.two_fields = 0 < len(self.fluid_models) < len(self.constitutive)
        if spec.pressure == "projection":  # the projection reads the liquids' field, with or without a body
            self.two_fields = True
        self.contact_fill = float(spec.contact_fill)
        # AFLIP (transfer.py): the liquids' particles keep α of their own velocity's difference from the grid's
        self.flip = float(spec.flip)
        # the liquids' pressure by a projection with one rigid body's motion (projection.py); its AFLIP is its own
        self.projection = spec.pressure == "projection"
        self.liquid_density = max((m.density for m in spec.materials if m.is_liquid), default=0.0)
        self.has_flip = self.flip > 0.0 and len(self.fluid_models) > 0 and not self.projection
        self.has_jbar = bool(spec.jbar) and len(self.fluid_models) > 0
        self.jbar_affine = self.has_jbar and spec.jbar == "affine"  # the nodes fit J affinely (transfer.py)
        # the contact test's share of each node's stencil beyond the walls or inside statics (grid.solid_share_of),
        # constant: filled once in upload()
        self.solid_share = ti.field(real, shape=self.grid_shape) if self.two_fields else None
        np_real = self.np_real
        self._uploads = []  # (field, numpy data) to upload once everything is allocated (module docstring)
        self.params = []
        for m in self.constitutive:
            table = ti.Struct.field({name: real for name in m.params}, shape=len(spec.materials))
            values = {name: np.zeros(len(spec.materials), dtype=np_real) for name in m.params}
            for i, mat in enumerate(spec.materials):
                if mat.model == m.name:
                    given = mat.kernel_params()
                    missing = [p for p in m.params if p not in given]
                    extra = [p for p in given if p not in m.params]
                    if missing or extra:
                        raise ValueError(f"material {mat.name!r} ({type(mat).__name__}): model {m.name!r} takes "
                                         f"parameters {m.params}; kernel_params() gave {tuple(given)}")
                    for p in m.params:
                        values[p][i] = given[p]
            self._uploads.append((table, values))
            self.params.append(table)

        # per particle
        self.mass = ti.field(real, shape=n)  # kg
        self.rest_volume = ti.field(real, shape=n)  # V⁰ (m³)
        self.material = ti.field(ti.i32, shape=n)  # index into the scene's materials (rows of self.params)
        self.model = ti.field(ti.i32, shape=n)  # index into self.constitutive
        model_of_material = np.array([names.index(m.model) for m in spec.materials], dtype=np.int32)
        self._uploads += [(self.mass, mass.astype(np_real)),
                          (self.rest_volume, np.asarray(spec.rest_volume).astype(np_real)),
                          (self.material, np.asarray(spec.material_index, dtype=np.int32)),
                          (self.model, model_of_material[spec.material_index])]

        # statics and tools as Taichi functions (SDFs in the world or tool frame)
        self.colliders = [statics.Collider(statics.sdf_func(st.shape, real, 0.5 * self.dx, self._uploads), st.friction,
                                           st.sticky, 0.01 * self.dx, self.dx) for st in spec.statics]
        # what each static's grid condition does at each node (statics.Collider.geometry: the mode and the surface
        # normals), which depends on the node's position only: filled once in upload() (grid.fill_static_geometry),
        # read by every grid update. Evaluated in the update itself, the SDF and its central-difference gradients
        # (up to 14 SDF evaluations a static a node) were most of the grid update's reverse-mode kernel, whose
        # compile was the test suite's largest after the gas's (docs/engine.md, "Statics' geometry per node").
        n_col = len(self.colliders)
        self.static_mode = ti.field(ti.i8, shape=(n_col, *self.grid_shape)) if n_col else None
        self.static_normal = ti.Vector.field(3, real, shape=(n_col, *self.grid_shape)) if n_col else None
        self.static_normal2 = ti.Vector.field(3, real, shape=(n_col, *self.grid_shape)) if n_col else None
        self.tool_specs = list(spec.tools)
        self.tools = [Tool(t, real, self.dx, self._uploads) for t in spec.tools]
        self.n_tools = len(self.tools)
        # the substep as a float64 field: the fast solver advances its float64 tool poses with it (a Python
        # constant in a kernel takes the working precision)
        self.tool_dt = ti.field(ti.f64, shape=())
        self._uploads.append((self.tool_dt, np.array(self.dt)))

        # emitters (emitters.py): which particles are pools, the nozzles; static flags the kernels unroll on
        self.emitter_specs = list(spec.emitters)
        self.n_emitters = len(self.emitter_specs)
        self.has_emitters = self.n_emitters > 0
        self.emitters_on_tools = any(e.tool is not None for e in self.emitter_specs)
        # the fast solver advances the tools after G2P when G2P reads their slot (updated in place)
        self.advance_after_g2p = self.emitters_on_tools or any(t.keep_out for t in spec.tools)
        self.emitters = None
        if self.has_emitters:
            self.emitters = EmitterModel(self.emitter_specs, spec.emitter_of, spec.pool_index, real, self._uploads)

        self.rigid = None
        if np.any(spec.body_index >= 0):
            self.rigid = RigidModel(spec.body_index, spec.x, mass, real, spec.body_shapes, self.dx)
            self._uploads += self.rigid.uploads

    def upload(self):
        """Put the Model's data into its fields (once, after the solvers and states are allocated)."""
        for target, data in self._uploads:
            target.from_numpy(data)
        self._uploads = []
        if self.colliders:
            grid.fill_static_geometry(self)
        if self.two_fields:
            grid.fill_solid_share(self)

    @property
    def np_real(self):
        return np.float64 if self.real == ti.f64 else np.float32

    @property
    def has_rigid(self) -> bool:
        return self.rigid is not None

    @property
    def projection_soft(self) -> bool:
        """Deformable solids beside a projected liquid: their nodes' velocities are unknowns of its solve
        (projection.py, "Deformable solids"; a scene with a rigid body has none there)."""
        return self.projection and not self.has_rigid and len(self.fluid_models) < len(self.constitutive)

    def initial_state(self) -> State:
        """The state the scene was built with: particles at rest shape (F = I, C = 0), tools at their start
        poses."""
        from scipy.spatial.transform import Rotation

        r, n = self.np_real, self.n_particles
        spec = self.spec
        position = np.array([t.position for t in self.tool_specs], dtype=np.float64).reshape(-1, 3)
        rotation = np.array([Rotation.from_quat(t.quaternion).as_matrix() for t in self.tool_specs],
                            dtype=np.float64).reshape(-1, 3, 3)
        return State(np.asarray(spec.x, dtype=r), np.asarray(spec.v, dtype=r), np.zeros((n, 3, 3), r),
                     np.tile(np.eye(3, dtype=r), (n, 1, 1)), position, rotation, 0,
                     np.zeros(self.n_emitters, dtype=np.int64), np.zeros(self.n_emitters))

    def state(self) -> StateBuffer:
        """A device state of one slot for the fast solver (tool poses in float64), not yet written."""
        return StateBuffer(self.n_particles, self.n_tools, 1, self.real, pose_real=ti.f64,
                           n_emitters=self.n_emitters)
