"""Gas (air, smoke) as an incompressible fluid on a staggered grid: Stam's "Stable Fluids" with a second-order
advection, Boussinesq buoyancy, vorticity confinement, viscosity, and an MGPCG pressure projection; solids
(statics, tools, MPM particles) as moving boundaries, inflow sources and sinks; a hand-written adjoint of the
projection and Taichi's autodiff of the other stages, so that the whole step is differentiable.

Grid (SI, world frame): nx × ny × nz cubic cells of side Δx from `lower`. Velocity on the faces (MAC): u_x at
x-faces (nx+1, ny, nz), u_y at y-faces, u_z at z-faces (m/s); scalars at cell centres: q[0] the temperature T
(K), q[1] the smoke density s (kg/m³), q[2:] any user-named advected scalars.

One gas step of Δt (stages in order, each writing a field of its own so that its gradient is a kernel's):

    boundaries   cells inside a static, a tool (SDF < 0) or MPM particles are solid; a solid cell moves with its
                 body: v_s(x) = v + ω × (x − p) for a tool, the particles' mean velocity, 0 for a static
    sources      q ← q + w a (q_src − q), u ← u + w a (u_src − u) with w(x) ∈ [0, 1] the soft indicator of the source
                 region in its own frame (about one cell wide at its walls, smooth: _box_weight_local),
                 a = 1 − exp(−Δt/τ) (τ = 0: a = 1) and u_src = speed · (the source frame's +z axis); faces next to
                 solids take the solid's velocity
    advection    semi-Lagrangian with an RK2 backtrace x* = x − Δt u(x − ½Δt u(x)) and trilinear interpolation,
                 with MacCormack's correction (Selle et al. 2008): φ̂ = A(φ), φ̃ = A⁻¹(φ̂), φ ← φ̂ + ½(φ − φ̃),
                 clamped to a range so that it stays bounded: limiter "cell", the range of the 8 values φ̂
                 interpolated from (Selle et al.); "continuous", [I(φ⁻), I(φ⁺)] with φ⁻_j, φ⁺_j the minimum and
                 maximum of φ over sample j's 3 × 3 × 3 neighbours and I the same trilinear interpolation at the
                 traced point. Each corner's neighbourhood holds the whole cell, so the continuous range holds the
                 cell's and lies within the 4 × 4 × 4 samples about it (no new extrema beyond those). The cell's
                 range jumps when the traced point crosses into the next cell, and the clamped value with it where
                 the clamp acts; the continuous range moves with the point, so its limiter adds kinks but no
                 jumps. (Neither makes AirCirculation's 240-step loss smooth: the flow amplifies small changes
                 over the horizon; bench/air_gradient.py, docs/gas.md.)
    forces       u ← u + Δt [ g (κ s − β (T − T_amb))                    Boussinesq buoyancy (g = gravity)
                              + ε Δx (N × ω),  N = ∇|ω| / |∇|ω||          vorticity confinement (Fedkiw et al.)
                              + ν ∇²u ]                                   viscosity (explicit; ν Δt/Δx² ≤ 1/6)
    projection   u ← ũ − M Dᵀ y with L y = D ũ (poisson.py; L = D M Dᵀ, M the open faces): D u = 0 on every fluid
                 cell to the solver's tolerance; the pressure is p = −ρ Δx y / Δt (Pa)

where ũ is u with the solid faces set to the solids' velocity (no flow through a solid: u·n = v_s·n), closed
walls to 0, inflow walls to their velocity; open walls have p = 0 outside. This is the scheme of Stam (1999)
on a MAC grid (Fedkiw, Stam & Jensen 2001 for buoyancy and vorticity confinement); FluidLab (Xian et al. 2023)
uses the same splitting with a Jacobi pressure solve.

Tools and statics by face fractions (spec.tool_faces, spec.static_faces == "fractions"; Batty, Bertails & Bridson
2007): each face has an open share w ∈ [0, 1] (face_weights: the area outside those solids, from their SDF at the
face's corners and centre; the statics' SDF sampled once on the host, the tools' every step), and

    projection   VB = w ũ + (1 − w) u_s,  L y = D VB with L = D W Dᵀ,  u = VB − W Dᵀ y

so the stored u is each face's flux velocity, D u = 0 on every cell with an open face, and u moves continuously
with the tools. Its adjoint: VB̄ = ḡ − Dᵀ y′ with L y′ = D W ḡ, and w̄ = g ⊙ (Dᵀ y′ − ḡ) with g = Dᵀ y of the
forward solve (L depends on W); the shares' own gradient, through the tools' SDF, comes from face_weights_grad.
A static's shares are fixed and have no gradient (nor that extra solve). MPM particles stay whole cells.

Gradients (GasSolver.backward_step): the projection is linear, u⁺ = P ũ with P = I − M Dᵀ Π L⁺ Π D, so its
adjoint is ũ̄ = ū⁺ − Dᵀ Π L⁺ D M ū⁺: one more solve with the same operator (Π removes the mean on enclosed fluid
regions, where L is singular). The other stages are kernels whose gradients Taichi generates (`kernel.grad`),
re-run from the step's start state.

What is conserved: the projection keeps the flow divergence-free (volume) to its tolerance; MacCormack
advection neither conserves the smoke's mass exactly nor creates extrema (the clamp): its mass error is a
truncation error, measured in tests/test_gas.py; sources and sinks add and remove what they set.
"""

import math

import numpy as np
import taichi as ti

from fluidlab_core.engine import statics
from fluidlab_core.engine.poisson import FLUID, SOLID, PoissonSolver
from fluidlab_core.gas import (SMOKE, TEMPERATURE, GasCFLError, GasSolverError,  # noqa: F401 (re-exported)
                               GasSourceSpec, GasSpec, GasState, NonFiniteGasError)
from fluidlab_core.runtime import compiled_fast

# stages of the step (indices into GasSolver.V / Q)
S0, S1, HAT, TLD, S2, S3, S3T, S4 = range(8)
N_VEL_STAGES, N_Q_STAGES = 8, 5
CLOSED, OPEN, INFLOW = 0, 1, 2  # wall kinds


@ti.func
def _smoothstep(u):
    t = ti.min(ti.max(u, 0.0), 1.0)
    return t * t * (3.0 - 2.0 * t)


def _box_weight_local(half, dx):
    """The soft indicator of a box of half extents `half` in its own frame, about one cell wide at the walls:
    w = Π_a S((h_a² − q_a²)/(2 h_a Δx) + ½), S the smoothstep. It is smooth in q everywhere (a box's SDF has kinks
    on its mid-planes, where a tool's pose would then have no gradient)."""
    h = tuple(float(v) for v in half)

    @ti.func
    def weight(q):
        w = 1.0
        for a in ti.static(range(3)):
            w *= _smoothstep((h[a] * h[a] - q[a] * q[a]) / (2.0 * h[a] * dx) + 0.5)
        return w

    # w = 0 where any q_a² ≥ h_a² + h_a Δx: outside the sphere of this radius about the origin
    return weight, math.sqrt(sum(v * v + v * dx for v in h))


def _disc_weight_local(radius, half, dx):
    """The soft indicator of a disc (radius, half thickness along z) in its own frame, likewise."""
    r, h = float(radius), float(half)

    @ti.func
    def weight(q):
        rr = q[0] * q[0] + q[1] * q[1]
        return _smoothstep((r * r - rr) / (2.0 * r * dx) + 0.5) * \
            _smoothstep((h * h - q[2] * q[2]) / (2.0 * h * dx) + 0.5)

    return weight, math.sqrt(r * r + r * dx + h * h + h * dx)


@ti.data_oriented
class GasSolver:
    """The gas step and its gradient on Taichi fields (see the module docstring). `tool_specs`: the scene's tools
    (engine/tools.ToolSpec), whose shapes block the gas when spec.tools_block; `static_solid`: (nx, ny, nz) bools,
    the cells inside statics, computed on the host once; `static_phi`: for statics by face fractions, the statics'
    signed distance (m) at the grid's vertices (nx+1, ny+1, nz+1) and at the three face arrays' centres."""

    def __init__(self, spec: GasSpec, real, tool_specs=(), static_solid: np.ndarray | None = None,
                 needs_grad: bool = False, static_phi=None):
        self.spec = spec
        self.real = real
        self.np_real = np.float64 if real == ti.f64 else np.float32
        self.shape = tuple(int(n) for n in spec.shape)
        nx, ny, nz = self.shape
        self.dx = float(spec.dx)
        self.n_q = len(spec.scalar_names)
        self.needs_grad = bool(needs_grad)
        g = self.needs_grad
        self.face_shapes = [(nx + 1, ny, nz), (nx, ny + 1, nz), (nx, ny, nz + 1)]
        # face velocities per stage (m/s) and scalars per stage
        self.V = [[ti.field(real, shape=self.face_shapes[d], needs_grad=g) for d in range(3)]
                  for _ in range(N_VEL_STAGES)]
        self.Q = [ti.field(real, shape=(self.n_q, nx, ny, nz), needs_grad=g) for _ in range(N_Q_STAGES)]
        # the range of the values each MacCormack point interpolated from (its clamp)
        self.Vlo = [ti.field(real, shape=self.face_shapes[d], needs_grad=g) for d in range(3)]
        self.Vhi = [ti.field(real, shape=self.face_shapes[d], needs_grad=g) for d in range(3)]
        self.Qlo = ti.field(real, shape=(self.n_q, nx, ny, nz), needs_grad=g)
        self.Qhi = ti.field(real, shape=(self.n_q, nx, ny, nz), needs_grad=g)
        # the continuous limiter: each sample's neighbourhood minimum and maximum (local_range), interpolated
        self.continuous = spec.advection == "maccormack" and spec.limiter == "continuous"
        if self.continuous:
            self.Vnlo = [ti.field(real, shape=self.face_shapes[d], needs_grad=g) for d in range(3)]
            self.Vnhi = [ti.field(real, shape=self.face_shapes[d], needs_grad=g) for d in range(3)]
            self.Qnlo = ti.field(real, shape=(self.n_q, nx, ny, nz), needs_grad=g)
            self.Qnhi = ti.field(real, shape=(self.n_q, nx, ny, nz), needs_grad=g)
        # with gradients, the advection's backtrace goes through fields of its own, so that Taichi differentiates
        # three short kernels rather than one long one (advect_sl): each face's and cell's midpoint m and traced
        # point x (m)
        if g:
            self.trace_mid = [ti.Vector.field(3, real, shape=self.face_shapes[d], needs_grad=g)
                              for d in range(3)] + [ti.Vector.field(3, real, shape=self.shape, needs_grad=g)]
            self.trace_x = [ti.Vector.field(3, real, shape=self.face_shapes[d], needs_grad=g)
                            for d in range(3)] + [ti.Vector.field(3, real, shape=self.shape, needs_grad=g)]
        # (velocity lo, velocity hi, scalar lo, scalar hi) of every clamp-range set, for zeroing their gradients
        self._range_fields = [(self.Vlo, self.Vhi, self.Qlo, self.Qhi)] + \
            ([(self.Vnlo, self.Vnhi, self.Qnlo, self.Qnhi)] if self.continuous else [])
        self.omega = ti.Vector.field(3, real, shape=self.shape, needs_grad=g)  # vorticity at cells (1/s)
        self.f_vort = ti.Vector.field(3, real, shape=self.shape, needs_grad=g)  # confinement acceleration (m/s²)
        self.solid = ti.field(ti.i8, shape=self.shape)  # 0: gas, 1: static, 2: tool, 3: particles
        self.static_solid = ti.field(ti.i8, shape=self.shape)
        self.solid_v = ti.Vector.field(3, real, shape=self.shape, needs_grad=g)  # velocity of a solid cell (m/s)
        # particles (coupling): mass and momentum per cell, written by the coupling kernel
        self.cell_m = ti.field(real, shape=self.shape)
        self.cell_mv = ti.Vector.field(3, real, shape=self.shape)
        # tools: pose at the end of the step and the twist held over it (world frame)
        self.tool_specs = list(tool_specs)
        nt = max(len(self.tool_specs), 1)
        self.n_tools = len(self.tool_specs)
        self.tool_p = ti.Vector.field(3, real, shape=nt, needs_grad=g)
        self.tool_R = ti.Matrix.field(3, 3, real, shape=nt, needs_grad=g)
        self.tool_v = ti.Vector.field(3, real, shape=nt, needs_grad=g)
        self.tool_w = ti.Vector.field(3, real, shape=nt, needs_grad=g)
        # sources: pose in the parent frame, speed, values
        self.sources = list(spec.sources)
        ns = max(len(self.sources), 1)
        self.src_p = ti.Vector.field(3, real, shape=ns, needs_grad=g)
        self.src_R = ti.Matrix.field(3, 3, real, shape=ns, needs_grad=g)
        self.src_speed = ti.field(real, shape=ns, needs_grad=g)
        self.src_q = ti.field(real, shape=(ns, self.n_q), needs_grad=g)
        # the sources' frames in the world (their parent tool's pose composed) and their weights w at the faces
        # and cells, from `source_frames` and `source_weights` before the blend (`sources_stage`): computed once a
        # step, so the blend's gradient kernel stays small (with the weight inline, once per face axis and scalar,
        # that kernel took 6 minutes to compile). src_centre is the frames' origin without a gradient: the weight
        # kernel skips points out of the source's reach with it.
        self.src_pw = ti.Vector.field(3, real, shape=ns, needs_grad=g)
        self.src_Rw = ti.Matrix.field(3, 3, real, shape=ns, needs_grad=g)
        self.src_centre = ti.Vector.field(3, real, shape=ns)
        # (a one-cell placeholder without sources: their kernels are not run then)
        self.src_wf = [ti.field(real, shape=(ns,) + (self.face_shapes[d] if self.sources else (1, 1, 1)),
                                needs_grad=g) for d in range(3)]
        self.src_wc = ti.field(real, shape=(ns,) + (self.shape if self.sources else (1, 1, 1)), needs_grad=g)
        self._wall_kind = tuple(INFLOW if not isinstance(w, str) else (OPEN if w == "open" else CLOSED)
                                for w in spec.walls)
        self._wall_vel = tuple(tuple(float(c) for c in (w if not isinstance(w, str) else (0.0, 0.0, 0.0)))
                               for w in spec.walls)
        # tools entering the projection by face fractions (spec.tool_faces == "fractions"): each face's open share
        # (face_w, with a gradient: it moves with the tools) and the blended velocity VB = w ũ + (1 − w) u_solid
        # whose divergence the projection removes
        # statics likewise (spec.static_faces == "fractions"): their SDF, fixed, sampled once on the host at the
        # grid's vertices (the faces' corners) and the faces' centres (static_phi)
        self.frac_tools = spec.tool_faces == "fractions" and spec.tools_block and bool(self.tool_specs)
        self.frac_statics = spec.static_faces == "fractions" and static_phi is not None
        # MPM particles likewise (spec.particle_faces == "fractions"): their volume share α at each face, deposited
        # with trilinear weights (continuous in their positions), takes that part of the face (particle_faces_*)
        self.frac_particles = spec.particle_faces == "fractions" and spec.particles_block
        self.fractional = self.frac_tools or self.frac_statics or self.frac_particles
        self.poisson = PoissonSolver(self.shape, [k == OPEN for k in self._wall_kind], weighted=self.fractional)
        if self.fractional:
            self.face_w = [ti.field(real, shape=self.face_shapes[d], needs_grad=g) for d in range(3)]
            self.VB = [ti.field(real, shape=self.face_shapes[d], needs_grad=g) for d in range(3)]
            self.face_g = [ti.field(real, shape=self.face_shapes[d]) for d in range(3)]  # Dᵀ y of the forward solve
        if self.frac_particles:
            # per face: Σ V_p N_f(x_p) (m³) and Σ V_p N_f(x_p) v_p,d, the particles' volume share α (deposited
            # volume / Δx³) and mean velocity ū; the share outside the tools and statics (w_g, before α)
            self.pf_m = [ti.field(real, shape=self.face_shapes[d], needs_grad=g) for d in range(3)]
            self.pf_mv = [ti.field(real, shape=self.face_shapes[d], needs_grad=g) for d in range(3)]
            self.pf_alpha = [ti.field(real, shape=self.face_shapes[d], needs_grad=g) for d in range(3)]
            self.pf_u = [ti.field(real, shape=self.face_shapes[d], needs_grad=g) for d in range(3)]
            self.face_wg = [ti.field(real, shape=self.face_shapes[d], needs_grad=g) for d in range(3)]
        if self.frac_statics:
            vertices, faces = static_phi
            self.static_phi_v = ti.field(real, shape=tuple(n + 1 for n in self.shape))
            self.static_phi_v.from_numpy(np.asarray(vertices, dtype=self.np_real))
            self.static_phi_f = [ti.field(real, shape=self.face_shapes[d]) for d in range(3)]
            for d in range(3):
                self.static_phi_f[d].from_numpy(np.asarray(faces[d], dtype=self.np_real))
        self.nu = ti.field(real, shape=())  # kinematic viscosity (m²/s), a field so that it can change (set_viscosity)
        self.bad = ti.field(ti.i32, shape=())
        self.max_speed = ti.field(real, shape=())
        self._tool_sdf = [statics.sdf_func(t.shape, real, 0.5 * self.dx) for t in self.tool_specs] \
            if spec.tools_block else []
        weights = [(_box_weight_local(s.size, self.dx) if s.shape == "box"
                    else _disc_weight_local(*s.size, self.dx)) for s in self.sources]
        self._src_weight = [w for w, _ in weights]
        self._src_reach2 = tuple((reach + self.dx) ** 2 for _, reach in weights)
        # compile-time constants of the kernels (Python numbers and tuples)
        self._lower = tuple(float(v) for v in spec.lower)
        self._gravity = tuple(float(v) for v in spec.gravity)
        self._src_has_speed = tuple(src.speed is not None for src in self.sources)
        self._src_tau = tuple(float(src.relaxation_time) for src in self.sources)
        self._src_tool = tuple(-1 if src.tool is None else int(src.tool) for src in self.sources)
        self._src_sets = tuple(tuple(self._source_sets(i, c) for c in range(self.n_q)) for i in range(len(self.sources)))
        self._src_sets_any = tuple(any(sets) for sets in self._src_sets)
        self._moving_solids = bool(self._tool_sdf) or spec.particles_block
        self._static = np.zeros(self.shape, dtype=np.int8) if static_solid is None else \
            np.asarray(static_solid, dtype=np.int8)
        self.static_solid.from_numpy(self._static)
        self.nu[None] = float(spec.viscosity)
        self._flags_ready = False
        self._carry = None  # the carried-gradient fields (carry_fields), made on first use
        self.stats = {"iterations": [], "residual": []}
        self.upload_sources()

    # --- host I/O ----------------------------------------------------------------------------------------------
    def upload_sources(self):
        """Write the sources' poses, speeds and values (from their specs) to the device."""
        names = self.spec.scalar_names
        for i, s in enumerate(self.sources):
            self.src_p[i] = s.position.tolist()
            self.src_R[i] = s.rotation().tolist()
            self.src_speed[i] = 0.0 if s.speed is None else float(s.speed)
            for j, n in enumerate(names):
                v = {"temperature": s.temperature, "smoke": s.smoke}.get(n, s.scalars.get(n))
                self.src_q[i, j] = 0.0 if v is None else float(v)

    def write_state(self, state: GasState, stage: int = S0):
        for d in range(3):
            self.V[stage][d].from_numpy(np.asarray(state.velocity[d], dtype=self.np_real))
        self.Q[min(stage, S2) if stage < N_Q_STAGES else S2].from_numpy(np.asarray(state.scalars, dtype=self.np_real))

    def read_state(self, stage: int = S0) -> GasState:
        q_stage = stage if stage < N_Q_STAGES else S2
        return GasState(tuple(self.V[stage][d].to_numpy() for d in range(3)), self.Q[q_stage].to_numpy())

    def initial_state(self) -> GasState:
        nx, ny, nz = self.shape
        q = np.zeros((self.n_q, nx, ny, nz), dtype=self.np_real)
        t0 = self.spec.initial_temperature
        q[TEMPERATURE] = self.spec.ambient_temperature if t0 is None else t0
        vel = tuple(np.zeros(s, dtype=self.np_real) for s in self.face_shapes)
        for d in range(3):  # inflow walls start with their velocity on their faces
            for side in range(2):
                w = self.spec.walls[2 * d + side]
                if not isinstance(w, str):
                    idx = [slice(None)] * 3
                    idx[d] = -1 if side else 0
                    vel[d][tuple(idx)] = float(w[d])
        return GasState(vel, q)

    def set_tools(self, p: np.ndarray, R: np.ndarray, v: np.ndarray, w: np.ndarray):
        """The tools' pose at the end of the step (T, 3), (T, 3, 3) and the twist held over it (T, 3), (T, 3)."""
        for i in range(self.n_tools):
            self.tool_p[i] = p[i].tolist()
            self.tool_R[i] = R[i].tolist()
            self.tool_v[i] = v[i].tolist()
            self.tool_w[i] = w[i].tolist()

    # --- small helpers -------------------------------------------------------------------------------------------
    @ti.func
    def _face_pos(self, d: ti.template(), I):
        """World position of face I of axis d."""
        off = ti.Vector([0.5, 0.5, 0.5])
        off[d] = 0.0
        return ti.Vector(self._lower) + self.dx * (I.cast(self.real) + off)

    @ti.func
    def _cell_pos(self, I):
        return ti.Vector(self._lower) + self.dx * (I.cast(self.real) + 0.5)

    @ti.func
    def _weights(self, nshape: ti.template(), x, off0: ti.template(), off1: ti.template(), off2: ti.template()):
        """The trilinear stencil of world point x in a grid of `nshape` samples offset by (off0, off1, off2) cells:
        the base index and the fractions (clamped into the grid; an axis with one sample has fraction 0)."""
        offs = ti.Vector([off0, off1, off2])
        gpos = (x - ti.Vector(self._lower)) / self.dx - offs
        base = ti.Vector([0, 0, 0])
        frac = ti.Vector([0.0, 0.0, 0.0], dt=self.real)
        for d in ti.static(range(3)):
            gd = ti.min(ti.max(gpos[d], 0.0), nshape[d] - 1.0)
            if ti.static(nshape[d] >= 2):
                b = ti.min(ti.cast(ti.floor(gd), ti.i32), nshape[d] - 2)
                base[d] = b
                frac[d] = gd - b
        return base, frac

    @ti.func
    def _corner(self, f: ti.template(), nshape: ti.template(), base, a: ti.template(), b: ti.template(),
                c: ti.template(), comp: ti.template()):
        """The value of f (or of its scalar comp when comp >= 0) at stencil corner (a, b, c) from base."""
        i0 = base[0] + (a if ti.static(nshape[0] >= 2) else 0)
        i1 = base[1] + (b if ti.static(nshape[1] >= 2) else 0)
        i2 = base[2] + (c if ti.static(nshape[2] >= 2) else 0)
        s = 0.0
        if ti.static(comp >= 0):
            s = f[comp, i0, i1, i2]
        else:
            s = f[i0, i1, i2]
        return s

    @ti.func
    def _corner_weight(self, frac, a: ti.template(), b: ti.template(), c: ti.template()):
        return (frac[0] if a else 1.0 - frac[0]) * (frac[1] if b else 1.0 - frac[1]) * \
            (frac[2] if c else 1.0 - frac[2])

    @ti.func
    def _interp(self, f: ti.template(), x, off0: ti.template(), off1: ti.template(), off2: ti.template(),
                comp: ti.template()):
        """Trilinear interpolation of field f (a face component, or with comp >= 0 the scalar comp of a Q field)
        at world point x; returns (value, min, max) of the 8 values used."""
        nshape = ti.static(f.shape[1:] if comp >= 0 else f.shape)
        base, frac = self._weights(nshape, x, off0, off1, off2)
        value = 0.0
        lo = 1e30
        hi = -1e30
        for a, b, c in ti.static(ti.ndrange(2, 2, 2)):
            s = self._corner(f, nshape, base, a, b, c, comp)
            value += self._corner_weight(frac, a, b, c) * s
            lo = ti.min(lo, s)
            hi = ti.max(hi, s)
        return value, lo, hi

    @ti.func
    def _interp_pair(self, f: ti.template(), g: ti.template(), x, off0: ti.template(), off1: ti.template(),
                     off2: ti.template(), comp: ti.template()):
        """Trilinear interpolation of two fields of the same shape at x, with one stencil (the continuous limiter's
        φ⁻ and φ⁺)."""
        nshape = ti.static(f.shape[1:] if comp >= 0 else f.shape)
        base, frac = self._weights(nshape, x, off0, off1, off2)
        vf = 0.0
        vg = 0.0
        for a, b, c in ti.static(ti.ndrange(2, 2, 2)):
            w = self._corner_weight(frac, a, b, c)
            vf += w * self._corner(f, nshape, base, a, b, c, comp)
            vg += w * self._corner(g, nshape, base, a, b, c, comp)
        return vf, vg

    @ti.func
    def _interp_value(self, f: ti.template(), x, off0: ti.template(), off1: ti.template(), off2: ti.template()):
        """Trilinear interpolation of face component f at world point x, the value alone (no clamp range: the
        backtrace's velocity samples need none, and the range's min/max would only enlarge the kernels that
        Taichi differentiates)."""
        nshape = ti.static(f.shape)
        base, frac = self._weights(nshape, x, off0, off1, off2)
        value = 0.0
        for a, b, c in ti.static(ti.ndrange(2, 2, 2)):
            value += self._corner_weight(frac, a, b, c) * self._corner(f, nshape, base, a, b, c, -1)
        return value

    @ti.func
    def _velocity_at(self, st: ti.template(), x):
        ux = self._interp_value(self.V[st][0], x, 0.0, 0.5, 0.5)
        uy = self._interp_value(self.V[st][1], x, 0.5, 0.0, 0.5)
        uz = self._interp_value(self.V[st][2], x, 0.5, 0.5, 0.0)
        return ti.Vector([ux, uy, uz])

    @ti.func
    def _backtrace(self, st: ti.template(), x, dt):
        """RK2 (midpoint) backtrace of x over dt in the velocity of stage st (advect_sl without gradients)."""
        mid = x - 0.5 * dt * self._velocity_at(st, x)
        return x - dt * self._velocity_at(st, mid)

    @ti.func
    def _lo_cell(self, d: ti.template(), I):
        """The cell below face I of axis d, clamped into the grid. Every neighbour read goes through a clamped index
        even where a branch guards it: the CPU backend may load before it branches, and a load outside a field
        crashed (a guarded read of cell −1)."""
        J = I - ti.Vector.unit(3, d, ti.i32)
        J[d] = ti.max(J[d], 0)
        return J

    @ti.func
    def _hi_cell(self, d: ti.template(), I):
        """The cell above face I of axis d, clamped into the grid (see _lo_cell)."""
        J = I
        J[d] = ti.min(J[d], ti.static(self.shape)[d] - 1)
        return J

    @ti.func
    def _face_solid(self, d: ti.template(), I):
        """Whether face I of axis d touches a solid cell or is a wall face, and the velocity it takes then."""
        shape = ti.static(self.shape)
        lo_cell = self._lo_cell(d, I)
        hi_cell = self._hi_cell(d, I)
        on_wall, is_open, v = self._wall_face(d, I)
        fixed = on_wall - is_open
        n = 0.0
        if fixed == 0:
            if I[d] > 0:
                if self.solid[lo_cell] != 0:
                    fixed = 1
                    v += self.solid_v[lo_cell]
                    n += 1.0
            if I[d] < shape[d]:
                if self.solid[hi_cell] != 0:
                    fixed = 1
                    v += self.solid_v[hi_cell]
                    n += 1.0
            if n > 1.0:
                v = 0.5 * v
        return fixed, v[d]

    @ti.func
    def _wall_face(self, d: ti.template(), I):
        """For face I of axis d: (1 on the domain's walls else 0, 1 where that wall is open else 0, the wall's
        velocity: an inflow's, else zero)."""
        shape = ti.static(self.shape)
        on_wall, is_open = 0, 0
        v = ti.Vector([0.0, 0.0, 0.0], dt=self.real)
        for side in ti.static(range(2)):
            if I[d] == ti.static(0 if side == 0 else shape[d]):
                on_wall = 1
                if ti.static(self._wall_kind[2 * d + side] == INFLOW):
                    v = ti.Vector(self._wall_vel[2 * d + side], dt=self.real)
                elif ti.static(self._wall_kind[2 * d + side] == OPEN):
                    is_open = 1
        return on_wall, is_open, v

    @ti.func
    def _shuts_whole(self, kind):
        """Whether a cell of this solid kind shuts its faces whatever the face fractions: particles' (3), and a
        static's (1) or a tool's (2) unless that kind enters by fractions."""
        return (kind == 3 and not ti.static(self.frac_particles)) or \
            (kind == 1 and not ti.static(self.frac_statics)) or (kind == 2 and not ti.static(self.frac_tools))

    @ti.func
    def _solid_phi(self, d: ti.template(), I, corner: ti.template()):
        """The signed distance (m) to the solids that enter by fractions at face I of axis d: its centre (corner
        = -1) or one of its four corners (0: −e1 −e2, 1: +e1 −e2, 2: +e1 +e2, 3: −e1 +e2, e1 and e2 half a cell
        along the next two axes); and the nearest tool's index where a tool is nearest, −1 where a static is."""
        a1, a2 = ti.static((d + 1) % 3, (d + 2) % 3)
        phi = 1e9
        tool = -1
        if ti.static(self.frac_statics):
            if ti.static(corner < 0):
                phi = self.static_phi_f[d][I]
            else:
                J = I
                if ti.static(corner == 1 or corner == 2):
                    J[a1] += 1
                if ti.static(corner == 2 or corner == 3):
                    J[a2] += 1
                phi = self.static_phi_v[J]
        if ti.static(self.frac_tools):
            x = self._face_pos(d, I)
            if ti.static(corner >= 0):
                h = 0.5 * self.dx
                s1 = ti.static(-1.0 if corner == 0 or corner == 3 else 1.0)
                s2 = ti.static(-1.0 if corner == 0 or corner == 1 else 1.0)
                x += h * (s1 * ti.Vector.unit(3, a1, self.real) + s2 * ti.Vector.unit(3, a2, self.real))
            pt, t = self._tool_phi(x)
            if pt < phi:
                phi = pt
                tool = t
        return phi, tool

    @ti.func
    def _tool_phi(self, x):
        """The signed distance (m) from x to the nearest blocking tool (negative inside), and that tool's index."""
        phi = 1e9
        which = 0
        for t in ti.static(range(len(self._tool_sdf))):
            q = self.tool_R[t].transpose() @ (x - self.tool_p[t])
            f = self._tool_sdf[t](q)
            if f < phi:
                phi = f
                which = t
        return phi, which

    @ti.func
    def _triangle_share(self, a, b, c):
        """The share of a triangle where a linear function with vertex values a, b, c is positive."""
        n_pos = ti.cast(a > 0.0, ti.i32) + ti.cast(b > 0.0, ti.i32) + ti.cast(c > 0.0, ti.i32)
        share = 0.0
        if n_pos == 3:
            share = 1.0
        elif n_pos == 1:  # the positive corner's triangle: p² / ((p − q)(p − r))
            pv, q, r = a, b, c
            if b > 0.0:
                pv, q, r = b, a, c
            elif c > 0.0:
                pv, q, r = c, a, b
            share = pv * pv / ((pv - q) * (pv - r))
        elif n_pos == 2:  # all but the negative corner's triangle
            nv, q, r = a, b, c
            if b <= 0.0:
                nv, q, r = b, a, c
            elif c <= 0.0:
                nv, q, r = c, a, b
            share = 1.0 - nv * nv / ((nv - q) * (nv - r))
        return share

    def face_weights(self):
        """The open share w of every face (_face_weights, one kernel an axis)."""
        for d in range(3):
            self._face_weights(d)

    def face_weights_grad(self):
        """The reverse of face_weights: one reverse kernel an axis. As one kernel for the three axes its reverse
        compiled in 50 s, as three in 32 s together (tests/test_gas_fractions.py's fractional-tool gradient scene;
        docs/gas.md): Taichi's simplification grows faster than the kernel."""
        for d in (2, 1, 0):
            self._face_weights.grad(d)

    @ti.kernel
    def _face_weights(self, d: ti.template()):
        """The open share w of every face of axis d (solids by fractions): 1 or 0 on the domain's walls (open or not), 0 next
        to a cell that shuts whole (a static, tool or particles' cell that does not enter by fractions), else the
        share w_g of the face's area outside the fractional tools and statics, from their SDF at its four corners
        and its centre (four triangles, φ linear on each: Bridson's area fraction; continuous in the tools' poses),
        less the particles' volume share α there with fractional particles: w = max(w_g − α, 0). Shares under
        1e-3 are taken as 0 (they would only slow the solve)."""
        for I in ti.grouped(self.face_w[d]):
            w = 1.0
            on_wall, is_open, _ = self._wall_face(d, I)
            if on_wall == 1:
                w = ti.cast(is_open, self.real)
            elif self._shuts_whole(self.solid[self._lo_cell(d, I)]) or \
                    self._shuts_whole(self.solid[self._hi_cell(d, I)]):
                w = 0.0
            elif ti.static(self.frac_tools or self.frac_statics):
                pc, _ = self._solid_phi(d, I, -1)
                p0, _ = self._solid_phi(d, I, 0)
                p1, _ = self._solid_phi(d, I, 1)
                p2, _ = self._solid_phi(d, I, 2)
                p3, _ = self._solid_phi(d, I, 3)
                w = 0.25 * (self._triangle_share(pc, p0, p1) + self._triangle_share(pc, p1, p2)
                            + self._triangle_share(pc, p2, p3) + self._triangle_share(pc, p3, p0))
                if w < 1e-3:
                    w = 0.0
            if ti.static(self.frac_particles):
                self.face_wg[d][I] = w
                if on_wall == 0:
                    w = ti.max(w - self.pf_alpha[d][I], 0.0)
                    if w < 1e-3:
                        w = 0.0
            self.face_w[d][I] = w

    @ti.kernel
    def _weights_to_poisson(self):
        """The pressure solve's cells and face shares: a cell is an unknown when any of its faces is open."""
        for I in ti.grouped(self.solid):
            total = ti.f64(0.0)
            for d in ti.static(range(3)):
                lo = self.face_w[d][I]
                hi = self.face_w[d][I + ti.Vector.unit(3, d, ti.i32)]
                self.poisson.w6[I][2 * d] = ti.cast(lo, ti.f64)
                self.poisson.w6[I][2 * d + 1] = ti.cast(hi, ti.f64)
                total += ti.cast(lo + hi, ti.f64)
            self.poisson.flags[0][I] = ti.cast(FLUID if total > 0.0 else SOLID, ti.i8)

    @ti.func
    def _face_solid_velocity(self, d: ti.template(), I):
        """The velocity (axis d) a face of fractional mode takes where it is shut: a wall's, or that of a cell that
        shuts whole (as _face_solid), else the nearest fractional solid's: a tool's rigid motion at the face's
        centre, or a static's (0); with fractional particles, blended with theirs by the part they shut."""
        us = 0.0
        on_wall, _, v_wall = self._wall_face(d, I)
        if on_wall == 1:
            us = v_wall[d]
        else:
            lo_cell = self._lo_cell(d, I)
            hi_cell = self._hi_cell(d, I)
            lo_other = self._shuts_whole(self.solid[lo_cell])
            hi_other = self._shuts_whole(self.solid[hi_cell])
            if lo_other and hi_other:
                us = 0.5 * (self.solid_v[lo_cell][d] + self.solid_v[hi_cell][d])
            elif lo_other:
                us = self.solid_v[lo_cell][d]
            elif hi_other:
                us = self.solid_v[hi_cell][d]
            elif ti.static(self.frac_tools):  # the nearest fractional solid's motion: a tool's, or a static's (0)
                _, t = self._solid_phi(d, I, -1)
                if t >= 0:
                    x = self._face_pos(d, I)
                    for k in ti.static(range(len(self._tool_sdf))):
                        if t == k:
                            us = (self.tool_v[k] + self.tool_w[k].cross(x - self.tool_p[k]))[d]
        if ti.static(self.frac_particles):
            # the shut part 1 − w: 1 − w_g of it the solids' above, w_g − w the particles' (their mean velocity);
            # on walls and next to whole cells w = w_g, so this leaves us as it is there
            w = self.face_w[d][I]
            wg = self.face_wg[d][I]
            if w < 1.0:
                us = ((1.0 - wg) * us + (wg - w) * self.pf_u[d][I]) / (1.0 - w)
        return us

    # --- stage kernels ---------------------------------------------------------------------------------------
    @ti.kernel
    def boundaries(self):
        """Solid cells and their velocities: statics, tools (SDF < 0 at the cell centre), particles (cells whose
        particle volume fraction is at least ½, at the particles' mean velocity)."""
        for I in ti.grouped(self.solid):
            x = self._cell_pos(I)
            kind = ti.cast(0, ti.i8)
            vs = ti.Vector([0.0, 0.0, 0.0], dt=self.real)
            if self.static_solid[I] != 0:
                kind = ti.cast(1, ti.i8)
            for t in ti.static(range(len(self._tool_sdf))):
                q = self.tool_R[t].transpose() @ (x - self.tool_p[t])
                if self._tool_sdf[t](q) < 0.0:
                    kind = ti.cast(2, ti.i8)
                    vs = self.tool_v[t] + self.tool_w[t].cross(x - self.tool_p[t])
            self.solid[I] = kind
            self.solid_v[I] = vs

    @ti.kernel
    def particle_solids(self, threshold: ti.f64):
        """Cells where the particles' volume share (cell_m holds it) reaches `threshold` are solid at the particles'
        mean velocity (coupling, MPM → gas)."""
        for I in ti.grouped(self.solid):
            if self.solid[I] == 0 and self.cell_m[I] >= threshold:
                self.solid[I] = ti.cast(3, ti.i8)
                self.solid_v[I] = self.cell_mv[I]

    @ti.kernel
    def particle_faces_clear(self):
        for d in ti.static(range(3)):
            for I in ti.grouped(self.pf_m[d]):
                self.pf_m[d][I] = 0.0
                self.pf_mv[d][I] = 0.0

    @ti.func
    def deposit_particle(self, xp, vol, vp):
        """Add a particle at xp (m) of volume vol (m³) and velocity vp to every face it reaches, with the trilinear
        weights N_f(x_p) of each axis's face lattice (fractional particles; the coupling's kernel calls this)."""
        for d in ti.static(range(3)):
            off = ti.Vector([0.5, 0.5, 0.5], dt=self.real)
            off[d] = 0.0
            gpos = (xp - ti.Vector(self._lower)) / self.dx - off
            base = ti.cast(ti.floor(gpos), ti.i32)
            frac = gpos - base.cast(self.real)
            for c in ti.static(ti.ndrange(2, 2, 2)):
                J = base + ti.Vector([c[0], c[1], c[2]])
                inside = True
                for a in ti.static(range(3)):
                    if J[a] < 0 or J[a] >= ti.static(self.face_shapes[d])[a]:
                        inside = False
                if inside:
                    wgt = 1.0
                    for a in ti.static(range(3)):
                        if ti.static(c[a] == 1):
                            wgt *= frac[a]
                        else:
                            wgt *= 1.0 - frac[a]
                    self.pf_m[d][J] += vol * wgt
                    self.pf_mv[d][J] += vol * wgt * vp[d]

    @ti.kernel
    def particle_faces_finish(self):
        """α = Σ V N / Δx³ and ū = Σ V N v / Σ V N at every face (0 where no particle reaches)."""
        for d in ti.static(range(3)):
            for I in ti.grouped(self.pf_m[d]):
                m = self.pf_m[d][I]
                u = 0.0
                if m > 0.0:
                    u = self.pf_mv[d][I] / m
                self.pf_u[d][I] = u
                self.pf_alpha[d][I] = m / ti.static(self.dx ** 3)

    @ti.kernel
    def _flags_to_poisson(self):
        for I in ti.grouped(self.solid):
            self.poisson.flags[0][I] = ti.cast(FLUID if self.solid[I] == 0 else SOLID, ti.i8)

    @ti.kernel
    def source_frames(self):
        """The sources' rotation and origin in the world: their own pose, composed with their tool's."""
        for _ in range(1):  # a loop, so that the kernel's gradient is Taichi's (no statements outside loops)
            for s in ti.static(range(len(self.sources))):
                if ti.static(self._src_tool[s] >= 0):
                    t = ti.static(self._src_tool[s])
                    p = self.tool_p[t] + self.tool_R[t] @ self.src_p[s]
                    self.src_Rw[s] = self.tool_R[t] @ self.src_R[s]
                    self.src_pw[s] = p
                    self.src_centre[s] = p
                else:
                    self.src_Rw[s] = self.src_R[s]
                    self.src_pw[s] = self.src_p[s]
                    self.src_centre[s] = self.src_p[s]

    @ti.kernel
    def source_weights(self):
        """w of every source at the faces (sources with a speed) and the cells (sources that set a scalar); 0 out of
        the source's reach, where the soft indicator and its derivatives are 0 (the frame is read only within it,
        so the gradient kernel adds into the frame's gradient from those points only)."""
        for d in ti.static(range(3)):
            for I in ti.grouped(self.V[S0][d]):
                x = self._face_pos(d, I)
                for s in ti.static(range(len(self.sources))):
                    if ti.static(self._src_has_speed[s]):
                        w = 0.0
                        if (x - self.src_centre[s]).norm_sqr() < ti.static(self._src_reach2[s]):
                            w = self._src_weight[s](self.src_Rw[s].transpose() @ (x - self.src_pw[s]))
                        self.src_wf[d][s, I[0], I[1], I[2]] = w
        for I in ti.grouped(self.solid):
            x = self._cell_pos(I)
            for s in ti.static(range(len(self.sources))):
                if ti.static(self._src_sets_any[s]):
                    w = 0.0
                    if (x - self.src_centre[s]).norm_sqr() < ti.static(self._src_reach2[s]):
                        w = self._src_weight[s](self.src_Rw[s].transpose() @ (x - self.src_pw[s]))
                    self.src_wc[s, I[0], I[1], I[2]] = w

    @ti.kernel
    def sources_stage(self, a: ti.template(), b: ti.template(), dt: ti.template()):
        """Stage b from stage a: the sources blend velocity and scalars with the weights of source_weights (where w
        = 0 the blend is the identity, and w's derivative is 0 as well), faces at solids take their velocity."""
        for d in ti.static(range(3)):
            for I in ti.grouped(self.V[a][d]):
                fixed, vs = 0, 0.0
                if ti.static(self.fractional):  # shut faces only: a partly open one keeps its flux velocity
                    if self.face_w[d][I] == 0.0:
                        fixed, vs = 1, self._face_solid_velocity(d, I)
                else:
                    fixed, vs = self._face_solid(d, I)
                u = self.V[a][d][I]
                if fixed:
                    u = vs
                else:
                    for s in ti.static(range(len(self.sources))):
                        if ti.static(self._src_has_speed[s]):
                            w = self.src_wf[d][s, I[0], I[1], I[2]]
                            if w > 0.0:
                                wa = w * self._source_rate(s, dt)
                                u += wa * (self.src_speed[s] * self.src_Rw[s][d, 2] - u)
                self.V[b][d][I] = u
        for I in ti.grouped(self.solid):
            gas = self.solid[I] == 0
            for c in ti.static(range(self.n_q)):
                q = self.Q[a][c, I[0], I[1], I[2]]
                if gas:
                    for s in ti.static(range(len(self.sources))):
                        if ti.static(self._src_sets[s][c]):
                            w = self.src_wc[s, I[0], I[1], I[2]]
                            if w > 0.0:
                                wa = w * self._source_rate(s, dt)
                                q += wa * (self.src_q[s, c] - q)
                self.Q[b][c, I[0], I[1], I[2]] = q

    @ti.func
    def _source_rate(self, s: ti.template(), dt):
        """a = 1 − exp(−Δt/τ) (1 for τ = 0: the source sets its values)."""
        rate = 1.0
        if ti.static(self._src_tau[s] > 0):
            rate = 1.0 - ti.exp(-dt / self._src_tau[s])
        return rate

    def _source_sets(self, s: int, c: int) -> bool:
        src = self.sources[s]
        name = self.spec.scalar_names[c]
        if name == "temperature":
            return src.temperature is not None
        if name == "smoke":
            return src.smoke is not None
        return name in src.scalars

    @ti.func
    def _neighbour_index(self, I, o, shape: ti.template()):
        """Index I + o clamped into a grid of `shape`."""
        J = I + o
        for a in ti.static(range(3)):
            J[a] = ti.min(ti.max(J[a], 0), shape[a] - 1)
        return J

    @ti.func
    def _range27(self, f: ti.template(), I, shape: ti.template(), comp: ti.template()):
        """Minimum and maximum of f (or of its scalar comp when comp >= 0) over the 3 × 3 × 3 samples around I,
        clamped at the grid's edge."""
        lo = 1e30
        hi = -1e30
        for o in ti.static(ti.grouped(ti.ndrange((-1, 2), (-1, 2), (-1, 2)))):
            J = self._neighbour_index(I, o, shape)
            v = 0.0
            if ti.static(comp >= 0):
                v = f[comp, J[0], J[1], J[2]]
            else:
                v = f[J]
            lo = ti.min(lo, v)
            hi = ti.max(hi, v)
        return lo, hi

    def local_range(self, src: int):
        """The continuous limiter's φ⁻, φ⁺: the minimum and maximum of stage src's values over each sample's
        3 × 3 × 3 neighbours (clamped at the grid's edge), into Vnlo/Vnhi and Qnlo/Qnhi. A kernel per face axis
        and one for the cells, as advect_sl."""
        self._faces_and_cells(self._range_faces, self._range_cells, False, src)

    def local_range_grad(self, src: int):
        """The adjoint of local_range."""
        self._faces_and_cells(self._range_faces, self._range_cells, True, src)

    @staticmethod
    def _faces_and_cells(faces, cells, grad: bool, *args):
        """A stage split into a kernel per face axis (faces(d, *args)) and one for the cells (cells(*args)): all
        four forward, or their reverse modes in reverse order."""
        if grad:
            cells.grad(*args)
            for d in (2, 1, 0):
                faces.grad(d, *args)
        else:
            for d in range(3):
                faces(d, *args)
            cells(*args)

    @ti.kernel
    def _range_faces(self, d: ti.template(), src: ti.template()):
        for I in ti.grouped(self.V[src][d]):
            lo, hi = self._range27(self.V[src][d], I, ti.static(self.face_shapes[d]), -1)
            self.Vnlo[d][I] = lo
            self.Vnhi[d][I] = hi

    @ti.kernel
    def _range_cells(self, src: ti.template()):
        for I in ti.grouped(self.solid):
            for c in ti.static(range(self.n_q)):
                lo, hi = self._range27(self.Q[src], I, ti.static(self.shape), c)
                self.Qnlo[c, I[0], I[1], I[2]] = lo
                self.Qnhi[c, I[0], I[1], I[2]] = hi

    def advect_sl(self, src: int, vel: int, dst: int, dt: float, keep: bool):
        """dst = src at the backtraced points (one semi-Lagrangian pass over dt in the velocity of stage vel; dt < 0
        traces forward). With `keep`, each point's clamp range for MacCormack goes to Vlo/Vhi, Qlo/Qhi: the range of
        the 8 values it interpolated, or with the continuous limiter the interpolated φ⁻, φ⁺ (local_range).
        A kernel per face axis and one for the cells, Δt a kernel argument (one instance for both MacCormack
        passes). With gradients the RK2 backtrace x* = x − Δt u(x − ½Δt u(x)) goes through fields: _trace_mid
        writes each sample's midpoint, _trace_x its traced point, and _advect_faces/_advect_cells interpolate
        there. Taichi's compile time grows faster than a kernel's length, most of all for reverse-mode kernels
        (mostly in its store-to-load forwarding pass), so three short kernels differentiate in about a third of
        the time of one long one (docs/gas.md, Speed; bench/gas_compile.py). Without gradients the backtrace stays
        inline: the fields would cost six vectors a cell."""
        for d in range(4):
            if self.needs_grad:
                self._trace_mid(d, vel, dt)
                self._trace_x(d, vel, dt)
            if d < 3:
                self._advect_faces(d, src, vel, dst, dt, keep)
            else:
                self._advect_cells(src, vel, dst, dt, keep)

    def advect_sl_grad(self, src: int, vel: int, dst: int, dt: float, keep: bool, retrace: bool = True):
        """The adjoint of advect_sl: for the cells, then each face axis backwards, the reverse modes of the three
        kernels, with the backtrace run again first unless `retrace` is False (the fields still hold this pass's
        points: it was the last advect_sl run)."""
        for d in (3, 2, 1, 0):
            if retrace:
                self._trace_mid(d, vel, dt)
                self._trace_x(d, vel, dt)
            if d < 3:
                self._advect_faces.grad(d, src, vel, dst, dt, keep)
            else:
                self._advect_cells.grad(src, vel, dst, dt, keep)
            self._trace_x.grad(d, vel, dt)
            self._trace_mid.grad(d, vel, dt)

    @ti.func
    def _sample_position(self, d: ti.template(), I):
        """World position of sample I: face I of axis d (d < 3) or cell I (d = 3)."""
        p = ti.Vector([0.0, 0.0, 0.0], dt=self.real)
        if ti.static(d < 3):
            p = self._face_pos(d, I)
        else:
            p = self._cell_pos(I)
        return p

    @ti.kernel
    def _trace_mid(self, d: ti.template(), vel: ti.template(), dt: float):
        """m = p − ½Δt u(p) at each face of axis d (d = 3: each cell): the RK2 backtrace's midpoint."""
        for I in ti.grouped(self.trace_mid[d]):
            p = self._sample_position(d, I)
            self.trace_mid[d][I] = p - 0.5 * dt * self._velocity_at(vel, p)

    @ti.kernel
    def _trace_x(self, d: ti.template(), vel: ti.template(), dt: float):
        """x = p − Δt u(m): the traced point."""
        for I in ti.grouped(self.trace_x[d]):
            p = self._sample_position(d, I)
            self.trace_x[d][I] = p - dt * self._velocity_at(vel, self.trace_mid[d][I])

    @ti.kernel
    def _advect_faces(self, d: ti.template(), src: ti.template(), vel: ti.template(), dst: ti.template(), dt: float,
                      keep: ti.template()):
        for I in ti.grouped(self.V[dst][d]):
            x = self._face_pos(d, I)
            if ti.static(self.needs_grad):
                x = self.trace_x[d][I]
            else:
                x = self._backtrace(vel, x, dt)
            o = [0.5, 0.5, 0.5]
            o[d] = 0.0
            value, lo, hi = self._interp(self.V[src][d], x, o[0], o[1], o[2], -1)
            self.V[dst][d][I] = value
            if ti.static(keep):
                if ti.static(self.continuous):
                    lo, hi = self._interp_pair(self.Vnlo[d], self.Vnhi[d], x, o[0], o[1], o[2], -1)
                self.Vlo[d][I] = lo
                self.Vhi[d][I] = hi

    @ti.kernel
    def _advect_cells(self, src: ti.template(), vel: ti.template(), dst: ti.template(), dt: float,
                      keep: ti.template()):
        for I in ti.grouped(self.solid):
            x = self._cell_pos(I)
            if ti.static(self.needs_grad):
                x = self.trace_x[3][I]
            else:
                x = self._backtrace(vel, x, dt)
            for c in ti.static(range(self.n_q)):
                value, lo, hi = self._interp(self.Q[src], x, 0.5, 0.5, 0.5, c)
                self.Q[dst][c, I[0], I[1], I[2]] = value
                if ti.static(keep):
                    if ti.static(self.continuous):
                        lo, hi = self._interp_pair(self.Qnlo, self.Qnhi, x, 0.5, 0.5, 0.5, c)
                    self.Qlo[c, I[0], I[1], I[2]] = lo
                    self.Qhi[c, I[0], I[1], I[2]] = hi

    @ti.func
    def _clamp(self, v, lo, hi):
        """v clamped to [lo, hi], with strict comparisons: where v equals a bound (a flat field, lo = v = hi) the
        value and its gradient are those of the unclamped scheme, not of one arbitrary corner."""
        out = v
        if v < lo:
            out = lo
        if v > hi:
            out = hi
        return out

    @ti.kernel
    def maccormack(self, a: ti.template(), hat: ti.template(), tld: ti.template(), out: ti.template()):
        """out = clamp(hat + ½ (a − tld)) to the range of the values hat interpolated (MacCormack; the range was kept
        by the pass that made hat)."""
        for d in ti.static(range(3)):
            for I in ti.grouped(self.V[out][d]):
                corrected = self.V[hat][d][I] + 0.5 * (self.V[a][d][I] - self.V[tld][d][I])
                self.V[out][d][I] = self._clamp(corrected, self.Vlo[d][I], self.Vhi[d][I])
        for I in ti.grouped(self.Q[out]):
            corrected = self.Q[hat][I] + 0.5 * (self.Q[a][I] - self.Q[tld][I])
            self.Q[out][I] = self._clamp(corrected, self.Qlo[I], self.Qhi[I])

    @ti.func
    def _cell_velocity(self, st: ti.template(), I):
        return 0.5 * ti.Vector([self.V[st][0][I] + self.V[st][0][I + ti.Vector([1, 0, 0])],
                                self.V[st][1][I] + self.V[st][1][I + ti.Vector([0, 1, 0])],
                                self.V[st][2][I] + self.V[st][2][I + ti.Vector([0, 0, 1])]])

    @ti.func
    def _stencil(self, I, j: ti.template()):
        """(lo, hi, h): the neighbours of cell I along axis j for a central difference over h cells, one-sided
        (h = 1) at a wall, none (h = 0) on an axis one cell thick."""
        shape = ti.static(self.shape)
        e = ti.Vector.unit(3, j, ti.i32)
        lo = I - e
        hi = I + e
        h = 2.0
        if I[j] == 0:
            lo = I
            h = 1.0
        if I[j] == shape[j] - 1:
            hi = I
            h = h - 1.0
        return lo, hi, h

    @ti.kernel
    def curl(self, st: ti.template()):
        """ω = ∇ × u at the cells, from the cell-centred velocity (central differences, one-sided at the walls)."""
        for I in ti.grouped(self.omega):
            grad = ti.Matrix.zero(self.real, 3, 3)  # grad[i, j] = ∂u_i/∂x_j
            for j in ti.static(range(3)):
                lo, hi, h = self._stencil(I, j)
                if h > 0.0:
                    dv = self._cell_velocity(st, hi) - self._cell_velocity(st, lo)
                    for i in ti.static(range(3)):
                        grad[i, j] = dv[i] / (h * self.dx)
            self.omega[I] = ti.Vector([grad[2, 1] - grad[1, 2], grad[0, 2] - grad[2, 0], grad[1, 0] - grad[0, 1]])

    @ti.kernel
    def confinement(self):
        """f = ε Δx (N × ω), N = ∇|ω| / |∇|ω|| (vorticity confinement) at the gas cells."""
        eps = ti.static(self.spec.vorticity)
        for I in ti.grouped(self.f_vort):
            gw = ti.Vector([0.0, 0.0, 0.0], dt=self.real)
            for j in ti.static(range(3)):
                lo, hi, h = self._stencil(I, j)
                if h > 0.0:
                    gw[j] = (ti.sqrt(self.omega[hi].dot(self.omega[hi]) + 1e-20)
                             - ti.sqrt(self.omega[lo].dot(self.omega[lo]) + 1e-20)) / (h * self.dx)
            N = gw / ti.sqrt(gw.dot(gw) + 1e-20)
            f = eps * self.dx * N.cross(self.omega[I])
            if self.solid[I] != 0:
                f = ti.Vector([0.0, 0.0, 0.0], dt=self.real)
            self.f_vort[I] = f

    @ti.kernel
    def forces(self, a: ti.template(), qa: ti.template(), b: ti.template(), dt: ti.template()):
        """Stage b = stage a + Δt (buoyancy + vorticity confinement + ν ∇²u) on the faces."""
        shape = ti.static(self.shape)
        beta = ti.static(self.spec.beta())
        kappa = ti.static(self.spec.kappa())
        t_amb = ti.static(self.spec.ambient_temperature)
        inv_dx2 = ti.static(1.0 / (self.dx * self.dx))
        for d in ti.static(range(3)):
            for I in ti.grouped(self.V[b][d]):
                gvec = ti.Vector(self._gravity)
                u = self.V[a][d][I]
                acc = 0.0
                lo = self._lo_cell(d, I)
                hi = self._hi_cell(d, I)
                has_lo = I[d] > 0
                has_hi = I[d] < shape[d]
                n = 0.0
                T = 0.0
                s = 0.0
                fv = 0.0
                if has_lo:
                    T += self.Q[qa][TEMPERATURE, lo[0], lo[1], lo[2]]
                    s += self.Q[qa][SMOKE, lo[0], lo[1], lo[2]]
                    fv += self.f_vort[lo][d]
                    n += 1.0
                if has_hi:
                    T += self.Q[qa][TEMPERATURE, hi[0], hi[1], hi[2]]
                    s += self.Q[qa][SMOKE, hi[0], hi[1], hi[2]]
                    fv += self.f_vort[hi][d]
                    n += 1.0
                T /= n
                s /= n
                fv /= n
                acc += gvec[d] * (kappa * s - beta * (T - t_amb))
                if ti.static(self.spec.vorticity > 0.0):
                    acc += fv
                nu = self.nu[None]
                if nu > 0.0:
                    lap = 0.0
                    for j in ti.static(range(3)):
                        ej = ti.Vector.unit(3, j, ti.i32)
                        lim = ti.static(self.face_shapes[d][j])
                        lo_j = I - ej
                        hi_j = I + ej
                        u_lo = u
                        u_hi = u
                        if I[j] > 0:
                            u_lo = self.V[a][d][lo_j]
                        if I[j] < lim - 1:
                            u_hi = self.V[a][d][hi_j]
                        lap += (u_lo + u_hi - 2.0 * u) * inv_dx2
                    acc += nu * lap
                self.V[b][d][I] = u + dt * acc

    @ti.kernel
    def override(self, a: ti.template(), b: ti.template()):
        """Stage b = stage a with the faces at solids and walls set to their velocity (ũ)."""
        for d in ti.static(range(3)):
            for I in ti.grouped(self.V[b][d]):
                if ti.static(self.fractional):  # shut faces take the solid's velocity; VB blends by the open share
                    w = self.face_w[d][I]
                    us = self._face_solid_velocity(d, I)
                    u = self.V[a][d][I]
                    if w == 0.0:
                        u = us
                    self.V[b][d][I] = u
                    self.VB[d][I] = w * u + (1.0 - w) * us
                else:
                    fixed, vs = self._face_solid(d, I)
                    u = self.V[a][d][I]
                    if fixed:
                        u = vs
                    self.V[b][d][I] = u

    @ti.func
    def _open_face(self, d: ti.template(), I):
        """M_f of face I of axis d: 1 where it is free (both sides gas, or gas and an open wall), else 0; with
        fractional tools its open share w."""
        shape = ti.static(self.shape)
        if ti.static(self.fractional):
            return self.face_w[d][I]
        lo_cell = self._lo_cell(d, I)
        hi_cell = self._hi_cell(d, I)
        ok = 1
        if I[d] == 0:
            if ti.static(self._wall_kind[2 * d] != OPEN):
                ok = 0
        elif I[d] == shape[d]:
            if ti.static(self._wall_kind[2 * d + 1] != OPEN):
                ok = 0
        if ok == 1:
            if I[d] > 0:
                if self.solid[lo_cell] != 0:
                    ok = 0
            if I[d] < shape[d]:
                if self.solid[hi_cell] != 0:
                    ok = 0
        return ti.cast(ok, self.real)

    @ti.kernel
    def divergence(self, f0: ti.template(), f1: ti.template(), f2: ti.template(), masked: ti.template()):
        """poisson.b = D u on the gas cells (m/s; × 1/Δx the divergence), of the face fields f0, f1, f2 (with
        `masked`: of M u, the open faces only)."""
        for I in ti.grouped(self.poisson.b):
            v = 0.0
            if self._is_unknown(I):
                for d in ti.static(range(3)):
                    f = ti.static((f0, f1, f2)[d])
                    hi = I + ti.Vector.unit(3, d, ti.i32)
                    u_hi = f[hi]
                    u_lo = f[I]
                    if ti.static(masked):
                        u_hi *= self._open_face(d, hi)
                        u_lo *= self._open_face(d, I)
                    v += ti.cast(u_hi - u_lo, self.real)  # the carried gradient is float64 (as before, summed in real)
            self.poisson.b[I] = v

    @ti.func
    def _dt_y(self, d: ti.template(), I):
        """(Dᵀ y)_f = y_low − y_high on face I of axis d, y = poisson.x (0 outside the grid and in solids)."""
        shape = ti.static(self.shape)
        lo_cell = self._lo_cell(d, I)
        hi_cell = self._hi_cell(d, I)
        y_lo = 0.0
        y_hi = 0.0
        if I[d] > 0:
            if self._is_unknown(lo_cell):
                y_lo = ti.cast(self.poisson.x[lo_cell], self.real)
        if I[d] < shape[d]:
            if self._is_unknown(hi_cell):
                y_hi = ti.cast(self.poisson.x[hi_cell], self.real)
        return y_lo - y_hi

    @ti.func
    def _is_unknown(self, I):
        """Whether cell I has a pressure: a gas cell, or (fractional tools) any cell with an open face."""
        out = self.solid[I] == 0
        if ti.static(self.fractional):
            out = self.poisson.flags[0][I] == FLUID
        return out

    @ti.kernel
    def subtract_gradient(self, src0: ti.template(), src1: ti.template(), src2: ti.template(),
                          dst0: ti.template(), dst1: ti.template(), dst2: ti.template(), masked: ti.template()):
        """dst = src − (M) Dᵀ y with y = poisson.x (_dt_y)."""
        for d in ti.static(range(3)):
            src = ti.static((src0, src1, src2)[d])
            dst = ti.static((dst0, dst1, dst2)[d])
            for I in ti.grouped(dst):
                g = self._dt_y(d, I)
                if ti.static(masked):
                    g *= self._open_face(d, I)
                dst[I] = src[I] - g

    @ti.kernel
    def _store_dt_y(self):
        for d in ti.static(range(3)):
            for I in ti.grouped(self.face_g[d]):
                self.face_g[d][I] = self._dt_y(d, I)

    @ti.kernel
    def copy_stage(self, a: ti.template(), b: ti.template(), qa: ti.template(), qb: ti.template()):
        for d in ti.static(range(3)):
            for I in ti.grouped(self.V[a][d]):
                self.V[b][d][I] = self.V[a][d][I]
        for I in ti.grouped(self.Q[qa]):
            self.Q[qb][I] = self.Q[qa][I]

    @ti.kernel
    def check_state(self, st: ti.template(), qs: ti.template()):
        """bad: bit d for a non-finite velocity component d, bit 3 + c for scalar c; max_speed: largest |u|."""
        self.bad[None] = 0
        self.max_speed[None] = 0.0
        for d in ti.static(range(3)):
            for I in ti.grouped(self.V[st][d]):
                u = self.V[st][d][I]
                if not (ti.abs(u) < 1e30):
                    ti.atomic_or(self.bad[None], 1 << d)
                else:
                    ti.atomic_max(self.max_speed[None], ti.abs(u))
        for c, i, j, k in self.Q[qs]:
            if not (ti.abs(self.Q[qs][c, i, j, k]) < 1e30):
                ti.atomic_or(self.bad[None], 1 << (3 + c))

    # --- the step ------------------------------------------------------------------------------------------------
    def prepare_boundaries(self, particles=None):
        """Solid cells for this step (and the pressure solver's flags when they changed)."""
        self.boundaries()
        if particles is not None:
            particles()
        if self._flags_ready and not self._moving_solids:  # fixed solids: the shares and flags stand
            return
        if self.fractional:  # the faces' open shares move with the tools every step (statics alone: once)
            self.face_weights()
            self._weights_to_poisson()
            w = [f.to_numpy() for f in self.face_w]
            links = [w[d].take(np.arange(1, self.shape[d]), axis=d) > 0.0 for d in range(3)]
            self.poisson.update_flags(links=links)
            self._flags_ready = True
        else:
            self._flags_to_poisson()
            self.poisson.update_flags()
            self._flags_ready = True

    def forward_stages(self, dt: float):
        """Stages S0 → S3T (everything before the projection's solve), from the state in stage S0."""
        if self.sources:
            self.source_frames()
            self.source_weights()
        self.sources_stage(S0, S1, dt)
        if self.spec.advection == "maccormack":
            if self.continuous:
                self.local_range(S1)
            self.advect_sl(S1, S1, HAT, dt, True)
            self.advect_sl(HAT, S1, TLD, -dt, False)
            self.maccormack(S1, HAT, TLD, S2)
        else:
            self.advect_sl(S1, S1, S2, dt, False)
        if self.spec.vorticity > 0.0:
            self.curl(S2)
            self.confinement()
        self.forces(S2, S2, S3, dt)
        self.override(S3, S3T)

    def project(self, dt: float, step: int):
        """S4 = S3T − M Dᵀ y, L y = D S3T; returns the solve's report (raises or warns when it misses)."""
        V = self.V[S3T]
        B = self.VB if self.fractional else V  # the flux the solve makes divergence-free
        self.divergence(B[0], B[1], B[2], False)
        rep = self.poisson.solve(self.spec.tolerance, self.spec.max_iterations)
        self._check_solve(rep, step, "pressure")
        W = self.V[S4]
        self.subtract_gradient(B[0], B[1], B[2], W[0], W[1], W[2], True)
        return rep

    def _check_solve(self, rep, step, what):
        if not (math.isfinite(rep.get("rhs_norm", 0.0)) and math.isfinite(rep["residual"])):
            self.check_state(S0, S0)  # which field of the step's start holds it
            self._raise_nonfinite(int(self.bad[None]) or 1, step, "the pressure solve's right-hand side: ")
        self.stats["iterations"].append(rep["iterations"])
        self.stats["residual"].append(rep["residual"])
        if not rep["converged"]:
            msg = (f"the gas {what} solve stopped at relative residual {rep['residual']:.3g} after "
                   f"{rep['iterations']} iterations in step {step}, above the tolerance {self.spec.tolerance:g}; raise "
                   f"max_iterations, loosen the tolerance, or check for solids that enclose gas cells")
            if self.spec.on_fail == "raise":
                raise GasSolverError(msg)
            import warnings

            warnings.warn(msg, RuntimeWarning, stacklevel=3)

    @compiled_fast
    def step(self, dt: float, step: int = 0, particles=None):
        """One gas step of dt seconds on the state in stage S0 (tools set with set_tools)."""
        self.prepare_boundaries(particles)
        self.forward_stages(dt)
        self.project(dt, step)
        self.copy_stage(S4, S0, S2, S0)
        if self.spec.check_every and step % self.spec.check_every == 0:
            self.check(step, dt)

    def check(self, step: int, dt: float):
        self.check_state(S0, S0)
        bad = int(self.bad[None])
        if bad:
            self._raise_nonfinite(bad, step)
        cfl = float(self.max_speed[None]) * dt / self.dx
        if cfl > self.spec.max_cfl:
            raise GasCFLError(f"gas step {step}: the fastest flow ({float(self.max_speed[None]):.3g} m/s) crosses "
                              f"{cfl:.2f} cells per gas step (dt {dt:.3g} s, Δx {self.dx:.3g} m), above max_cfl "
                              f"{self.spec.max_cfl:g} that the advection takes; use gas substeps >= "
                              f"{math.ceil(cfl / self.spec.max_cfl * self.spec.substeps)} or slower sources")

    def _raise_nonfinite(self, bad: int, step: int, where: str = ""):
        names = [f"velocity u_{'xyz'[d]}" for d in range(3) if bad & (1 << d)]
        names += [self.spec.scalar_names[c] for c in range(self.n_q) if bad & (1 << (3 + c))]
        raise NonFiniteGasError(f"{where}the gas field(s) {', '.join(names)} became NaN or infinite in step {step}; "
                                f"use a smaller dt or more gas substeps, or check the sources' and the state's values")

    def pressure(self, dt: float) -> np.ndarray:
        """(nx, ny, nz) pressure of the last projection (Pa, up to a constant in enclosed regions; 0 in solids)."""
        y = self.poisson.x.to_numpy()
        return -self.spec.air_density * self.dx / dt * y * (self.solid.to_numpy() == 0)

    # --- gradients --------------------------------------------------------------------------------------------
    def clear_grads(self):
        """Zero the gradients of every stage (one launch: a field's own fill() costs milliseconds a call)."""
        self._zero_grads()

    @ti.kernel
    def _zero_grads(self):
        for st in ti.static(range(N_VEL_STAGES)):
            for d in ti.static(range(3)):
                for I in ti.grouped(self.V[st][d]):
                    self.V[st][d].grad[I] = 0.0
        for st in ti.static(range(N_Q_STAGES)):
            for I in ti.grouped(self.Q[st]):
                self.Q[st].grad[I] = 0.0
        if ti.static(self.needs_grad):
            for d in ti.static(range(4)):
                for I in ti.grouped(self.trace_x[d]):
                    self.trace_mid[d].grad[I] = ti.Vector.zero(self.real, 3)
                    self.trace_x[d].grad[I] = ti.Vector.zero(self.real, 3)
        for vlo, vhi, qlo, qhi in ti.static(self._range_fields):
            for d in ti.static(range(3)):
                for I in ti.grouped(vlo[d]):
                    vlo[d].grad[I] = 0.0
                    vhi[d].grad[I] = 0.0
            for I in ti.grouped(qlo):
                qlo.grad[I] = 0.0
                qhi.grad[I] = 0.0
        if ti.static(self.fractional):
            for d in ti.static(range(3)):
                for I in ti.grouped(self.VB[d]):
                    self.VB[d].grad[I] = 0.0
                    self.face_w[d].grad[I] = 0.0
        if ti.static(self.frac_particles):
            for d in ti.static(range(3)):
                for I in ti.grouped(self.pf_m[d]):
                    self.pf_m[d].grad[I] = 0.0
                    self.pf_mv[d].grad[I] = 0.0
                    self.pf_alpha[d].grad[I] = 0.0
                    self.pf_u[d].grad[I] = 0.0
                    self.face_wg[d].grad[I] = 0.0
        for I in ti.grouped(self.omega):
            self.omega.grad[I] = ti.Vector([0.0, 0.0, 0.0])
            self.f_vort.grad[I] = ti.Vector([0.0, 0.0, 0.0])
            self.solid_v.grad[I] = ti.Vector([0.0, 0.0, 0.0])
        if ti.static(len(self.sources) > 0):
            for d in ti.static(range(3)):
                for J in ti.grouped(self.src_wf[d]):
                    self.src_wf[d].grad[J] = 0.0
            for J in ti.grouped(self.src_wc):
                self.src_wc.grad[J] = 0.0
        for s in range(self.src_pw.shape[0]):
            self.src_pw.grad[s] = ti.Vector([0.0, 0.0, 0.0])
            self.src_Rw.grad[s] = ti.Matrix.zero(self.real, 3, 3)
        for t in range(self.tool_p.shape[0]):
            self.tool_p.grad[t] = ti.Vector([0.0, 0.0, 0.0])
            self.tool_R.grad[t] = ti.Matrix.zero(self.real, 3, 3)
            self.tool_v.grad[t] = ti.Vector([0.0, 0.0, 0.0])
            self.tool_w.grad[t] = ti.Vector([0.0, 0.0, 0.0])

    @ti.kernel
    def carry_finite(self, g0: ti.template(), g1: ti.template(), g2: ti.template(), gq: ti.template()) -> ti.i32:
        """0 if the carried gradient is finite, else bit 0 (velocity) and bit 1 (scalars)."""
        bad = 0
        for d in ti.static(range(3)):
            g = ti.static((g0, g1, g2)[d])
            for I in ti.grouped(g):
                if not (ti.abs(g[I]) < 1e300):
                    bad |= 1
        for I in ti.grouped(gq):
            if not (ti.abs(gq[I]) < 1e300):
                bad |= 2
        return bad

    def clear_param_grads(self):
        for f in (self.src_p, self.src_R, self.src_speed, self.src_q):
            f.grad.fill(0)

    @ti.kernel
    def _seed(self, g0: ti.template(), g1: ti.template(), g2: ti.template(), gq: ti.template()):
        """V[S3T].grad = g − Dᵀ y (the projection's adjoint: g the gradient carried in, y the adjoint solve's
        solution); Q[S2].grad += gq."""
        for d in ti.static(range(3)):
            gin = ti.static((g0, g1, g2)[d])
            for I in ti.grouped(gin):
                if ti.static(self.fractional):
                    # S4 = VB − W Dᵀ L(W)⁺ D VB: to VB, ḡ − Dᵀ y'; to each share w_f (L depends on W too),
                    # g_f ((Dᵀ y')_f − ḡ_f) with g = Dᵀ y of the forward solve (face_g) and y' = L⁺ D W ḡ
                    dty = self._dt_y(d, I)
                    gi = ti.cast(gin[I], self.real)
                    self.VB[d].grad[I] = gi - dty
                    self.face_w[d].grad[I] += self.face_g[d][I] * (dty - gi)
                else:
                    self.V[S3T][d].grad[I] = ti.cast(gin[I], self.real) - self._dt_y(d, I)
        for I in ti.grouped(gq):
            self.Q[S2].grad[I] += ti.cast(gq[I], self.real)

    def backward_step(self, dt: float, step: int, carry_v, carry_q, particles=None, particles_grad=None):
        """The gradient of one gas step. The state at the step's start must be in S0 and the tools set; carry_v
        (3 face fields) and carry_q hold the gradient with respect to the step's result and are replaced by the
        gradient with respect to its start. Source and tool gradients accumulate in their fields' .grad.
        particles(): rasterises the particles as in the forward step; particles_grad(): called once solid_v.grad
        holds the gradient with respect to the solid cells' velocities (coupling, engine/gas_coupling.py)."""
        self.prepare_boundaries(particles)
        self.forward_stages(dt)
        self.clear_grads()
        if self.frac_tools or self.frac_particles:  # the forward solve again: its Dᵀ y carries the gradient to
            # the face shares (statics' shares are fixed: no gradient, no solve)
            self.divergence(self.VB[0], self.VB[1], self.VB[2], False)
            rep = self.poisson.solve(self.spec.tolerance, self.spec.max_iterations)
            self._check_solve(rep, step, "pressure (backward)")
            self._store_dt_y()
        # projection adjoint: ũ̄ = ḡ − Dᵀ Π L⁺ D M ḡ
        self.divergence(carry_v[0], carry_v[1], carry_v[2], True)
        rep = self.poisson.solve(self.spec.tolerance, self.spec.max_iterations)
        self._check_solve(rep, step, "adjoint pressure")
        self.poisson.remove_solution_means()
        self._seed(carry_v[0], carry_v[1], carry_v[2], carry_q)
        self.override.grad(S3, S3T)
        self.forces.grad(S2, S2, S3, dt)
        if self.spec.vorticity > 0.0:
            self.confinement.grad()
            self.curl.grad(S2)
        if self.spec.advection == "maccormack":
            self.maccormack.grad(S1, HAT, TLD, S2)
            self.advect_sl_grad(HAT, S1, TLD, -dt, False, retrace=False)  # forward_stages' last pass
            self.advect_sl_grad(S1, S1, HAT, dt, True)
            if self.continuous:
                self.local_range_grad(S1)
        else:
            self.advect_sl_grad(S1, S1, S2, dt, False, retrace=False)
        self.sources_stage.grad(S0, S1, dt)
        if particles_grad is not None and not self.frac_particles:
            # every stage that reads solid_v (sources, override) is behind us, and boundaries.grad (which takes
            # solid_v's gradient for the tools' cells) is not yet
            particles_grad()
        if self.sources:
            self.source_weights.grad()
            self.source_frames.grad()
        if self._tool_sdf:
            self.boundaries.grad()
        if self.frac_tools or self.frac_particles:
            self.face_weights_grad()  # every reader of the shares (override, the projection) is behind us
        if particles_grad is not None and self.frac_particles:
            particles_grad()  # every reader of the particles' face fields is behind us
        self._take_carry(carry_v[0], carry_v[1], carry_v[2], carry_q)

    def backward_substeps(self, starts, dt: float, first_step: int, carry_v, carry_q, particles=None,
                          particles_grad=None):
        """Back through len(starts) consecutive substeps of dt, the j-th numbered first_step + j and begun from
        the state starts[j] (read_state()), last first: backward_step for each, the tools set as they were
        for them. The state is left at starts[0]. Returns (the tools' gradients summed over the substeps:
        (dL/dp, dL/dR, dL/dv, dL/dω) as tool_grads(), or None without tools; the names of the carried
        gradients that became NaN or infinite, "velocity" and/or "scalars", for the caller's error)."""
        sums = None
        for j in reversed(range(len(starts))):
            self.write_state(starts[j])
            self.backward_step(dt, first_step + j, carry_v, carry_q, particles=particles, particles_grad=particles_grad)
            if self.n_tools:
                got = self.tool_grads()
                sums = got if sums is None else tuple(a + b for a, b in zip(sums, got))
        flags = self.carry_finite(*carry_v, carry_q)
        return sums, [name for bit, name in ((1, "velocity"), (2, "scalars")) if flags & bit]

    @ti.kernel
    def _take_carry(self, g0: ti.template(), g1: ti.template(), g2: ti.template(), gq: ti.template()):
        for d in ti.static(range(3)):
            gout = ti.static((g0, g1, g2)[d])
            for I in ti.grouped(gout):
                gout[I] = self.V[S0][d].grad[I]
        for I in ti.grouped(gq):
            gq[I] = self.Q[S0].grad[I]

    def carry_fields(self):
        """Fields for the gradient carried between steps (3 face fields, one scalar field), float64; made once
        per solver and the same on every call (the caller zeroes them). The kernels that take them (`_seed`,
        `_take_carry`, `carry_finite`) are compiled per field they are given: new fields on every backward pass
        recompiled them on every optimiser iteration, and Taichi never frees a field."""
        if self._carry is None:
            nx, ny, nz = self.shape
            self._carry = ([ti.field(ti.f64, shape=s) for s in self.face_shapes],
                           ti.field(ti.f64, shape=(self.n_q, nx, ny, nz)))
        return self._carry

    def source_grads(self) -> dict:
        """{source name: {"position" (3,), "rotation" (3,) tangent (R ← exp([θ]×) R), "speed", <scalar>}}: the
        gradients accumulated in the sources' fields since clear_param_grads, in each source's parent frame."""
        from fluidlab_core.engine.checkpoint import rotation_tangent_grad

        out = {}
        gp, gR = self.src_p.grad.to_numpy(), self.src_R.grad.to_numpy()
        gs, gq = self.src_speed.grad.to_numpy(), self.src_q.grad.to_numpy()
        for i, src in enumerate(self.sources):
            d = {"position": gp[i].astype(np.float64),
                 "rotation": rotation_tangent_grad(gR[i].astype(np.float64), src.rotation())}
            if src.speed is not None:
                d["speed"] = float(gs[i])
            for c, name in enumerate(self.spec.scalar_names):
                if self._src_sets[i][c]:
                    d[name] = float(gq[i, c])
            out[src.name] = d
        return out

    def tool_grads(self):
        """(dL/dp, dL/dR, dL/dv, dL/dω) of this step's tool fields, (T, 3), (T, 3, 3), (T, 3), (T, 3)."""
        t = self.n_tools
        return (self.tool_p.grad.to_numpy()[:t].astype(np.float64), self.tool_R.grad.to_numpy()[:t].astype(np.float64),
                self.tool_v.grad.to_numpy()[:t].astype(np.float64), self.tool_w.grad.to_numpy()[:t].astype(np.float64))
