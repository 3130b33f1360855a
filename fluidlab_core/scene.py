"""Scene building: a domain in the world frame, particle bodies, static colliders; `build()` makes a
`Simulator`.

    scene = Scene(lower=(0.3, -0.2, 0.0), upper=(0.7, 0.2, 0.4), grid_res=64, dt=2e-3, substeps=10)
    water = scene.add_particles(Box((0.35, -0.1, 0.02), (0.5, 0.1, 0.2)), materials.WATER, name="water")
    scene.add_static(Cup(...), friction=0.3)
    sim = scene.build()

Units: metres, seconds, kilograms; the world frame is REP-103 (z up), gravity (0, 0, −9.81) m/s² unless set.
Grid: Δx = (longest side of the domain) / grid_res; the other axes get as many cells as they need. Particles
are sampled on a lattice of spacing Δx/2 (8 per cell) unless `particle_spacing` says otherwise.

Stability is checked at build. The explicit solver needs, for the substep Δt = dt / substeps,
    Δt ≤ cfl · Δx / (c_max + v_max)        c_max = max over materials of sqrt((λ + 2μ)/ρ)
    Δt ≤ ρ Δx² / (6 (η + ζ))               for each material with a shear or bulk viscosity (explicit diffusion)
with cfl = 0.5 and v_max the fastest expected speed (`max_speed`, default: the initial speeds plus the
free-fall speed sqrt(2 g H) over the domain height H, or the tools' max_speed if faster). A scene that breaks either is refused with the
numbers and the substep count that would satisfy it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fluidlab_core import materials as M
from fluidlab_core import shapes as S

CFL_NUMBER = 0.5
MIN_WALL_CELLS = 2.0  # thinnest container wall, in grid cells (see engine/statics.py)


class UnstableTimeStepError(ValueError):
    """The scene's substep is larger than the explicit solver's stability limit."""


@dataclass(frozen=True)
class ParticleHandle:
    """A body of particles in a scene: rows start:start+count of every particle array."""

    name: str
    index: int
    start: int
    count: int
    material: M.Material
    body: int  # rigid body index, or −1
    emitter: int = -1  # the emitter whose pool these particles are (emitted in row order), or −1

    @property
    def slice(self) -> slice:
        return slice(self.start, self.start + self.count)


@dataclass(frozen=True)
class StaticHandle:
    name: str
    shape: S.Shape
    friction: float
    sticky: bool


@dataclass(frozen=True)
class _Body:
    handle: ParticleHandle
    points: np.ndarray  # (n, 3) m
    velocity: np.ndarray  # (n, 3) m/s
    rest_volume: float  # what each particle stands for (m³): the sampling lattice's cell volume
    shape: S.Shape

def _pose7(what: str, pose) -> np.ndarray:
    """(x, y, z, qx, qy, qz, qw) as floats, refused unless finite with a non-zero quaternion."""
    pose = np.asarray(pose, dtype=float)
    if pose.shape != (7,) or not np.all(np.isfinite(pose)) or np.linalg.norm(pose[3:]) < 1e-9:
        raise ValueError(f"{what}: pose must be (x, y, z, qx, qy, qz, qw) with a non-zero quaternion, got {pose!r}")
    return pose


def _vec3(name, value):
    arr = np.asarray(value, dtype=float)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    return arr


class Scene:
    def __init__(self, lower=(0.0, 0.0, 0.0), upper=(1.0, 1.0, 1.0), grid_res: int = 64, dt: float = 2e-3,
                 substeps: int = 10, gravity=(0.0, 0.0, -9.81), particle_spacing: float | None = None,
                 max_speed: float | None = None, wall_friction: float = 0.0, seed: int = 0,
                 contact_fill: float = 0.97, flip: float | None = None, jbar: bool | str = False,
                 pressure: str = "state"):
        """lower/upper: the domain walls (m). grid_res: cells along the longest side. dt: one `step` (s),
        split into `substeps`. particle_spacing: sampling lattice (m, default Δx/2). max_speed: fastest
        expected speed for the stability check (m/s). wall_friction: Coulomb coefficient of the domain walls.
        seed: seeds particle jitter. contact_fill: the volume fill of a grid node at which fluids and solids
        share a velocity there (engine/grid.py: two velocity fields; in (0, 2], default 0.97). flip: the share
        α in [0, 1) of FLIP in the liquids' velocity update (AFLIP, Fei et al. 2021): 0 is APIC (the default and
        the paper's); α > 0 gives back α of each liquid particle's own velocity detail, which APIC smooths away at
        every transfer (less numerical viscosity). jbar: the liquids' J averaged through the grid before each
        substep (J-bar; "affine": fitted affinely at each node, exact for a linear J where the liquid ends). Both
        are forward only (no gradients) and change how floating bodies sit (docs/engine.md); engine/transfer.py
        has the formulas. pressure: the liquids' pressure, "state" (the default: weakly compressible, from each
        particle's volume change by its equation of state) or "projection" (incompressible: the pressure from a
        Poisson solve on the grid, with one rigid body's velocity, or the deformable solids' nodes' velocities, as
        unknowns of the same solve, so that a body floats at Archimedes' depth; engine/projection.py). "projection"
        is forward only, for liquids (of one density or several) with one rigid body or deformable solids (not
        both), statics and tools (a rigid body meets them through engine/rigid.py's contact), emitters and gas (a
        liquid's bulk viscosity or damping, which act on its pressure, are then dropped: the projection sets the
        pressure; its shear viscosity stays); its flip defaults to 0.99 (docs/engine.md, "Floating bodies: the projection"). flip defaults to 0 (APIC)
        otherwise."""
        self.lower, self.upper = _vec3("lower", lower), _vec3("upper", upper)
        if not np.all(self.lower < self.upper):
            raise ValueError(f"the domain needs lower < upper on every axis, got lower={tuple(self.lower)}, "
                             f"upper={tuple(self.upper)}")
        if not (isinstance(grid_res, (int, np.integer)) and grid_res >= 4):
            raise ValueError(f"grid_res must be an integer >= 4, got {grid_res!r}")
        if not (dt > 0 and math.isfinite(dt)):
            raise ValueError(f"dt must be a positive number of seconds, got {dt!r}")
        if not (isinstance(substeps, (int, np.integer)) and substeps >= 1):
            raise ValueError(f"substeps must be an integer >= 1, got {substeps!r}")
        if wall_friction < 0:
            raise ValueError(f"wall_friction must be >= 0, got {wall_friction}")
        if not (0.0 < contact_fill <= 2.0):
            raise ValueError(f"contact_fill must be in (0, 2] (a node's volume fill), got {contact_fill!r}")
        self.contact_fill = float(contact_fill)
        if pressure not in ("state", "projection"):
            raise ValueError(f"pressure must be 'state' (equation of state) or 'projection' (engine/projection.py), "
                             f"got {pressure!r}")
        self.pressure = pressure
        if flip is None:
            flip = 0.99 if pressure == "projection" else 0.0
        if not (0.0 <= flip < 1.0):
            raise ValueError(f"flip must be in [0, 1) (the FLIP share of the liquids' velocity update), got {flip!r}")
        self.flip = float(flip)
        if jbar not in (False, True, "affine"):
            raise ValueError(f"jbar must be False, True or 'affine', got {jbar!r}")
        self.jbar = jbar
        self.grid_res = int(grid_res)
        self.dx = float((self.upper - self.lower).max() / self.grid_res)
        self.dt = float(dt)
        self.substeps = int(substeps)
        self.gravity = _vec3("gravity", gravity)
        self.particle_spacing = float(particle_spacing) if particle_spacing else 0.5 * self.dx
        if self.particle_spacing <= 0:
            raise ValueError(f"particle_spacing must be positive, got {particle_spacing}")
        self.max_speed = max_speed
        self.wall_friction = float(wall_friction)
        self.rng = np.random.default_rng(seed)
        self.bodies: list[_Body] = []
        self.statics: list[StaticHandle] = []
        self.tools: list = []  # engine.tools.ToolSpec
        self.emitters: list = []  # engine.emitters.EmitterSpec
        self.gas = None  # fluidlab_core.gas.GasSpec once add_gas was called
        self._n_particles = 0
        self._n_rigid = 0

    @property
    def substep_dt(self) -> float:
        return self.dt / self.substeps

    # --- contents ---------------------------------------------------------------------------------------
    def add_particles(self, shape: S.Shape, material: M.Material, name: str | None = None,
                      velocity=(0.0, 0.0, 0.0), spacing: float | None = None, jitter: float = 0.0) -> ParticleHandle:
        """Fill `shape` with particles of `material`, moving at `velocity` (m/s). Returns a handle for
        `Simulator.positions` and friends. A rigid material makes one rigid body per call."""
        if not isinstance(material, M.Material):
            raise TypeError(f"material must be a fluidlab_core.materials.Material, got {type(material).__name__}")
        if isinstance(shape, S.CONTAINERS):
            raise ValueError(f"{type(shape).__name__} is a container: add it with add_static(), and fill its "
                             f"interior() with particles")
        name = name or f"{material.name}_{len(self.bodies)}"
        if any(b.handle.name == name for b in self.bodies):
            raise ValueError(f"a particle body named {name!r} already exists")
        s = float(spacing) if spacing else self.particle_spacing
        points = shape.sample(s, rng=self.rng, jitter=jitter)
        cell = shape.cell_volume(s)
        try:
            volume = shape.volume()
        except NotImplementedError:  # a user-defined shape may not know its volume
            volume = len(points) * cell
        if len(points) == 0 or volume < 0.5 * cell:
            raise ValueError(f"{name!r}: the shape ({volume:.3g} m³) holds no particle at spacing {s:.4g} m; "
                             f"make it larger or the spacing smaller")
        lo, hi = points.min(axis=0), points.max(axis=0)
        if np.any(lo < self.lower) or np.any(hi > self.upper):
            raise ValueError(f"{name!r}: particles span {tuple(np.round(lo, 4))}..{tuple(np.round(hi, 4))} m, outside "
                             f"the domain {tuple(self.lower)}..{tuple(self.upper)} m")
        vel = np.broadcast_to(_vec3("velocity", velocity), points.shape).copy()
        body = -1
        if material.is_rigid:
            body, self._n_rigid = self._n_rigid, self._n_rigid + 1
        handle = ParticleHandle(name, len(self.bodies), self._n_particles, len(points), material, body)
        self._n_particles += len(points)
        self.bodies.append(_Body(handle, points, vel, cell, shape))
        return handle

    def add_static(self, shape: S.Shape, friction: float = 0.5, sticky: bool = False,
                   name: str | None = None) -> StaticHandle:
        """A fixed collider: a primitive, a container (Cup, Tank) or a Mesh. friction: Coulomb coefficient;
        sticky: particles touching it stop."""
        if not isinstance(shape, S.Shape):
            raise TypeError(f"shape must be a fluidlab_core.shapes.Shape, got {type(shape).__name__}")
        if not (friction >= 0 and math.isfinite(friction)):
            raise ValueError(f"friction must be a finite number >= 0, got {friction!r}")
        handle = StaticHandle(name or f"static_{len(self.statics)}", shape, float(friction), bool(sticky))
        self.statics.append(handle)
        return handle

    def add_tool(self, shape: S.Shape, pose=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0), name: str | None = None,
                 friction: float = 0.0, softness: float | None = None, action_mask=(1, 1, 1, 1, 1, 1),
                 workspace=None, max_speed: float = 1.0, keep_out: bool = False):
        """A kinematic tool moved by `Simulator.step(action)` (see fluidlab_core.engine.tools).

        shape: its geometry in the tool's own frame (m); pose: initial (x, y, z, qx, qy, qz, qw) of the tool
        frame in the world; friction: Coulomb coefficient; softness: soft contact sharpness in 1/m (None:
        hard contact); action_mask: which of (vx, vy, vz, wx, wy, wz) the action drives; workspace:
        ((x, y, z), (x, y, z)) bounds on the tool position; max_speed: fastest tool point (m/s), for the
        stability check; keep_out: after each substep put particles found inside the tool back on its surface
        (for a tool that carries fluid: a glass, a cone; its walls must be 2 cells thick, as a static's)."""
        from fluidlab_core.engine.tools import ToolSpec

        if not isinstance(shape, S.Shape):
            raise TypeError(f"shape must be a fluidlab_core.shapes.Shape, got {type(shape).__name__}")
        pose = np.asarray(pose, dtype=float)
        if pose.shape != (7,) or not np.all(np.isfinite(pose)) or np.linalg.norm(pose[3:]) < 1e-9:
            raise ValueError(f"tool pose must be (x, y, z, qx, qy, qz, qw) with a non-zero quaternion, got {pose!r}")
        mask = np.asarray(action_mask, dtype=bool)
        if mask.shape != (6,):
            raise ValueError(f"action_mask must be 6 booleans for (vx, vy, vz, wx, wy, wz), got {action_mask!r}")
        if softness is not None and not (softness > 0 and math.isfinite(softness)):
            raise ValueError(f"softness must be a positive number (1/m) or None for hard contact, got {softness!r}")
        if not (friction >= 0 and math.isfinite(friction)):
            raise ValueError(f"friction must be a finite number >= 0, got {friction!r}")
        if workspace is not None:
            lo, hi = _vec3("workspace lower", workspace[0]), _vec3("workspace upper", workspace[1])
            if not np.all(lo <= hi) or not np.all((pose[:3] >= lo) & (pose[:3] <= hi)):
                raise ValueError(f"workspace {tuple(lo)}..{tuple(hi)} must have lower <= upper and contain the "
                                 f"tool's initial position {tuple(pose[:3])}")
            workspace = (lo, hi)
        name = name or f"tool_{len(self.tools)}"
        if any(t.name == name for t in self.tools):
            raise ValueError(f"a tool named {name!r} already exists")
        if keep_out and isinstance(shape, S.CONTAINERS) and shape.thinnest_wall() < MIN_WALL_CELLS * self.dx - 1e-12:
            raise ValueError(f"tool {name!r}: wall thickness {shape.thinnest_wall():.4g} m is under 2 grid cells "
                             f"({MIN_WALL_CELLS * self.dx:.4g} m): the fluid it carries would leak through it")
        spec = ToolSpec(name, shape, pose[:3].copy(), pose[3:] / np.linalg.norm(pose[3:]), float(friction),
                        None if softness is None else float(softness), mask, workspace, float(max_speed),
                        keep_out=bool(keep_out))
        self.tools.append(spec)
        return spec

    def add_emitter(self, material: M.Material, rate: float, nozzle: str = "disc", size=0.005, speed=None,
                    pose=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0), tool=None, name: str | None = None,
                    pool: int | None = None, duration: float | None = None) -> ParticleHandle:
        """A nozzle that adds `material` to the scene while it runs (engine/emitters.py has the equations).

        rate: volumetric flow rate (m³/s). nozzle: "disc" (size: radius, m) or "rectangle" (size: (width,
        height), m), in the xy plane of the nozzle frame; the fluid leaves along the frame's +z axis. speed:
        exit speed (m/s; default rate / area, at which the stream leaves at rest density). pose: (x, y, z, qx,
        qy, qz, qw) of the nozzle frame in the world, or in the tool's frame when `tool` (a tool from
        add_tool, or its name) carries it. pool: particles to allocate (rounded up to whole rows), or
        duration: seconds of emission to allocate for; one of them is needed. Returns the handle of the
        emitted body (its rows hold the pool; readers return the particles emitted so far)."""
        from fluidlab_core.engine.emitters import EmitterSpec, blocked_reason, pool_for

        if not isinstance(material, M.Material):
            raise TypeError(f"material must be a fluidlab_core.materials.Material, got {type(material).__name__}")
        if material.is_rigid:
            raise ValueError(f"emitter: a rigid material ({material.name}) cannot be emitted; rigid bodies are "
                             f"added with add_particles")
        name = name or f"{material.name}_emitted_{len(self.emitters)}"
        if any(b.handle.name == name for b in self.bodies):
            raise ValueError(f"a particle body named {name!r} already exists")
        pose = _pose7(f"emitter {name!r}", pose)
        tool_index = self._carrier(f"emitter {name!r}", tool)
        spec = EmitterSpec(name, material, nozzle, size, rate, None if speed is None else float(speed),
                           pose[:3].copy(), pose[3:] / np.linalg.norm(pose[3:]), tool_index, self.particle_spacing)
        extent = float((self.upper - self.lower).min())
        across = 2.0 * spec.size if spec.shape == "disc" else max(spec.size)
        if across >= extent:
            raise ValueError(f"emitter {name!r}: the nozzle ({across:.4g} m across) is larger than the domain's "
                             f"smallest side ({extent:.4g} m)")
        if pool is None and duration is None:
            raise ValueError(f"emitter {name!r}: give its pool (particles) or the duration (s) to allocate for")
        if pool is not None:
            if int(pool) < spec.n_row:
                raise ValueError(f"emitter {name!r}: a pool of {pool} particles is smaller than one row of its "
                                 f"nozzle ({spec.n_row} particles at spacing {spec.spacing:.4g} m)")
            spec.pool = -(-int(pool) // spec.n_row) * spec.n_row
        else:
            if not (duration > 0 and math.isfinite(duration)):
                raise ValueError(f"emitter {name!r}: duration must be a positive number of seconds, got {duration!r}")
            spec.pool = pool_for(spec, float(duration))
        parent = self.tools[tool_index] if tool_index is not None else None
        from scipy.spatial.transform import Rotation

        tool_R = Rotation.from_quat(parent.quaternion).as_matrix() if parent is not None else None
        why = blocked_reason(spec, self.statics, self.lower, self.upper, self.dx,
                             parent.position if parent is not None else None, tool_R)
        if why:
            where = f"at the initial pose of tool {parent.name!r}" if parent is not None else "where it is fixed"
            raise ValueError(f"emitter {name!r} cannot emit {where}: {why}; move the nozzle")
        from fluidlab_core.engine.emitters import nozzle_world_points

        exit_centre = nozzle_world_points(spec, parent.position if parent is not None else None, tool_R).mean(axis=0)
        points = np.tile(exit_centre, (spec.pool, 1))  # parked at the nozzle until emitted
        handle = ParticleHandle(name, len(self.bodies), self._n_particles, spec.pool, material, -1,
                                emitter=len(self.emitters))
        self._n_particles += spec.pool
        self.bodies.append(_Body(handle, points, np.zeros_like(points), spec.particle_volume, None))
        self.emitters.append(spec)
        return handle

    # --- gas (air, smoke) ---------------------------------------------------------------------------------
    def add_gas(self, resolution: int | None = None, lower=None, upper=None, walls="closed",
                ambient_temperature: float = 293.15, initial_temperature: float | None = None,
                air_density: float = 1.2, buoyancy_temperature: float | None = None,
                buoyancy_smoke: float | None = None, vorticity: float = 0.0, viscosity: float = 0.0,
                advection: str = "maccormack", limiter: str = "cell", tolerance: float = 1e-6,
                max_iterations: int = 200, on_fail: str = "raise", max_cfl: float = 2.0, scalars=(), substeps: int = 1,
                statics_block: bool = True, tools_block: bool = True, particles_block: bool = False,
                particle_drag: float = 0.0, drag_bodies=None, check_every: int = 1, tool_faces: str = "cells",
                static_faces: str = "cells", particle_faces: str = "cells"):
        """Fill a box of the domain with gas (air and smoke), simulated on a grid of its own (engine/gas.py has the
        equations). A scene with gas and no particles builds a GasSimulator (fluidlab_core/gas_simulator.py).

        resolution: cells along the gas box's longest side (default the scene's grid_res); lower/upper: the gas
        box (m, default the domain; it must lie inside it). walls: "closed" (no flow through), "open" (p = 0
        outside: outflow and inflow), an inflow velocity (vx, vy, vz) m/s, one for all faces or a dict over
        "x-", "x+", "y-", "y+", "z-", "z+" (others closed). Temperatures in K (initial: the ambient by default);
        air_density kg/m³. Buoyancy a = g (κ s − β (T − T_amb)): β in 1/K (default 1/T_amb, an ideal gas), κ in
        m³/kg (default 1/air_density). vorticity: the confinement strength ε (0: off); viscosity: kinematic ν in
        m²/s (0: off; explicit, so ν dt/Δx² ≤ 1/6 per gas substep). advection: "maccormack" (second order,
        clamped) or "semi-lagrangian"; limiter: MacCormack's clamp range, "cell" (the 8 values the point was
        interpolated from, the usual one; it jumps as the point crosses into the next cell) or "continuous" (the
        interpolated minimum and maximum of each value's 27 neighbours: looser, and continuous in the point, so
        the loss has no jumps from it; engine/gas.py). tolerance: relative residual of the pressure solve (MGPCG), at most
        max_iterations; on_fail: "raise" or "warn" when it is not reached. max_cfl: the most cells the flow may
        cross in one gas step (checked at build from the sources' speeds and every step from the flow). scalars:
        names of extra advected scalars. substeps: gas steps per scene step. statics_block / tools_block /
        particles_block: which solids the gas flows around (particles: MPM cells at least half full move the gas
        with them); particle_drag: 1/s, the rate at which the gas drags particles towards its velocity (0: none),
        on the particle bodies named in drag_bodies (default all), which ride in the gas and do not block it:
        engine/gas_coupling.py. tool_faces: how a blocking tool enters the pressure projection: "cells" (a cell
        whose centre is inside the tool is solid, so the flow's boundary moves a whole cell at a time as the tool
        moves) or "fractions" (each cell face is open by the share of its area outside the tool, Batty et al.
        2007, so the boundary and the flux through it move continuously with the tool's pose). static_faces: the
        same for statics ("fractions": a curved or slanted static is seen by its area, not as a staircase of
        cells; computed once at build). particle_faces (with particles_block): "cells" (cells at least half full of
        particles are solid) or "fractions" (the particles' volume share at each face, deposited with trilinear
        weights, shuts that part of it, moving at their mean velocity there: continuous in their positions).
        """
        from fluidlab_core.gas import ADVECTIONS, LIMITERS, TOOL_FACES, GasSpec, _number, parse_walls

        if self.gas is not None:
            raise ValueError("the scene already has gas (add_gas once)")
        lo = self.lower if lower is None else _vec3("gas lower", lower)
        hi = self.upper if upper is None else _vec3("gas upper", upper)
        tol = 1e-9 * float(np.max(self.upper - self.lower))
        if not np.all(lo < hi):
            raise ValueError(f"the gas box needs lower < upper on every axis, got {tuple(lo)}..{tuple(hi)}")
        if np.any(lo < self.lower - tol) or np.any(hi > self.upper + tol):
            raise ValueError(f"the gas box {tuple(lo)}..{tuple(hi)} m does not fit the scene's domain "
                             f"{tuple(self.lower)}..{tuple(self.upper)} m")
        res = self.grid_res if resolution is None else resolution
        if not (isinstance(res, (int, np.integer)) and res >= 2):
            raise ValueError(f"gas resolution must be an integer >= 2 (cells along the longest side), got {res!r}")
        dx = float((hi - lo).max() / int(res))
        shape = tuple(max(1, int(round(float(e) / dx))) for e in (hi - lo))
        if advection not in ADVECTIONS:
            raise ValueError(f"advection must be one of {ADVECTIONS}, got {advection!r}")
        if limiter not in LIMITERS:
            raise ValueError(f"limiter must be one of {LIMITERS}, got {limiter!r}")
        if on_fail not in ("raise", "warn"):
            raise ValueError(f"on_fail must be 'raise' or 'warn', got {on_fail!r}")
        for what, value in (("tool_faces", tool_faces), ("static_faces", static_faces),
                            ("particle_faces", particle_faces)):
            if value not in TOOL_FACES:
                raise ValueError(f"{what} must be one of {TOOL_FACES}, got {value!r}")
        if particle_faces == "fractions" and not particles_block:
            raise ValueError("particle_faces='fractions' says how particles block the gas: it needs "
                             "particles_block=True")
        if not (isinstance(substeps, (int, np.integer)) and substeps >= 1):
            raise ValueError(f"gas substeps must be an integer >= 1, got {substeps!r}")
        if not (isinstance(max_iterations, (int, np.integer)) and max_iterations >= 1):
            raise ValueError(f"max_iterations must be an integer >= 1, got {max_iterations!r}")
        tolerance = _number("tolerance", tolerance, 0.0, strict=True)
        if tolerance >= 1.0:
            raise ValueError(f"tolerance is a relative residual below 1, got {tolerance}")
        names = tuple(str(n) for n in scalars)
        for n in names:
            if not n.isidentifier() or n in ("temperature", "smoke", "velocity"):
                raise ValueError(f"scalar name {n!r} must be an identifier other than temperature, smoke, velocity")
        if len(set(names)) != len(names):
            raise ValueError(f"scalar names must be unique, got {names}")
        self.gas = GasSpec(
            lower=lo, shape=shape, dx=dx, walls=parse_walls(walls), gravity=self.gravity.copy(),
            ambient_temperature=_number("ambient_temperature", ambient_temperature, 0.0, strict=True),
            initial_temperature=_number("initial_temperature", initial_temperature, 0.0, strict=True,
                                        allow_none=True),
            air_density=_number("air_density", air_density, 0.0, strict=True),
            buoyancy_temperature=_number("buoyancy_temperature", buoyancy_temperature, allow_none=True),
            buoyancy_smoke=_number("buoyancy_smoke", buoyancy_smoke, allow_none=True),
            vorticity=_number("vorticity", vorticity, 0.0), viscosity=_number("viscosity", viscosity, 0.0),
            advection=advection, limiter=limiter, tolerance=tolerance, max_iterations=int(max_iterations), on_fail=on_fail,
            max_cfl=_number("max_cfl", max_cfl, 0.0, strict=True), scalars=names, substeps=int(substeps),
            statics_block=bool(statics_block), tools_block=bool(tools_block), particles_block=bool(particles_block),
            tool_faces=tool_faces, static_faces=static_faces, particle_faces=particle_faces,
            particle_drag=_number("particle_drag", particle_drag, 0.0), check_every=int(check_every),
            drag_bodies=None if drag_bodies is None else tuple(str(b) for b in drag_bodies))
        return self.gas

    def add_gas_source(self, name: str | None = None, shape: str = "box", size=(0.01, 0.01, 0.01),
                       pose=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0), tool=None, speed: float | None = None,
                       temperature: float | None = None, smoke: float | None = None, scalars: dict | None = None,
                       relaxation_time: float = 0.0):
        """An inflow (vent, fan, heater) in the gas: inside its region it sets the velocity to `speed` (m/s) along
        its frame's +z axis, the temperature (K), the smoke density (kg/m³) and named scalars (those given; None
        leaves a field alone), fully each step or, with relaxation_time τ (s), by 1 − exp(−Δt/τ) of the way.
        shape: "box" (size: half extents (3,) m) or "disc" (size: (radius, half thickness) m) in its frame;
        pose: (x, y, z, qx, qy, qz, qw) of that frame in the world, or in the frame of `tool` (a tool or its
        name), which then carries it. Its parameters have gradients (GasRolloutResult.grad_sources)."""
        from fluidlab_core.gas import GasSourceSpec, _number

        if self.gas is None:
            raise ValueError("add_gas() before adding gas sources")
        name = name or f"source_{len(self.gas.sources)}"
        if any(src.name == name for src in self.gas.sources):
            raise ValueError(f"a gas source named {name!r} already exists")
        if shape == "box":
            size = _vec3(f"source {name!r} size", size)
        elif shape == "disc":
            size = tuple(float(v) for v in np.asarray(size, dtype=np.float64).reshape(-1))
            if len(size) != 2:
                raise ValueError(f"source {name!r}: a disc's size is (radius, half thickness) in m, got {size}")
        else:
            raise ValueError(f"source {name!r}: shape must be 'box' or 'disc', got {shape!r}")
        if not all(v > 0 and math.isfinite(v) for v in size):
            raise ValueError(f"source {name!r}: size must be positive (m), got {tuple(size)}")
        pose = _pose7(f"source {name!r}", pose)
        tool_index = self._carrier(f"source {name!r}", tool)
        values = {k: _number(f"source {name!r} {k}", v, allow_none=True)
                  for k, v in (("speed", speed), ("temperature", temperature), ("smoke", smoke))}
        if values["temperature"] is not None and values["temperature"] <= 0:
            raise ValueError(f"source {name!r}: temperature is in kelvin and must be > 0, got {temperature}")
        extra = {}
        for k, v in (scalars or {}).items():
            if k not in self.gas.scalars:
                raise ValueError(f"source {name!r}: unknown scalar {k!r}; add_gas(scalars=...) names "
                                 f"{self.gas.scalars or 'none'}")
            extra[k] = _number(f"source {name!r} scalar {k}", v)
        if all(v is None for v in values.values()) and not extra:
            raise ValueError(f"source {name!r} sets nothing: give speed, temperature, smoke or scalars")
        src = GasSourceSpec(name, shape, tuple(size), pose[:3].copy(), pose[3:] / np.linalg.norm(pose[3:]),
                            tool_index, values["speed"], values["temperature"], values["smoke"], extra,
                            _number("relaxation_time", relaxation_time, 0.0))
        self.gas.sources.append(src)
        return src

    def add_gas_sink(self, name: str | None = None, shape: str = "box", size=(0.01, 0.01, 0.01),
                     pose=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0), tool=None, suction: float | None = None,
                     relaxation_time: float = 0.0):
        """A sink: inside its region smoke and named scalars go to 0 (at once, or over relaxation_time s) and, with
        `suction` (m/s), the gas is drawn in along its frame's −z axis. Same shapes and frames as a source."""
        if self.gas is None:
            raise ValueError("add_gas() before adding gas sinks")
        speed = None if suction is None else -abs(float(suction))
        return self.add_gas_source(name or f"sink_{len(self.gas.sources)}", shape, size, pose, tool, speed=speed,
                                   smoke=0.0, scalars={k: 0.0 for k in self.gas.scalars},
                                   relaxation_time=relaxation_time)

    def gas_limits(self) -> dict:
        """The gas step's limits for what the scene holds now: the expected fastest flow (sources, inflow walls,
        tools; m/s), the CFL number it gives per gas substep, and the explicit viscosity number ν Δt/Δx²."""
        g = self.gas
        speeds = [abs(src.speed) + (self.tools[src.tool].max_speed if src.tool is not None else 0.0)
                  for src in g.sources if src.speed is not None]
        speeds += [float(np.linalg.norm(w)) for w in g.walls if not isinstance(w, str)]
        if g.tools_block:
            speeds += [t.max_speed for t in self.tools]
        v = max(speeds, default=0.0)
        sub = self.dt / g.substeps
        return {"speed": v, "cfl": v * sub / g.dx, "viscous": g.viscosity * sub / g.dx ** 2, "dx": g.dx,
                "substep": sub}

    def _carrier(self, what: str, tool) -> int | None:
        """The index of the tool (or tool name) that carries an emitter or a source, None for the world."""
        if tool is None:
            return None
        key = tool if isinstance(tool, str) else getattr(tool, "name", None)
        names = [t.name for t in self.tools]
        if key not in names:
            raise ValueError(f"{what}: no tool {key!r} to carry it; tools: {', '.join(names) or 'none'}")
        return names.index(key)

    # --- checks -----------------------------------------------------------------------------------------
    def stability_limits(self) -> dict:
        """The substep limits of the module docstring, with the numbers that set them."""
        mats = {b.handle.material.name: b.handle.material for b in self.bodies}
        if self.max_speed is not None:
            v_max = float(self.max_speed)
        else:
            v0 = max((float(np.linalg.norm(b.velocity, axis=1).max()) for b in self.bodies), default=0.0)
            v0 = max([v0] + [e.speed + (self.tools[e.tool].max_speed if e.tool is not None else 0.0)
                             for e in self.emitters])
            height = float(self.upper[2] - self.lower[2])
            v_tools = max((t.max_speed for t in self.tools), default=0.0)
            v_max = max(v0, v_tools) + math.sqrt(2.0 * float(np.linalg.norm(self.gravity)) * height)
        waves = mats
        if self.pressure == "projection":
            # the projection holds the liquid incompressible and a rigid body carries no stress: neither's sound
            # speed limits the substep, the flow's CFL does (a liquid's shear viscosity still does, below)
            waves = {k: m for k, m in mats.items() if not (m.is_liquid or m.is_rigid)}
        stiffest = max(waves.values(), key=lambda m: m.wave_speed(), default=None)
        c = stiffest.wave_speed() if stiffest else 0.0
        limits = {"dx": self.dx, "v_max": v_max, "wave_speed": c,
                  "stiffest": stiffest.name if stiffest else None,
                  "cfl_dt": CFL_NUMBER * self.dx / (c + v_max) if c + v_max > 0 else math.inf,
                  "viscous_dt": math.inf, "viscous_material": None}
        for m in mats.values():
            eta_total = m.viscosity + m.bulk_viscosity  # shear and bulk: both diffuse momentum explicitly
            if self.pressure == "projection" and m.is_liquid:
                eta_total = m.viscosity  # the projection replaces the isotropic part of the stress
            if eta_total > 0:
                dt_v = m.density * self.dx ** 2 / (6.0 * eta_total)
                if dt_v < limits["viscous_dt"]:
                    limits["viscous_dt"], limits["viscous_material"] = dt_v, m.name
        limits["max_dt"] = min(limits["cfl_dt"], limits["viscous_dt"])
        return limits

    def stable_substeps(self) -> int:
        """The fewest substeps per step of dt that pass the stability check for what the scene holds now."""
        return max(1, math.ceil(self.dt / self.stability_limits()["max_dt"] - 1e-9))

    def check(self):
        """Refuse scenes the solver cannot run: unstable substep, walls too thin to hold liquid, nothing in it."""
        if self.gas is not None:
            lim = self.gas_limits()
            if lim["cfl"] > self.gas.max_cfl:
                need = math.ceil(self.dt * lim["speed"] / (self.gas.max_cfl * lim["dx"]))
                raise UnstableTimeStepError(
                    f"gas: the fastest expected flow ({lim['speed']:.3g} m/s from the sources, inflow walls and tools) "
                    f"crosses {lim['cfl']:.2f} cells per gas substep of {lim['substep']:.3g} s (Δx {lim['dx']:.3g} m), "
                    f"above max_cfl {self.gas.max_cfl:g}; use add_gas(substeps >= {need}) or a smaller dt")
            if lim["viscous"] > 1.0 / 6.0:
                need = math.ceil(self.dt * self.gas.viscosity * 6.0 / lim["dx"] ** 2)
                raise UnstableTimeStepError(
                    f"gas: the explicit viscosity needs ν Δt/Δx² ≤ 1/6, got {lim['viscous']:.3g} (ν "
                    f"{self.gas.viscosity:.3g} m²/s, gas substep {lim['substep']:.3g} s, Δx {lim['dx']:.3g} m); use "
                    f"add_gas(substeps >= {need})")
            if not self.bodies:
                return
        if not self.bodies:
            raise ValueError("the scene has no particles: add_particles() at least once (or add_gas() for a gas "
                             "scene)")
        lim = self.stability_limits()
        sub = self.substep_dt
        if sub > lim["max_dt"]:
            need = math.ceil(self.dt / lim["max_dt"])
            if lim["cfl_dt"] <= lim["viscous_dt"]:
                why = (f"CFL limit {CFL_NUMBER}·Δx/(c + v_max) = {lim['cfl_dt']:.3g} s with Δx = {self.dx:.4g} m, "
                       f"wave speed c = {lim['wave_speed']:.3g} m/s of material {lim['stiffest']!r} and expected "
                       f"max speed v_max = {lim['v_max']:.3g} m/s")
            else:
                why = (f"viscous limit ρΔx²/(6(η + ζ)) = {lim['viscous_dt']:.3g} s of material "
                       f"{lim['viscous_material']!r} with Δx = {self.dx:.4g} m")
            raise UnstableTimeStepError(
                f"unstable time step: substep dt/substeps = {self.dt:.3g}/{self.substeps} = {sub:.3g} s exceeds the "
                f"{why}. Use substeps >= {need} for dt = {self.dt:.3g} s (or a smaller dt, or a coarser grid).")
        min_wall = MIN_WALL_CELLS * self.dx
        for st in self.statics:
            if isinstance(st.shape, S.CONTAINERS) and st.shape.thinnest_wall() < min_wall - 1e-12:
                raise ValueError(
                    f"static {st.name!r}: wall thickness {st.shape.thinnest_wall():.4g} m is under 2 grid cells "
                    f"(2·Δx = {min_wall:.4g} m): liquid would leak through it. Make the wall at least "
                    f"{min_wall:.4g} m thick or the grid finer.")

    # --- build ------------------------------------------------------------------------------------------
    def build(self, requires_grad: bool = False, grad_memory: float = 512e6, grad_max_steps: int = 200):
        """Allocate the Taichi fields and compile the solver; returns a `Simulator`.

        requires_grad: also allocate the differentiable solver, for `Simulator.rollout(..., grad=True)`. Its
        buffer holds the per-substep state of one checkpoint segment: as many steps as fit in `grad_memory`
        bytes, at most `grad_max_steps`. Rollouts longer than the buffer are split into equal segments as long
        as it allows (checkpoint.plan_segments): with 200 steps, a 10,000-step rollout keeps 50 segment starts
        and recomputes 98 % of its steps once."""
        self.check()
        from fluidlab_core import runtime

        if self.pressure == "projection":
            self.check_projection(requires_grad)
        if requires_grad and self.flip > 0:
            raise ValueError(f"flip={self.flip} (AFLIP) has a forward only: the differentiable solver transfers by "
                             "APIC; build with requires_grad=False, or make the Scene with flip=0 for gradients")
        if requires_grad and self.jbar:
            raise ValueError(f"jbar={self.jbar!r} (the liquids' J averaged through the grid) has a forward only; "
                             "build with requires_grad=False, or make the Scene with jbar=False for gradients")
        if self.gas is not None and not self.bodies:
            return self._build_gas(requires_grad)
        from fluidlab_core.engine.model import Model, ModelSpec
        from fluidlab_core.engine.solver import FastSolver
        from fluidlab_core.simulator import Simulator

        config = runtime.ensure_init()
        real = runtime.real_dtype()
        mats: list[M.Material] = []
        for b in self.bodies:
            if b.handle.material not in mats:
                mats.append(b.handle.material)
        handles = [b.handle for b in self.bodies]
        spec = ModelSpec(
            lower=self.lower, upper=self.upper, dx=self.dx, dt=self.substep_dt, substeps=self.substeps,
            gravity=self.gravity, wall_friction=self.wall_friction, contact_fill=self.contact_fill,
            flip=self.flip, jbar=self.jbar, pressure=self.pressure,
            x=np.concatenate([b.points for b in self.bodies]), v=np.concatenate([b.velocity for b in self.bodies]),
            material_index=np.concatenate([np.full(h.count, mats.index(h.material)) for h in handles]),
            body_index=np.concatenate([np.full(h.count, h.body) for h in handles]),
            rest_volume=np.concatenate([np.full(b.handle.count, b.rest_volume) for b in self.bodies]),
            materials=mats, statics=list(self.statics), tools=list(self.tools),
            body_shapes=[b.shape for b in self.bodies if b.handle.body >= 0],
            emitters=list(self.emitters),
            emitter_of=np.concatenate([np.full(h.count, h.emitter) for h in handles]),
            pool_index=np.concatenate([np.arange(h.count) if h.emitter >= 0 else np.zeros(h.count, dtype=int)
                                       for h in handles]))
        # every field is allocated before any data goes in: one SNode tree for all (engine/model.py)
        model = Model(spec, real)
        copies = runtime.scatter_copies()
        solver = FastSolver(model, scatter_copies=copies)
        state = model.state()
        diff = None
        if requires_grad:
            from fluidlab_core.engine.diff_solver import DiffSolver, buffer_steps

            steps = buffer_steps(model, grad_memory, grad_max_steps)
            diff = DiffSolver(model, steps * self.substeps + 1, scatter_copies=copies)
        model.upload()
        state.write(0, model.initial_state())
        sim = Simulator(self, model, solver, state, handles, config, diff=diff)
        if self.gas is not None:
            from fluidlab_core.engine.gas_coupling import GasParticleCoupling

            gas = self._gas_solver(requires_grad=requires_grad)
            names = self.gas.drag_bodies
            rows = None
            if self.gas.particle_drag > 0:
                chosen = [h for h in handles if names is None or h.name in names]
                rows = np.concatenate([np.arange(h.start, h.start + h.count) for h in chosen]) if chosen else None
            sim.attach_gas(gas, GasParticleCoupling(gas, model, rows, self.gas.particle_drag))
        return sim

    def check_projection(self, requires_grad: bool = False):
        """Refuse (ValueError) what pressure="projection" does not handle yet, naming it; the build calls it, and a
        caller may before building (the benchmark refuses such a task before its sweep runs)."""
        why = []
        if requires_grad:
            why.append("gradients (it has a forward solver only; build with requires_grad=False)")
        if self.jbar:
            why.append("jbar (the projection holds the liquid's volume itself)")
        from fluidlab_core.engine import constitutive

        def liquid(m):  # a liquid by its material and by its constitutive model (the solver's test)
            return m.is_liquid and constitutive.get(m.model).fluid

        liquids = {b.handle.material.density for b in self.bodies if liquid(b.handle.material)}
        others = sorted({b.handle.material.name for b in self.bodies
                         if not liquid(b.handle.material) and not b.handle.material.is_rigid})
        rigid = [b.handle.name for b in self.bodies if b.handle.material.is_rigid]
        if others and rigid:
            why.append(f"deformable solids ({', '.join(others)}) beside a rigid body")
        if len(rigid) > 1:
            why.append(f"{len(rigid)} rigid bodies ({', '.join(rigid)}); it couples one")
        if not liquids:
            why.append("a scene without liquid")
        if why:
            raise ValueError("pressure='projection' (engine/projection.py) does not handle yet: " + "; ".join(why)
                             + ". Use pressure='state' for this scene.")

    def _build_gas(self, requires_grad: bool):
        """A GasSimulator for a scene with gas and no particles."""
        from fluidlab_core import runtime
        from fluidlab_core.gas_simulator import GasSimulator

        config = runtime.ensure_init()
        return GasSimulator(self, self.gas, self._gas_solver(requires_grad), config)

    def _gas_solver(self, requires_grad: bool):
        """The gas's solver, with the statics rasterised on the host."""
        from fluidlab_core import runtime
        from fluidlab_core.engine.gas import GasSolver

        real = runtime.real_dtype()
        g = self.gas
        static = np.zeros(g.shape, dtype=np.int8)
        static_phi = None
        if g.statics_block and self.statics:
            def phi(shape, offset):
                """The statics' signed distance (m, their union's: the minimum) at the points lower + Δx (index +
                offset) of a grid of `shape` points."""
                idx = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1).reshape(-1, 3)
                points = g.lower + g.dx * (idx + np.asarray(offset, dtype=np.float64))
                return np.min([np.asarray(st.shape.sdf(points), dtype=np.float64) for st in self.statics],
                              axis=0).reshape(shape)

            static = (phi(g.shape, (0.5, 0.5, 0.5)) < 0.0).astype(np.int8)
            if g.static_faces == "fractions":  # at the faces' corners (the grid's vertices) and centres
                n = np.asarray(g.shape)
                faces = [phi(tuple(n + np.eye(3, dtype=int)[d]), [0.0 if a == d else 0.5 for a in range(3)])
                         for d in range(3)]
                static_phi = (phi(tuple(n + 1), (0.0, 0.0, 0.0)), faces)
        if not np.any(static == 0):
            raise ValueError("the statics fill the whole gas box: no cell holds gas")
        return GasSolver(g, real, tool_specs=self.tools, static_solid=static, needs_grad=requires_grad,
                         static_phi=static_phi)
