"""Gas (air and smoke) as the scene describes it: the options of `Scene.add_gas`, sources and sinks, the gas state
on the host, and what a loss sees of it. No Taichi here; the solver is fluidlab_core/engine/gas.py, which has the
equations.

Units (SI, world frame): velocity m/s on the faces of a staggered grid, temperature K, smoke density kg/m³ (a
mass concentration: real smoke is 1e-4 to 1e-2 kg/m³), named scalars in the user's units, pressure Pa.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

TEMPERATURE, SMOKE = 0, 1
WALLS = ("x-", "x+", "y-", "y+", "z-", "z+")
ADVECTIONS = ("maccormack", "semi-lagrangian")
LIMITERS = ("cell", "continuous")  # MacCormack's clamp range (engine/gas.py)
TOOL_FACES = ("cells", "fractions")  # how a tool or a static blocks the pressure projection (engine/gas.py)


class GasSolverError(RuntimeError):
    """The pressure solve did not reach its tolerance within its iteration cap."""


class NonFiniteGasError(FloatingPointError):
    """A gas field became NaN or infinite."""


class GasCFLError(ValueError):
    """The flow moved more than the advection scheme takes in one step."""


@dataclass
class GasSourceSpec:
    """An inflow (a vent, a fan, a heater) or a sink: a region in its own frame that sets the velocity and
    scalars inside it (see the module docstring). Frame: `position`, `quaternion` (x, y, z, w) in the world or,
    with `tool`, in that tool's frame; the flow leaves along the frame's +z axis."""

    name: str
    shape: str  # "box" (size: half extents (3,), m) or "disc" (size: (radius, half thickness), m)
    size: tuple
    position: np.ndarray
    quaternion: np.ndarray
    tool: int | None
    speed: float | None  # m/s along +z (None: the velocity is left alone)
    temperature: float | None  # K
    smoke: float | None  # kg/m³
    scalars: dict = field(default_factory=dict)  # name -> value
    relaxation_time: float = 0.0  # s (0: the values are set each step)

    def rotation(self) -> np.ndarray:
        from scipy.spatial.transform import Rotation

        return Rotation.from_quat(self.quaternion).as_matrix()


@dataclass
class GasSpec:
    """The gas as the scene describes it (Scene.add_gas checks and documents every option)."""

    lower: np.ndarray
    shape: tuple[int, int, int]
    dx: float
    walls: tuple  # per WALLS entry: "closed", "open" or an inflow velocity (3,) m/s
    gravity: np.ndarray
    ambient_temperature: float = 293.15
    initial_temperature: float | None = None
    air_density: float = 1.2
    buoyancy_temperature: float | None = None  # β, 1/K (None: 1/T_amb, an ideal gas)
    buoyancy_smoke: float | None = None  # κ, m³/kg (None: 1/ρ_air)
    vorticity: float = 0.0  # ε
    viscosity: float = 0.0  # ν, m²/s
    advection: str = "maccormack"
    limiter: str = "cell"
    tolerance: float = 1e-6
    max_iterations: int = 200
    on_fail: str = "raise"
    max_cfl: float = 2.0
    scalars: tuple = ()
    substeps: int = 1
    statics_block: bool = True
    tools_block: bool = True
    tool_faces: str = "cells"
    static_faces: str = "cells"
    particle_faces: str = "cells"
    particles_block: bool = False
    particle_drag: float = 0.0  # 1/s
    drag_bodies: tuple | None = None  # names of the particle bodies the gas drags (None: all)
    check_every: int = 1
    sources: list = field(default_factory=list)

    @property
    def scalar_names(self) -> tuple:
        return ("temperature", "smoke", *self.scalars)

    @property
    def upper(self) -> np.ndarray:
        return self.lower + self.dx * np.asarray(self.shape, dtype=np.float64)

    def beta(self) -> float:
        return 1.0 / self.ambient_temperature if self.buoyancy_temperature is None else self.buoyancy_temperature

    def kappa(self) -> float:
        return 1.0 / self.air_density if self.buoyancy_smoke is None else self.buoyancy_smoke

    def temperature_range(self) -> tuple[float, float]:
        """(low, high) K of the temperatures the gas can hold: the initial and ambient ones and the sources' (a
        picture's fixed colour scale)."""
        values = [self.ambient_temperature, self.initial_temperature or self.ambient_temperature]
        values += [s.temperature for s in self.sources if s.temperature is not None]
        lo, hi = min(values), max(values)
        return (lo, hi) if hi > lo else (lo - 1.0, hi + 1.0)


@dataclass
class GasState:
    """A snapshot of the gas: face velocities (u_x (nx+1, ny, nz), u_y (nx, ny+1, nz), u_z (nx, ny, nz+1)) in m/s
    and the scalars (n_q, nx, ny, nz): temperature (K), smoke (kg/m³), then the named scalars."""

    velocity: tuple
    scalars: np.ndarray

    def copy(self) -> "GasState":
        return GasState(tuple(np.array(v, copy=True) for v in self.velocity), np.array(self.scalars, copy=True))

    def arrays(self) -> dict:
        return {"u_x": self.velocity[0], "u_y": self.velocity[1], "u_z": self.velocity[2], "q": self.scalars}

    def cell_velocity(self) -> np.ndarray:
        """(nx, ny, nz, 3) velocity at the cell centres (the mean of the two faces on each axis)."""
        ux, uy, uz = self.velocity
        return np.stack([0.5 * (ux[1:] + ux[:-1]), 0.5 * (uy[:, 1:] + uy[:, :-1]), 0.5 * (uz[:, :, 1:] + uz[:, :, :-1])],
                        axis=-1)


def face_grad_from_cells(g: np.ndarray) -> tuple:
    """The adjoint of GasState.cell_velocity: face gradients from an (nx, ny, nz, 3) gradient at the centres."""
    nx, ny, nz, _ = g.shape
    out = []
    for d, n in enumerate((nx, ny, nz)):
        shape = [nx, ny, nz]
        shape[d] += 1
        f = np.zeros(shape)
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[d], hi[d] = slice(0, n), slice(1, n + 1)
        f[tuple(lo)] += 0.5 * g[..., d]
        f[tuple(hi)] += 0.5 * g[..., d]
        out.append(f)
    return tuple(out)




@dataclass
class GasView:
    """What a loss sees of the gas after a step: cell-centred fields in float64, and the grid to sample them.
    temperature (nx, ny, nz) K, smoke (nx, ny, nz) kg/m³, velocity (nx, ny, nz, 3) m/s (the mean of each cell's
    two faces per axis), scalars {name: (nx, ny, nz)}, solid (nx, ny, nz) bools; lower (3,) m and dx m: cell
    (i, j, k) is centred at lower + dx (i + ½, j + ½, k + ½).

    A loss returns gradients with respect to these under the keys "gas_temperature", "gas_smoke",
    "gas_velocity" and "gas_<scalar name>"."""

    temperature: np.ndarray
    smoke: np.ndarray
    velocity: np.ndarray
    scalars: dict
    solid: np.ndarray
    lower: np.ndarray
    dx: float

    @classmethod
    def of(cls, state: GasState, spec: GasSpec, solid: np.ndarray) -> "GasView":
        q = np.asarray(state.scalars, dtype=np.float64)
        return cls(q[TEMPERATURE], q[SMOKE], state.cell_velocity().astype(np.float64),
                   {n: q[2 + i] for i, n in enumerate(spec.scalars)}, np.asarray(solid, dtype=bool),
                   np.asarray(spec.lower, dtype=np.float64), float(spec.dx))

    def field(self, name: str) -> np.ndarray:
        if name == "temperature":
            return self.temperature
        if name == "smoke":
            return self.smoke
        if name == "velocity":
            return self.velocity
        if name in self.scalars:
            return self.scalars[name]
        raise KeyError(f"no gas field {name!r}; fields: temperature, smoke, velocity"
                       + "".join(f", {n}" for n in self.scalars))

    def weights(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Trilinear interpolation of cell-centred fields at `points` (P, 3): (flat cell indices (P, 8), weights
        (P, 8)). Points outside the gas grid take the nearest cells' values."""
        return trilinear_weights(np.asarray(points, dtype=np.float64), self.lower, self.dx, self.temperature.shape)

    def sample(self, name: str, points) -> np.ndarray:
        """Values of a cell-centred field at world points (P, 3) (P,) or (P, 3) for the velocity."""
        idx, w = self.weights(points)
        f = self.field(name)
        flat = f.reshape(-1, *f.shape[3:])
        return np.einsum("pk,pk...->p...", w, flat[idx])


def trilinear_weights(points: np.ndarray, lower, dx: float, shape) -> tuple[np.ndarray, np.ndarray]:
    """(flat indices (P, 8), weights (P, 8)) of the trilinear interpolation of a cell-centred field."""
    shape = np.asarray(shape)
    g = (points - np.asarray(lower)) / dx - 0.5
    g = np.clip(g, 0.0, shape - 1.0)
    base = np.minimum(np.floor(g).astype(np.int64), np.maximum(shape - 2, 0))
    frac = g - base
    idx = np.zeros((len(points), 8), dtype=np.int64)
    w = np.zeros((len(points), 8))
    n = 0
    for a in (0, 1):
        for b in (0, 1):
            for c in (0, 1):
                i = np.minimum(base + np.array([a, b, c]), shape - 1)
                idx[:, n] = np.ravel_multi_index(i.T, tuple(shape))
                w[:, n] = (np.where(a, frac[:, 0], 1 - frac[:, 0]) * np.where(b, frac[:, 1], 1 - frac[:, 1])
                           * np.where(c, frac[:, 2], 1 - frac[:, 2]))
                n += 1
    return idx, w


def _number(name: str, value, low=None, strict: bool = False, allow_none: bool = False) -> float | None:
    if value is None and allow_none:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {value!r}")
    if low is not None and (v <= low if strict else v < low):
        raise ValueError(f"{name} must be {'>' if strict else '>='} {low}, got {value!r}")
    return v


def parse_walls(walls) -> tuple:
    """Per WALLS face: "closed", "open" or an inflow velocity (3,) m/s, from one string for all, or a dict
    {face: kind} over the default "closed"."""
    if isinstance(walls, str):
        walls = {f: walls for f in WALLS}
    if not isinstance(walls, dict):
        raise ValueError(f"walls must be 'closed', 'open' or a dict {{face: kind}} over faces {WALLS}, got {walls!r}")
    out = []
    for f in WALLS:
        w = walls.get(f, "closed")
        if isinstance(w, str):
            if w not in ("closed", "open"):
                raise ValueError(f"wall {f}: kind must be 'closed', 'open' or an inflow velocity (vx, vy, vz) in "
                                 f"m/s, got {w!r}")
            out.append(w)
        else:
            v = np.asarray(w, dtype=np.float64)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise ValueError(f"wall {f}: an inflow velocity must be 3 finite numbers (m/s), got {w!r}")
            out.append(tuple(float(c) for c in v))
    unknown = set(walls) - set(WALLS)
    if unknown:
        raise ValueError(f"walls: unknown face(s) {sorted(unknown)}; faces are {WALLS}")
    return tuple(out)
