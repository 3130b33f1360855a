"""Geometric shapes in the world frame (metres, z up): particle bodies and static colliders.

Every shape knows its axis-aligned bounds and its signed distance (negative inside) as a vectorised numpy
function; `sample()` fills it with a regular lattice of particles. The Taichi side of statics
(`fluidlab_core.engine.statics`) evaluates the same distances inside kernels.

Containers (`Cup`, `Tank`) are open at the top and are meant for `Scene.add_static`; `interior()` gives
the shape of the liquid that fills them to a height.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def _vec3(name: str, value) -> tuple[float, float, float]:
    arr = np.asarray(value, dtype=float)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be 3 finite numbers (metres), got {value!r}")
    return tuple(float(v) for v in arr)


def _positive(name: str, value) -> float:
    v = float(value)
    if not np.isfinite(v) or v <= 0:
        raise ValueError(f"{name} must be a positive number (metres), got {value!r}")
    return v


class Shape:
    """Base class: `bounds()` and `sdf(points)`."""

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def sdf(self, points: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def volume(self) -> float:
        raise NotImplementedError

    def sample(self, spacing: float, rng: np.random.Generator | None = None, jitter: float = 0.0) -> np.ndarray:
        """Cell centres of a lattice of about `spacing` (m) that lie inside; each particle stands for
        `cell_volume(spacing)` m³. `jitter` moves each point by up to ±jitter·spacing per axis, drawn from `rng`."""
        lo, hi = self.bounds()
        steps = self._lattice_steps(spacing)
        counts = np.maximum(np.floor((hi - lo) / steps + 1e-9).astype(int), 1)
        # centre the lattice in the bounds so that symmetric shapes are sampled symmetrically
        start = lo + 0.5 * ((hi - lo) - (counts - 1) * steps)
        axes = [start[d] + steps[d] * np.arange(counts[d]) for d in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        points = grid[self.sdf(grid) < 0.0]
        if jitter > 0.0:
            rng = rng if rng is not None else np.random.default_rng(0)
            points = points + rng.uniform(-jitter * steps, jitter * steps, size=points.shape)
        return points

    def _lattice_steps(self, spacing: float) -> np.ndarray:
        return np.full(3, float(spacing))

    def cell_volume(self, spacing: float) -> float:
        """The rest volume each sampled particle stands for (m³)."""
        return float(np.prod(self._lattice_steps(spacing)))


@dataclass(frozen=True)
class Box(Shape):
    lower: tuple[float, float, float]
    upper: tuple[float, float, float]

    def __post_init__(self):
        lo, hi = _vec3("Box.lower", self.lower), _vec3("Box.upper", self.upper)
        if not all(a < b for a, b in zip(lo, hi)):
            raise ValueError(f"Box needs lower < upper on every axis, got lower={lo}, upper={hi}")
        object.__setattr__(self, "lower", lo)
        object.__setattr__(self, "upper", hi)

    def bounds(self):
        return np.array(self.lower), np.array(self.upper)

    def sdf(self, points):
        lo, hi = self.bounds()
        c, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
        q = np.abs(np.asarray(points) - c) - h
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
        inside = np.minimum(q.max(axis=-1), 0.0)
        return outside + inside

    def volume(self):
        lo, hi = self.bounds()
        return float(np.prod(hi - lo))

    def _lattice_steps(self, spacing):
        # a whole number of cells per side, so that the particles fill the box exactly
        extent = np.array(self.upper) - np.array(self.lower)
        return extent / np.maximum(np.round(extent / spacing), 1)


@dataclass(frozen=True)
class Sphere(Shape):
    center: tuple[float, float, float]
    radius: float

    def __post_init__(self):
        object.__setattr__(self, "center", _vec3("Sphere.center", self.center))
        object.__setattr__(self, "radius", _positive("Sphere.radius", self.radius))

    def bounds(self):
        c = np.array(self.center)
        return c - self.radius, c + self.radius

    def sdf(self, points):
        return np.linalg.norm(np.asarray(points) - np.array(self.center), axis=-1) - self.radius

    def volume(self):
        return 4.0 / 3.0 * np.pi * self.radius ** 3


@dataclass(frozen=True)
class Cylinder(Shape):
    """Solid cylinder with a vertical (z) axis; `center` is its geometric centre."""

    center: tuple[float, float, float]
    radius: float
    height: float

    def __post_init__(self):
        object.__setattr__(self, "center", _vec3("Cylinder.center", self.center))
        object.__setattr__(self, "radius", _positive("Cylinder.radius", self.radius))
        object.__setattr__(self, "height", _positive("Cylinder.height", self.height))

    def bounds(self):
        c = np.array(self.center)
        e = np.array([self.radius, self.radius, 0.5 * self.height])
        return c - e, c + e

    def sdf(self, points):
        d = np.asarray(points) - np.array(self.center)
        q = np.stack([np.hypot(d[..., 0], d[..., 1]) - self.radius, np.abs(d[..., 2]) - 0.5 * self.height], -1)
        return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)

    def volume(self):
        return np.pi * self.radius ** 2 * self.height


@dataclass(frozen=True)
class Cup(Shape):
    """Open-top cylindrical container standing on `base_center` (the centre of its outer bottom face).

    outer_radius, height: outer dimensions; wall_thickness: side wall; base_thickness: bottom (defaults to
    the wall thickness). The inside is a cylinder of radius outer_radius - wall_thickness."""

    base_center: tuple[float, float, float]
    outer_radius: float
    height: float
    wall_thickness: float
    base_thickness: float | None = None

    def __post_init__(self):
        object.__setattr__(self, "base_center", _vec3("Cup.base_center", self.base_center))
        for name in ("outer_radius", "height", "wall_thickness"):
            object.__setattr__(self, name, _positive(f"Cup.{name}", getattr(self, name)))
        base = self.wall_thickness if self.base_thickness is None else _positive("Cup.base_thickness",
                                                                                  self.base_thickness)
        object.__setattr__(self, "base_thickness", base)
        if self.wall_thickness >= self.outer_radius or self.base_thickness >= self.height:
            raise ValueError(f"Cup walls are thicker than the cup: wall {self.wall_thickness} m vs radius "
                             f"{self.outer_radius} m, base {self.base_thickness} m vs height {self.height} m")

    @property
    def inner_radius(self) -> float:
        return self.outer_radius - self.wall_thickness

    def thinnest_wall(self) -> float:
        return min(self.wall_thickness, self.base_thickness)

    def _outer(self):
        x, y, z = self.base_center
        return Cylinder((x, y, z + 0.5 * self.height), self.outer_radius, self.height)

    def _hollow(self):
        # the cavity, extended above the rim so that the top is open
        x, y, z = self.base_center
        z0, z1 = z + self.base_thickness, z + 2.0 * self.height
        return Cylinder((x, y, 0.5 * (z0 + z1)), self.inner_radius, z1 - z0)

    def bounds(self):
        return self._outer().bounds()

    def sdf(self, points):
        return np.maximum(self._outer().sdf(points), -self._hollow().sdf(points))

    def volume(self):
        return self._outer().volume() - np.pi * self.inner_radius ** 2 * (self.height - self.base_thickness)

    def interior(self, fill_height: float, clearance: float = 0.0) -> Cylinder:
        """The liquid that fills the cup to `fill_height` above its inner bottom, `clearance` off the walls."""
        _positive("fill_height", fill_height)
        x, y, z = self.base_center
        z0 = z + self.base_thickness + clearance
        return Cylinder((x, y, z0 + 0.5 * fill_height), self.inner_radius - clearance, fill_height)


@dataclass(frozen=True)
class Tank(Shape):
    """Open-top box container: outer bounds `lower`..`upper`, walls and floor `wall_thickness` thick."""

    lower: tuple[float, float, float]
    upper: tuple[float, float, float]
    wall_thickness: float

    def __post_init__(self):
        outer = Box(self.lower, self.upper)
        object.__setattr__(self, "lower", outer.lower)
        object.__setattr__(self, "upper", outer.upper)
        w = _positive("Tank.wall_thickness", self.wall_thickness)
        object.__setattr__(self, "wall_thickness", w)
        ext = np.array(outer.upper) - np.array(outer.lower)
        if 2 * w >= ext[0] or 2 * w >= ext[1] or w >= ext[2]:
            raise ValueError(f"Tank walls ({w} m) leave no inside in a tank of size {tuple(ext)} m")

    def thinnest_wall(self) -> float:
        return self.wall_thickness

    def _hollow(self):
        lo, hi, w = np.array(self.lower), np.array(self.upper), self.wall_thickness
        return Box(lo + [w, w, w], hi + [-w, -w, hi[2] - lo[2]])

    def bounds(self):
        return np.array(self.lower), np.array(self.upper)

    def sdf(self, points):
        return np.maximum(Box(self.lower, self.upper).sdf(points), -self._hollow().sdf(points))

    def volume(self):
        lo, hi, w = np.array(self.lower), np.array(self.upper), self.wall_thickness
        inner = (hi - lo) - [2 * w, 2 * w, w]
        return float(np.prod(hi - lo) - np.prod(inner))

    def interior(self, fill_height: float, clearance: float = 0.0) -> Box:
        _positive("fill_height", fill_height)
        lo, hi, w = np.array(self.lower), np.array(self.upper), self.wall_thickness + clearance
        return Box(lo + [w, w, w], [hi[0] - w, hi[1] - w, lo[2] + w + fill_height])


@dataclass(frozen=True)
class Mesh(Shape):
    """A closed triangle mesh from a file (any format trimesh reads), scaled then placed at `pose`:
    (x, y, z, qx, qy, qz, qw) in metres with a unit quaternion, or a 4×4 matrix."""

    path: str
    pose: tuple | None = None
    scale: float | tuple[float, float, float] = 1.0
    _mesh: object = field(default=None, init=False, repr=False, compare=False)

    def mesh(self):
        if self._mesh is None:
            from fluidlab_core.shapes.mesh_sdf import load_mesh

            object.__setattr__(self, "_mesh", load_mesh(self.path, pose=self.pose, scale=self.scale))
        return self._mesh

    def bounds(self):
        b = self.mesh().bounds
        return np.array(b[0]), np.array(b[1])

    def sdf(self, points):
        import trimesh

        return -trimesh.proximity.signed_distance(self.mesh(), np.asarray(points, dtype=float))

    def volume(self):
        return float(self.mesh().volume)

    def sample(self, spacing, rng=None, jitter=0.0):
        from fluidlab_core.shapes.mesh_sdf import sample_mesh_volume

        return sample_mesh_volume(self.mesh(), spacing, rng=rng, jitter=jitter)
