"""Gas and particles in one scene: the MPM particles move the gas, and the gas drags light particles.

Operator splitting, once per scene step (after the MPM step of dt, before the gas step of dt):

    particles → gas   each gas cell's particle volume share φ_c = Σ_{p in c} V_p / Δx_g³ and mean velocity
                      ū_c = Σ V_p v_p / Σ V_p over the particles the gas does not drag; cells with φ_c ≥ ½ are
                      solid for the gas and move at ū_c (the gas flows round the liquid and is pushed by it, as
                      round a tool); dragged (light) particles ride in the gas and do not block it
    gas → particles   v_p ← v_p + (1 − exp(−k Δt)) (u_gas(x_p) − v_p) for the particles of the bodies the user
                      named, with u_gas the trilinear interpolation of the face velocities and k (1/s) the drag
                      rate, i.e. Stokes-like drag relaxing a particle to the local air speed over 1/k seconds

What is and is not conserved: the first is a boundary condition (the gas's volume is kept by its projection; the
particles lose nothing); the second moves particle momentum towards the gas's without giving the gas the
reaction, so momentum is not conserved by the pair (the gas is treated as an external wind on light particles,
whose momentum is small beside the air's driving it). Neither direction is differentiated yet: a rollout with
gradients refuses a scene that couples gas and particles (simulator.py).
"""
import numpy as np
import taichi as ti


@ti.data_oriented
class GasParticleCoupling:
    """The two coupling kernels between a StateBuffer's slot 0 (the fast solver's state) and a GasSolver."""

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

    @ti.kernel
    def rasterize(self, x: ti.template(), v: ti.template()):
        """gas.cell_m = particle volume share per gas cell, gas.cell_mv = their mean velocity."""
        g = self.gas
        shape = ti.static(g.shape)
        for I in ti.grouped(g.cell_m):
            g.cell_m[I] = 0.0
            g.cell_mv[I] = ti.Vector([0.0, 0.0, 0.0])
        for p in range(self.model.n_particles):
            c = ti.cast(ti.floor((x[0, p] - ti.Vector(g._lower)) / g.dx), ti.i32)
            inside = 0 <= c[0] < shape[0] and 0 <= c[1] < shape[1] and 0 <= c[2] < shape[2]
            c = ti.min(ti.max(c, 0), ti.Vector([shape[0] - 1, shape[1] - 1, shape[2] - 1]))
            if inside and self.drag[p] == 0:  # the particles the gas drags ride in it and do not block it
                vol = self.model.rest_volume[p]
                g.cell_m[c] += vol
                g.cell_mv[c] += vol * v[0, p]
        for I in ti.grouped(g.cell_m):
            m = g.cell_m[I]
            if m > 0.0:
                g.cell_mv[I] = g.cell_mv[I] / m
            g.cell_m[I] = m / self.cell_volume

    @ti.kernel
    def apply_drag(self, x: ti.template(), v: ti.template(), dt: ti.f64):
        g = self.gas
        a = 1.0 - ti.exp(-self.drag_rate * dt)
        for p in range(self.model.n_particles):
            if self.drag[p] != 0:
                u = g._velocity_at(0, x[0, p])
                v[0, p] = v[0, p] + a * (u - v[0, p])

    def particles_to_gas(self, state):
        """Before a gas step: the particle cells become moving solids (with particles_block)."""
        self.rasterize(state.x, state.v)
        self.gas.particle_solids(0.5)

    def gas_to_particles(self, state, dt: float):
        if self.drag_rate > 0.0:
            self.apply_drag(state.x, state.v, dt)
