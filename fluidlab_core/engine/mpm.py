"""3-D MLS-MPM solver (APIC transfer, quadratic B-spline weights) on one dense grid shared by all materials.

One substep of length Δt (Hu et al. 2018, "A moving least squares material point method"; Jiang et al.
2015 for APIC):
    clear grid     m_i = 0, (mv)_i = 0
    P2G            F_p ← (I + Δt C_p) F_p; (F_p, τ_p) ← model(F_p, C_p)        (constitutive.py)
                   A_p = −Δt V⁰_p (4/Δx²) τ_p + m_p C_p
                   m_i += w_ip m_p,  (mv)_i += w_ip (m_p v_p + A_p (x_i − x_p))
                   (on the CPU each thread scatters into a private grid and the grids are summed, which
                   avoids atomic float adds; on a GPU the scatter is atomic)
    grid update    v_i = (mv)_i / m_i + Δt g; static colliders (statics.py); tools (tools.py); domain walls
    G2P            v_p = Σ w_ip v_i,  C_p = (4/Δx²) Σ w_ip v_i (x_i − x_p)ᵀ,  x_p ← x_p + Δt v_p;
                   particles inside a static or past a wall are put back on its surface
    rigid          rigid bodies projected to their best rigid motion (rigid.py)

Units are SI throughout (m, s, kg, Pa). The grid covers the domain [lower, upper] plus `PAD` cells on every
side, so that particles at a wall keep their whole 3×3×3 stencil on the grid; the domain walls are at
lower and upper: nodes sit at lower + (k + ½)Δx and those within half a cell of a wall remove velocity
into it, so particles stop at the wall itself. Particle rest volume V⁰ = s³ for a lattice spacing s, mass m = ρ V⁰.
"""

from dataclasses import dataclass

import numpy as np
import taichi as ti

from fluidlab_core.engine import constitutive, statics
from fluidlab_core.engine.rigid import RigidBodies

PAD = 3  # grid cells outside the domain walls on every side


@dataclass
class SolverSpec:
    """Everything the kernels need, in SI units; produced by `Scene.build`."""

    lower: np.ndarray  # domain wall positions (m)
    upper: np.ndarray
    dx: float  # grid spacing (m)
    dt: float  # substep (s)
    gravity: np.ndarray  # m/s²
    wall_friction: float
    x: np.ndarray  # (N, 3) initial positions (m)
    v: np.ndarray  # (N, 3) initial velocities (m/s)
    material_index: np.ndarray  # (N,) index into `materials`
    body_index: np.ndarray  # (N,) rigid body index or -1
    rest_volume: np.ndarray  # (N,) m³
    materials: list  # Material objects
    colliders: list  # statics.Collider objects
    tools: list  # tools.Tool objects
    body_shapes: list  # each rigid body's Shape at rest (world frame), for keeping other particles out


@ti.data_oriented
class MPMSolver:
    def __init__(self, spec: SolverSpec, real, scatter_copies: int = 0):
        self.spec = spec
        self.real = real
        n = len(spec.x)
        self.n_particles = n
        self.dx = float(spec.dx)
        self.inv_dx = 1.0 / self.dx
        self.dt = float(spec.dt)
        # nodes sit at lower + (k + ½)Δx: the outermost wall nodes are half a cell inside the walls, so
        # particles (which stop about half a cell beyond the last node that stops them) stop at the walls
        self.origin = tuple(float(v) for v in spec.lower - (PAD - 0.5) * self.dx)
        self.lower = tuple(float(v) for v in spec.lower)
        self.upper = tuple(float(v) for v in spec.upper)
        self.grid_shape = tuple(int(np.ceil((spec.upper[d] - spec.lower[d]) / self.dx - 1e-9)) + 2 * PAD
                                for d in range(3))
        self.gravity = tuple(float(g) for g in spec.gravity)
        # Nodes lighter than this are treated as empty. A node at the edge of a particle's stencil can get a
        # weight of 1e-20 or less; its mass squared underflows in float32 and the gradient of v = mv/m
        # (−mv/m²) overflows to inf, then NaN. A millionth of the lightest particle's mass drops only nodes
        # whose velocity reaches particles with weights under 1e-6.
        rest = np.asarray(spec.rest_volume, dtype=np.float64)
        dens = np.array([m.density for m in spec.materials])[np.asarray(spec.material_index)]
        self.mass_floor = float(1e-6 * (rest * dens).min()) if n else 0.0

        # models present in the scene, unrolled statically in P2G
        self.model_names = sorted({m.model for m in spec.materials})
        self.models = [constitutive.with_svd(name) for name in self.model_names]
        model_of_material = np.array([self.model_names.index(m.model) for m in spec.materials], dtype=np.int32)

        # particle state
        self.x = ti.Vector.field(3, real, shape=n)  # position (m)
        self.v = ti.Vector.field(3, real, shape=n)  # velocity (m/s)
        self.C = ti.Matrix.field(3, 3, real, shape=n)  # APIC affine velocity ≈ ∇v (1/s)
        self.F = ti.Matrix.field(3, 3, real, shape=n)  # deformation gradient (elastic part)
        self.material = ti.field(ti.i32, shape=n)  # index into material_params
        self.model = ti.field(ti.i32, shape=n)  # index into self.models
        self.rest_volume = ti.field(real, shape=n)  # V⁰ (m³)
        self.mass = ti.field(real, shape=n)  # kg
        self.pressure = ti.field(real, shape=n)  # Cauchy pressure −tr(σ)/3 (Pa), filled on request
        # material parameters (μ, λ, y1, y2, η), see Material.kernel_params
        self.material_params = ti.Vector.field(5, real, shape=len(spec.materials))

        # grid
        self.grid_m = ti.field(real, shape=self.grid_shape)  # node mass (kg)
        self.grid_v = ti.Vector.field(3, real, shape=self.grid_shape)  # node momentum, then velocity
        # CPU: one private grid per thread for a scatter without atomics (a float atomic add is a
        # compare-and-swap loop on x64 and cost ~88 % of a substep); GPU: atomics
        self.scatter_copies = int(scatter_copies)
        self.scatter_chunk = -(-n // max(self.scatter_copies, 1))
        if self.scatter_copies:
            shape = (self.scatter_copies,) + self.grid_shape
            self.grid_m_private = ti.field(real, shape=shape)  # per-thread node mass (kg)
            self.grid_v_private = ti.Vector.field(3, real, shape=shape)  # per-thread node momentum

        # NaN / infinity watch: which fields (bits 1 x, 2 v, 4 F) and the first particle found
        self.bad_field = ti.field(ti.i32, shape=())
        self.bad_particle = ti.field(ti.i32, shape=())

        np_real = np.float64 if real == ti.f64 else np.float32
        density = np.array([m.density for m in spec.materials])
        self.material_params.from_numpy(np.array([m.kernel_params() for m in spec.materials], dtype=np_real))
        self.material.from_numpy(spec.material_index.astype(np.int32))
        self.model.from_numpy(model_of_material[spec.material_index])
        self.rest_volume.from_numpy(spec.rest_volume.astype(np_real))
        self.mass.from_numpy((spec.rest_volume * density[spec.material_index]).astype(np_real))
        self.rigid = None
        if np.any(spec.body_index >= 0):
            self.rigid = RigidBodies(self, spec.body_index, real, spec.body_shapes, self.dx)
            self.rigid.set_rest(spec.x, spec.rest_volume * density[spec.material_index], spec.body_index)
        self.reset(spec.x, spec.v)

    # --- state ------------------------------------------------------------------------------------------
    def reset(self, x, v):
        np_real = self.np_real
        self.x.from_numpy(np.asarray(x, dtype=np_real))
        self.v.from_numpy(np.asarray(v, dtype=np_real))
        self.C.from_numpy(np.zeros((self.n_particles, 3, 3), dtype=np_real))
        self.F.from_numpy(np.tile(np.eye(3, dtype=np_real), (self.n_particles, 1, 1)))

    @property
    def np_real(self):
        return np.float64 if self.real == ti.f64 else np.float32

    # --- kernels ----------------------------------------------------------------------------------------
    @ti.func
    def _stencil(self, xp):
        """Base node and quadratic B-spline weights of a particle (Hu 2018, eq. 3)."""
        Xp = (xp - ti.Vector(self.origin)) * self.inv_dx
        base = ti.cast(Xp - 0.5, ti.i32)
        # never index off the grid, even for a NaN position (the NaN check then reports it)
        for d in ti.static(range(3)):
            base[d] = ti.min(ti.max(base[d], 0), self.grid_shape[d] - 3)
        fx = Xp - base
        w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
        return base, fx, w

    @ti.func
    def _particle_update(self, p):
        """P2G's per-particle work: update F and the stress; returns what the particle scatters."""
        dt, inv_dx = self.dt, self.inv_dx
        Cp = self.C[p]
        Fp = (ti.Matrix.identity(float, 3) + dt * Cp) @ self.F[p]
        tau = ti.Matrix.zero(float, 3, 3)
        prm = self.material_params[self.material[p]]
        for k in ti.static(range(len(self.models))):
            if self.model[p] == k:
                Fp, tau = self.models[k](Fp, Cp, prm)
        self.F[p] = Fp
        mp = self.mass[p]
        affine = (-dt * self.rest_volume[p] * 4.0 * inv_dx * inv_dx) * tau + mp * Cp
        return mp, mp * self.v[p], affine

    @ti.kernel
    def substep(self, tool_state: ti.types.ndarray()):
        """One MLS-MPM substep: the tools' poses and twists for it, clear grid, P2G, grid update, G2P.

        tool_state: (max(n_tools, 1), 18) rows of origin (m), rotation (row-major), linear (m/s) and angular
        (rad/s) velocity, copied into the tools' fields first (in this launch: a launch per field from Python
        cost more than the substep on small scenes). On the CPU the substep runs as three parallel loops: P2G
        into the private grids; their sum (zeroing them for the next substep) with the grid update; G2P."""
        dt, dx = self.dt, self.dx
        for k in ti.static(range(len(self.spec.tools))):
            tool = self.spec.tools[k]
            tool.position[None] = ti.Vector([tool_state[k, i] for i in ti.static(range(3))])
            tool.rotation[None] = ti.Matrix([[tool_state[k, 3 + 3 * i + j] for j in ti.static(range(3))]
                                             for i in ti.static(range(3))])
            tool.linear_velocity[None] = ti.Vector([tool_state[k, 12 + i] for i in ti.static(range(3))])
            tool.angular_velocity[None] = ti.Vector([tool_state[k, 15 + i] for i in ti.static(range(3))])
        if ti.static(self.scatter_copies == 0):
            # clear grid
            for I in ti.grouped(self.grid_m):
                self.grid_m[I] = 0.0
                self.grid_v[I] = ti.Vector.zero(float, 3)
            # P2G, atomic scatter
            for p in self.x:
                base, fx, w = self._stencil(self.x[p])
                mp, momentum, affine = self._particle_update(p)
                for offset in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
                    dpos = (offset - fx) * dx
                    weight = w[offset[0]][0] * w[offset[1]][1] * w[offset[2]][2]
                    self.grid_v[base + offset] += weight * (momentum + affine @ dpos)
                    self.grid_m[base + offset] += weight * mp
            for I in ti.grouped(self.grid_m):
                self._grid_update(I, self.grid_m[I], self.grid_v[I])
        else:
            # P2G: each thread scatters its share of particles into its own grid, without atomics (the grids
            # are zero: allocated so, and zeroed again as they are summed)
            ti.loop_config(block_dim=1)
            for c in range(self.scatter_copies):
                for p in range(c * self.scatter_chunk, ti.min((c + 1) * self.scatter_chunk, self.n_particles)):
                    base, fx, w = self._stencil(self.x[p])
                    mp, momentum, affine = self._particle_update(p)
                    for offset in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
                        dpos = (offset - fx) * dx
                        weight = w[offset[0]][0] * w[offset[1]][1] * w[offset[2]][2]
                        i, j, k = base[0] + offset[0], base[1] + offset[1], base[2] + offset[2]
                        self.grid_v_private[c, i, j, k] = self.grid_v_private[c, i, j, k] + weight * (
                            momentum + affine @ dpos)
                        self.grid_m_private[c, i, j, k] = self.grid_m_private[c, i, j, k] + weight * mp
            # sum the private grids (zeroing them) and update the node
            for I in ti.grouped(self.grid_m):
                m = 0.0
                mv = ti.Vector.zero(float, 3)
                for c in range(self.scatter_copies):
                    m += self.grid_m_private[c, I[0], I[1], I[2]]
                    mv += self.grid_v_private[c, I[0], I[1], I[2]]
                    self.grid_m_private[c, I[0], I[1], I[2]] = 0.0
                    self.grid_v_private[c, I[0], I[1], I[2]] = ti.Vector.zero(float, 3)
                self._grid_update(I, m, mv)
        # G2P
        for p in self.x:
            new_v, new_C = self._gather(self.grid_v, self.x[p])
            xp = self.x[p] + dt * new_v
            # statics: particles found inside are put back on the surface
            for k in ti.static(range(len(self.spec.colliders))):
                xp, new_v = self.spec.colliders[k].particle(xp, new_v)
            # domain walls: the same for particles past a wall
            xp, new_v = self._clamp_to_walls(xp, new_v)
            self.v[p] = new_v
            self.C[p] = new_C
            self.x[p] = xp

    @ti.func
    def _grid_update(self, I, m, mv):
        """Node I's mass and velocity from its mass and momentum: gravity, statics, tools, walls (nodes lighter
        than mass_floor keep their momentum, which G2P weighs as a velocity of about zero)."""
        self.grid_m[I] = m
        vn = mv
        if m > self.mass_floor:
            vn = mv / m + self.dt * ti.Vector(self.gravity)
            xn = ti.Vector(self.origin) + I * self.dx
            for k in ti.static(range(len(self.spec.colliders))):
                vn = self.spec.colliders[k].grid(xn, vn)
            for k in ti.static(range(len(self.spec.tools))):
                vn = self.spec.tools[k].contact(xn, vn)
            vn = self._walls(xn, vn)
        self.grid_v[I] = vn

    @ti.func
    def _gather(self, grid_v, xp):
        """G2P's gather at position xp: v_p = Σ w_ip v_i and C_p = (4/Δx²) Σ w_ip v_i (x_i − x_p)ᵀ."""
        base, fx, w = self._stencil(xp)
        new_v = ti.Vector.zero(float, 3)
        new_C = ti.Matrix.zero(float, 3, 3)
        for offset in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
            dpos = offset - fx
            weight = w[offset[0]][0] * w[offset[1]][1] * w[offset[2]][2]
            g_v = grid_v[base + offset]
            new_v += weight * g_v
            new_C += (4.0 * self.inv_dx * weight) * g_v.outer_product(dpos)
        return new_v, new_C

    @ti.func
    def _walls(self, xn, vn):
        """Domain walls at lower/upper: nodes within half a cell of a wall lose their velocity into it
        (slip, optional Coulomb friction). Whole-vector updates only: Taichi's reverse mode mishandles a
        vector component written inside a runtime branch."""
        half = 0.5 * self.dx
        for d in ti.static(range(3)):
            into = (xn[d] < self.lower[d] + half * 1.01 and vn[d] < 0.0) or \
                (xn[d] > self.upper[d] - half * 1.01 and vn[d] > 0.0)
            if into:
                normal_speed = ti.abs(vn[d])
                vn = vn * (1.0 - ti.Vector.unit(3, d, float))
                if ti.static(self.spec.wall_friction > 0.0):
                    vt_norm = statics.safe_norm(vn)
                    if vt_norm > 1e-12:
                        vn *= ti.max(0.0, 1.0 - self.spec.wall_friction * normal_speed / vt_norm)
        return vn

    @ti.func
    def _clamp_to_walls(self, xp, vp):
        """Particles past a wall go back onto it and lose their velocity into it (whole-vector form, see
        _walls)."""
        lo, hi = ti.Vector(self.lower), ti.Vector(self.upper)
        below = ti.cast(xp < lo, float)
        above = ti.cast(xp > hi, float)
        xp = ti.min(ti.max(xp, lo), hi)
        vp = vp - below * ti.min(vp, 0.0) - above * ti.max(vp, 0.0)
        return xp, vp

    @ti.kernel
    def read_xv(self, x: ti.types.ndarray(), v: ti.types.ndarray()):
        """Positions and velocities into (N, 3) arrays of any float type, in one launch (a rollout's loss reads
        both after every step)."""
        for p in range(self.n_particles):
            for i in ti.static(range(3)):
                x[p, i] = self.x[p][i]
                v[p, i] = self.v[p][i]

    @ti.kernel
    def find_nonfinite(self) -> ti.i32:
        """Flag the fields holding a NaN or infinity (bits: 1 x, 2 v, 4 F) and the first such particle; returns
        the bits (so that a check that finds nothing costs one launch)."""
        self.bad_field[None] = 0
        self.bad_particle[None] = self.n_particles
        for p in self.x:
            bits = 0
            if not (ti.abs(self.x[p]).max() < 1e30):
                bits |= 1
            if not (ti.abs(self.v[p]).max() < 1e30):
                bits |= 2
            if not (ti.abs(self.F[p]).max() < 1e30):
                bits |= 4
            if bits > 0:
                ti.atomic_or(self.bad_field[None], bits)
                ti.atomic_min(self.bad_particle[None], p)
        return self.bad_field[None]

    @ti.kernel
    def compute_pressure(self):
        """Cauchy pressure p = −tr(τ)/(3J) of every particle from its current state."""
        for p in self.x:
            Fp = self.F[p]
            tau = ti.Matrix.zero(float, 3, 3)
            prm = self.material_params[self.material[p]]
            for k in ti.static(range(len(self.models))):
                if self.model[p] == k:
                    _, tau = self.models[k](Fp, self.C[p], prm)
            self.pressure[p] = -tau.trace() / (3.0 * Fp.determinant())
