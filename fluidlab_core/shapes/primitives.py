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


def frustum_sdf(q_r, q_z, r1: float, r2: float, half: float):
    """Signed distance to a solid frustum (a capped cone) in its axial coordinates: q_r the distance from the
    axis, q_z the height above its mid-plane, radius r1 at q_z = −half and r2 at q_z = +half (exact; after
    Quilez, "distance functions", capped cone). Works on numpy arrays."""
    k2r, k2z = r2 - r1, 2.0 * half
    ca_r = q_r - np.minimum(q_r, np.where(q_z < 0.0, r1, r2))
    ca_z = np.abs(q_z) - half
    t = np.clip(((r2 - q_r) * k2r + (half - q_z) * k2z) / (k2r * k2r + k2z * k2z), 0.0, 1.0)
    cb_r, cb_z = q_r - r2 + k2r * t, q_z - half + k2z * t
    sign = np.where((cb_r < 0.0) & (ca_z < 0.0), -1.0, 1.0)
    return sign * np.sqrt(np.minimum(ca_r ** 2 + ca_z ** 2, cb_r ** 2 + cb_z ** 2))


@dataclass(frozen=True)
class Frustum(Shape):
    """Solid frustum (capped cone) with a vertical (z) axis: radius `bottom_radius` at its bottom face, centred
    at `base_center`, and `top_radius` at `height` above it (either radius may be the smaller)."""

    base_center: tuple[float, float, float]
    bottom_radius: float
    top_radius: float
    height: float

    def __post_init__(self):
        object.__setattr__(self, "base_center", _vec3("Frustum.base_center", self.base_center))
        for name in ("bottom_radius", "top_radius", "height"):
            object.__setattr__(self, name, _positive(f"Frustum.{name}", getattr(self, name)))

    def bounds(self):
        c = np.array(self.base_center)
        r = max(self.bottom_radius, self.top_radius)
        return c - [r, r, 0.0], c + [r, r, self.height]

    def sdf(self, points):
        d = np.asarray(points) - np.array(self.base_center)
        return frustum_sdf(np.hypot(d[..., 0], d[..., 1]), d[..., 2] - 0.5 * self.height, self.bottom_radius,
                           self.top_radius, 0.5 * self.height)

    def volume(self):
        r1, r2 = self.bottom_radius, self.top_radius
        return np.pi * self.height * (r1 * r1 + r1 * r2 + r2 * r2) / 3.0


@dataclass(frozen=True)
class Cone(Shape):
    """Open-top conical container standing on its tip (an ice-cream cone): the outer surface narrows from
    `top_radius` at the rim, `height` above `tip_center`, to `tip_radius` at the tip; the wall is
    `wall_thickness` thick measured normal to it. The cavity's bottom is `base_thickness` above the tip (default:
    at least the wall, and where the cavity is half a wall wide, so that the pointed end is solid)."""

    tip_center: tuple[float, float, float]
    top_radius: float
    height: float
    wall_thickness: float
    tip_radius: float = 0.004
    base_thickness: float | None = None

    def __post_init__(self):
        object.__setattr__(self, "tip_center", _vec3("Cone.tip_center", self.tip_center))
        for name in ("top_radius", "height", "wall_thickness", "tip_radius"):
            object.__setattr__(self, name, _positive(f"Cone.{name}", getattr(self, name)))
        if self.top_radius <= self.tip_radius:
            raise ValueError(f"a Cone widens upwards: top radius {self.top_radius} m <= tip radius "
                             f"{self.tip_radius} m")
        w, s = self.wall_thickness, self.slope
        base = max(w, (0.5 * w + w * np.sqrt(1.0 + s * s) - self.tip_radius) / s) if self.base_thickness is None \
            else _positive("Cone.base_thickness", self.base_thickness)
        object.__setattr__(self, "base_thickness", float(base))
        if self._hollow_radius(self.base_thickness) <= 0.0 or self.base_thickness >= self.height:
            raise ValueError(f"Cone walls ({self.wall_thickness} m, bottom {self.base_thickness} m) leave no inside "
                             f"in a cone of top radius {self.top_radius} m and height {self.height} m")

    @property
    def slope(self) -> float:
        """Radius gained per metre of height."""
        return (self.top_radius - self.tip_radius) / self.height

    def _hollow_radius(self, z: float) -> float:
        """Radius of the cavity at height z above the tip (the outer radius less the wall, horizontally)."""
        return self.tip_radius + self.slope * z - self.wall_thickness * np.sqrt(1.0 + self.slope ** 2)

    def thinnest_wall(self) -> float:
        return min(self.wall_thickness, self.base_thickness)

    def _outer(self):
        return Frustum(self.tip_center, self.tip_radius, self.top_radius, self.height)

    def _hollow(self):
        # the cavity, extended above the rim so that the top is open
        x, y, z = self.tip_center
        z0, z1 = self.base_thickness, 2.0 * self.height
        return Frustum((x, y, z + z0), self._hollow_radius(z0), self._hollow_radius(z1), z1 - z0)

    def bounds(self):
        return self._outer().bounds()

    def sdf(self, points):
        return np.maximum(self._outer().sdf(points), -self._hollow().sdf(points))

    def volume(self):
        inner = Frustum(self._hollow().base_center, self._hollow_radius(self.base_thickness),
                        self._hollow_radius(self.height), self.height - self.base_thickness)
        return self._outer().volume() - inner.volume()

    def capacity(self) -> float:
        """Volume the cone holds up to its rim (m³)."""
        return self._outer().volume() - self.volume()


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
