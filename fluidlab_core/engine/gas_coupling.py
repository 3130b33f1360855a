"""Gas and particles in one scene: the MPM particles move the gas, and the gas drags light particles.

Operator splitting, once per scene step (after the MPM step of dt, before the gas step of dt):

    particles → gas   each gas cell's particle volume share φ_c = Σ_{p in c} V_p / Δx_g³ and mean velocity
                      ū_c = Σ V_p v_p / Σ V_p over the particles the gas does not drag; cells with φ_c ≥ ½ are
                      solid for the gas and move at ū_c (the gas flows round the liquid and is pushed by it, as
                      round a tool); dragged (light) particles ride in the gas and do not block it.
                      With particle_faces="fractions" instead: each gas face f gets the particles' volume share
                      α_f = Σ V_p N_f(x_p) / Δx_g³ and mean velocity ū_f = Σ V_p N_f v_p / Σ V_p N_f, N_f the
                      trilinear weight of the face's lattice (continuous in x_p), and is open by
                      w_f = max(w_g − α_f, 0) (w_g its share outside tools and statics), its shut part moving at
                      ū_f (engine/gas.py, face fractions)
    gas → particles   v_p ← v_p + a (u_gas(x_p) − v_p), a = 1 − exp(−k Δt), for the particles of the bodies the
                      user named, with u_gas the trilinear interpolation of the face velocities and k (1/s) the
                      drag rate, i.e. Stokes-like drag relaxing a particle to the local air speed over 1/k seconds

What is and is not conserved: the first is a boundary condition (the gas's volume is kept by its projection; the
particles lose nothing); the second moves particle momentum towards the gas's without giving the gas the
reaction, so momentum is not conserved by the pair (the gas is treated as an external wind on light particles,
whose momentum is small beside the air's driving it).

Gradients (CoupledGas, driven by checkpoint.rollout_with_grad): a scene step is the MPM substeps (slot s0 → s1
of the differentiable solver's buffer), then the gas substeps with the particles of slot s1 as solids, then the
drag on slot s1 in place. Going back through step j, the gradient held by slot s1 is that of the state after the
drag; in reverse order:

    drag          v̄_p ← (1 − a) v̄_p;  x̄_p += a (∂u_gas/∂x)ᵀ v̄_p;  ū_gas += a Wᵀ v̄_p   (W: the interpolation
                  weights; Taichi's autodiff of `drag_wind`, which reads the gas after the step)
    gas substeps  GasSolver.backward_step, each from its start state (kept on the host by the forward or by the
                  segment's recompute), with the particles of slot s1 rasterised again; the gradient of the solid
                  cells' velocities goes to the particles that made them: v̄_p += (V_p / Σ_c V) ∂L/∂ū_c (with
                  fractional particles: of the faces' shares and velocities, to x̄_p and v̄_p)
    tools         the gas's gradients with respect to the tools' pose (end of step, slot s1) and twist go into
                  the MPM state's tool gradients, so the MPM backward carries them on

Which cell a particle falls in, and whether a cell is solid (φ_c ≥ ½), are piecewise constant in the positions:
their derivative is zero almost everywhere, and the gradient carries none (a finite difference across a cell
boundary sees a jump instead). With fractional particles the shares and velocities are trilinear deposits, and
their gradient (Taichi's autodiff of deposit_faces and particle_faces_finish, after the shares' own gradient from
the projection's adjoint) reaches the particles' positions and velocities; it has kinks where a particle crosses a
face lattice's plane and where a share reaches 0 (w_g = α), and shares under 1e-3 are set to 0 (a step of 1e-3).
The dragged particles' own cells are not solid, so the two directions touch
disjoint particles and the in-place drag leaves what the solids' backward reads unchanged.
"""
import numpy as np
import taichi as ti


@ti.data_oriented
class GasParticleCoupling:
    """The coupling kernels between slot s of a StateBuffer (slot 0 of the fast solver's state; any slot of the
    differentiable solver's buffer) and a GasSolver."""

    def __init__(self, gas, model, drag_rows: np.ndarray | None, drag_rate: float):
        self.gas = gas
        self.model = model
        self.drag_rate = float(drag_rate)
        n = model.n_particles
        self.drag = ti.field(ti.i8, shape=max(n, 1))  # 1 for particles the gas drags
        mask = np.zeros(max(n, 1), dtype=np.int8)
        if drag_rows is not None:
            mask[np.asarray(drag_rows)] = 1
        self.drag.from_numpy(mask)
        self.cell_volume = gas.dx ** 3
        # a · u_gas(x_p) of the dragged particles (m/s), for the drag's gradient (autodiff of drag_wind)
        self.wind = ti.Vector.field(3, model.real, shape=max(n, 1), needs_grad=gas.needs_grad)

    @ti.kernel
    def rasterize(self, x: ti.template(), v: ti.template(), s: ti.i32):
        """gas.cell_m = particle volume share per gas cell, gas.cell_mv = their mean velocity."""
        g = self.gas
        shape = ti.static(g.shape)
        for I in ti.grouped(g.cell_m):
            g.cell_m[I] = 0.0
            g.cell_mv[I] = ti.Vector([0.0, 0.0, 0.0])
        for p in range(self.model.n_particles):
            c = self._cell_of(x[s, p])
            inside = 0 <= c[0] < shape[0] and 0 <= c[1] < shape[1] and 0 <= c[2] < shape[2]
            if inside and self.drag[p] == 0:  # the particles the gas drags ride in it and do not block it
                vol = self.model.rest_volume[p]
                g.cell_m[c] += vol
                g.cell_mv[c] += vol * v[s, p]
        for I in ti.grouped(g.cell_m):
            m = g.cell_m[I]
            if m > 0.0:
                g.cell_mv[I] = g.cell_mv[I] / m
            g.cell_m[I] = m / self.cell_volume

    @ti.kernel
    def deposit_faces(self, x: ti.template(), v: ti.template(), s: ti.i32):
        """Fractional particles: every blocking particle's volume and velocity onto the gas faces it reaches
        (GasSolver.deposit_particle; differentiable in x and v)."""
        for p in range(self.model.n_particles):
            if self.drag[p] == 0:
                self.gas.deposit_particle(x[s, p], self.model.rest_volume[p], v[s, p])

    @ti.func
    def _cell_of(self, xp):
        """The gas cell holding position xp (may lie outside the grid)."""
        return ti.cast(ti.floor((xp - ti.Vector(self.gas._lower)) / self.gas.dx), ti.i32)

    @ti.kernel
    def apply_drag(self, x: ti.template(), v: ti.template(), s: ti.i32, dt: ti.f64):
        g = self.gas
        a = 1.0 - ti.exp(-self.drag_rate * dt)
        for p in range(self.model.n_particles):
            if self.drag[p] != 0:
                u = g._velocity_at(0, x[s, p])
                v[s, p] = v[s, p] + a * (u - v[s, p])

    # --- gradients -----------------------------------------------------------------------------------------------
    @ti.kernel
    def drag_wind(self, x: ti.template(), s: ti.i32, a: ti.f64):
        """wind_p = a u_gas(x_p) for the dragged particles (its reverse is the drag's gradient in x and u_gas)."""
        for p in range(self.model.n_particles):
            if self.drag[p] != 0:
                self.wind[p] = a * self.gas._velocity_at(0, x[s, p])

    @ti.kernel
    def drag_seed(self, v: ti.template(), s: ti.i32, a: ti.f64):
        """wind.grad = v̄ and v̄ ← (1 − a) v̄ on the dragged particles of slot s (zero wind.grad elsewhere)."""
        for p in range(self.model.n_particles):
            gv = ti.Vector([0.0, 0.0, 0.0], dt=self.model.real)
            if self.drag[p] != 0:
                gv = v.grad[s, p]
                v.grad[s, p] = (1.0 - a) * gv
            self.wind.grad[p] = gv

    @ti.kernel
    def add_velocity_grad(self, c0: ti.template(), c1: ti.template(), c2: ti.template()):
        """The carried gas gradient c += ∂L/∂u of the gas's stage S0 (what the drag read)."""
        g = self.gas
        for d in ti.static(range(3)):
            c = ti.static((c0, c1, c2)[d])
            for I in ti.grouped(c):
                c[I] += ti.cast(g.V[0][d].grad[I], ti.f64)

    @ti.kernel
    def solid_grad(self, x: ti.template(), v: ti.template(), s: ti.i32):
        """v̄_p += (V_p / Σ_c V) ∂L/∂ū_c for the particles that make the particle-solid cell c (particle_solids set
        ū_c = cell_mv, the volume-weighted mean of their velocities)."""
        g = self.gas
        shape = ti.static(g.shape)
        for p in range(self.model.n_particles):
            c = self._cell_of(x[s, p])
            inside = 0 <= c[0] < shape[0] and 0 <= c[1] < shape[1] and 0 <= c[2] < shape[2]
            if inside and self.drag[p] == 0:
                if g.solid[c] == 3:
                    share = self.model.rest_volume[p] / (g.cell_m[c] * self.cell_volume)
                    v.grad[s, p] = v.grad[s, p] + share * g.solid_v.grad[c]

    # --- the scene step's two halves (fast and differentiable solvers alike) -----------------------------------
    def particles_to_gas(self, state, s: int = 0):
        """Before a gas step: the particle cells of slot s become moving solids (with particles_block), or with
        fractional particles their volume share and velocity at each face."""
        if self.gas.frac_particles:
            self.gas.particle_faces_clear()
            self.deposit_faces(state.x, state.v, s)
            self.gas.particle_faces_finish()
            return
        self.rasterize(state.x, state.v, s)
        self.gas.particle_solids(0.5)

    def particles_grad(self, state, s: int):
        """After the gas step's backward: the gradients of the solid cells' velocities (cells), or of the faces'
        particle shares and velocities (fractions), to the particles of slot s."""
        if self.gas.frac_particles:
            self.gas.particle_faces_finish.grad()
            self.deposit_faces.grad(state.x, state.v, s)
        else:
            self.solid_grad(state.x, state.v, s)

    def gas_to_particles(self, state, dt: float, s: int = 0):
        if self.drag_rate > 0.0:
            self.apply_drag(state.x, state.v, s, dt)


class CoupledGas:
    """The gas of a coupled scene after each MPM step: on the fast solver's state (Simulator._gas_step) and inside
    a checkpointed gradient rollout (checkpoint.rollout_with_grad), where it also keeps the gas's state at each
    segment's start and goes back through each step (module docstring).

    coupling: the scene's GasParticleCoupling (its gas built with gradients for a gradient rollout); state: the
    solver's StateBuffer; dt: the scene step (s); first_step: the scene's step count at the rollout's start.
    Host memory of a gradient rollout: the gas's state at each segment's start (in memory even when the particles'
    checkpoints go to disk), and for the segment being undone, each gas substep's start."""

    def __init__(self, coupling: GasParticleCoupling, state, dt: float, first_step: int):
        self.cp, self.gas, self.state = coupling, coupling.gas, state
        self.dt = float(dt)
        self.substeps = int(self.gas.spec.substeps)
        self.sub_dt = self.dt / self.substeps
        self.first_step = int(first_step)
        self.segment_starts: dict = {}  # segment index → gas state at its start
        self.kept: dict = {}  # step → gas states at each gas substep's start, and after the step (what the drag read)
        self.carry_v, self.carry_q = None, None
        self.tool_grad = None

    def _set_tools(self, slot: int, twist: np.ndarray):
        if self.gas.n_tools:
            p, R = self.state.read_tools(slot)
            twist = np.asarray(twist, dtype=np.float64)
            self.gas.set_tools(p, R, twist[:, :3], twist[:, 3:])

    def _particles(self, slot: int):
        return (lambda: self.cp.particles_to_gas(self.state, slot)) if self.gas.spec.particles_block else None

    # --- forward -------------------------------------------------------------------------------------------------
    def segment_start(self, b: int):
        self.segment_starts[b] = self.gas.read_state()

    def restore(self, b: int):
        self.gas.write_state(self.segment_starts[b])

    def after_step(self, g: int, slot: int, twist: np.ndarray, keep: bool):
        """Step g's gas (the MPM state of step g's end in `slot`), keeping its states for the backward if `keep`."""
        self._set_tools(slot, twist)
        kept = []
        for j in range(self.substeps):
            if keep:
                kept.append(self.gas.read_state())
            self.gas.step(self.sub_dt, (self.first_step + g) * self.substeps + j, particles=self._particles(slot))
        if keep:
            kept.append(self.gas.read_state())
            self.kept[g] = kept
        self.cp.gas_to_particles(self.state, self.dt, slot)

    # --- backward ------------------------------------------------------------------------------------------------
    def begin_backward(self):
        self.final = self.gas.read_state()
        self.carry_v, self.carry_q = self.gas.carry_fields()
        for f in (*self.carry_v, self.carry_q):
            f.fill(0)
        self.gas.clear_param_grads()

    def backward_step(self, g: int, s0: int, s1: int, twist: np.ndarray):
        """Step g's gas and drag, backward: slot s1's gradient becomes that of the state before the gas's step,
        the carried gas gradient that of the gas before it, and the tools' gradients go into slots s0 … s1."""
        from fluidlab_core.engine.checkpoint import NonFiniteGradientError

        gas, cp = self.gas, self.cp
        kept = self.kept.pop(g)
        if cp.drag_rate > 0.0:
            a = 1.0 - np.exp(-cp.drag_rate * self.dt)
            gas.write_state(kept[-1])
            gas.clear_grads()
            cp.drag_seed(self.state.v, s1, a)
            cp.drag_wind.grad(self.state.x, s1, a)
            cp.add_velocity_grad(*self.carry_v)
        self._set_tools(s1, twist)
        particles_grad = (lambda: cp.particles_grad(self.state, s1)) if gas.spec.particles_block else None
        tool_g, bad = gas.backward_substeps(kept[:self.substeps], self.sub_dt, (self.first_step + g) * self.substeps,
                                            self.carry_v, self.carry_q, particles=self._particles(s1),
                                            particles_grad=particles_grad)
        if bad:
            raise NonFiniteGradientError(f"the gas gradient ({', '.join(bad)}) became NaN or infinite going back "
                                         f"through step {self.first_step + g + 1}")
        if tool_g is not None:
            gp, gR, gv, gw = tool_g
            self.state.add_steps_grad([s1], [{"tool_position": gp, "tool_rotation": gR}])
            self.state.add_twist_grad(s0, np.concatenate([gv, gw], axis=1))

    def finish(self, result):
        """The gradients with respect to the gas's start (result.grad_gas_velocity, grad_gas_scalars) and its
        sources (grad_gas_sources); the gas back in its final state."""
        result.grad_gas_velocity = tuple(f.to_numpy() for f in self.carry_v)
        result.grad_gas_scalars = self.carry_q.to_numpy()
        result.grad_gas_sources = self.gas.source_grads()
        self.gas.write_state(self.final)
