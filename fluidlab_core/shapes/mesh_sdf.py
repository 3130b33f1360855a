"""Meshes for tools and bodies: loading, signed distance grids and volume sampling.

Pure numpy/trimesh (no Taichi): the solver uploads the arrays built here.

* ``load_mesh`` reads a mesh file and places it in the world: scale first, then a rigid pose.
* ``mesh_sdf_grid`` tabulates the signed distance of a closed mesh on a regular grid
  (``SDFGrid``); colliders sample it with ``SDFGrid.sample`` (trilinear).
* ``sample_mesh_volume`` fills a closed mesh with particles on a regular lattice.

Units and signs
---------------
Every length is in metres. Signed distance is NEGATIVE INSIDE the mesh and positive outside
(the usual SDF convention). trimesh's ``proximity.signed_distance`` uses the opposite sign
(positive inside); ``mesh_sdf_grid`` flips it.

Caching
-------
Signed distance queries are slow (closest-triangle search per node), so ``mesh_sdf_grid`` caches
its result as ``sdf_<sha256>.npz`` in ``cache_dir`` (default: ``$FLUIDLAB_CACHE_DIR``, else
``~/.cache/fluidlab/sdf``). The key hashes the mesh's vertex and face arrays, the spacing and
the padding, so any change to the mesh or the grid gives a new file. Files are written
atomically (temporary file in the same folder, then ``os.replace``); a file that cannot be read
or does not match its key is ignored, with a warning, and recomputed.
"""
from __future__ import annotations

import hashlib
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

MAX_GRID_NODES = 256**3  # largest SDF grid / sampling lattice, in nodes
QUERY_CHUNK = 32768  # points per trimesh proximity / containment query
CACHE_FORMAT = "fluidlab-sdf-v1"  # bump when the cached arrays change meaning
CACHE_ENV_VAR = "FLUIDLAB_CACHE_DIR"
_ROTATION_TOL = 1e-6  # tolerance on R^T R = I for a 4x4 pose


# --------------------------------------------------------------------------------------------
# loading


def load_mesh(path, pose=None, scale=1.0, require_watertight: bool = True) -> trimesh.Trimesh:
    """Load a mesh file (any format trimesh reads), scale it, then move it by ``pose``.

    Args:
        path: mesh file (.obj, .stl, .ply, ...). Multi-part files are merged into one mesh.
        pose: None (identity), a 7-sequence ``(x, y, z, qx, qy, qz, qw)`` with the position in
            metres and a quaternion in (x, y, z, w) order (normalised here), or a 4x4 rigid
            homogeneous matrix. Scaling belongs in ``scale``, not in the pose.
        scale: positive scalar or 3 per-axis factors, applied in the mesh's own frame before
            the pose (e.g. 0.001 for a CAD file in millimetres).
        require_watertight: raise if the mesh is not closed (signed distance and volume
            sampling need a closed mesh).

    Faces are oriented outwards (a mesh with negative volume is inverted).
    """
    path = Path(path).expanduser()
    if not path.exists():
        raise FileNotFoundError(f"mesh file not found: {path}")
    if not path.is_file():
        raise ValueError(f"mesh path is not a file: {path}")
    scale_matrix = _scale_matrix(scale)
    pose_matrix = pose_to_matrix(pose)
    try:
        mesh = trimesh.load(str(path), force="mesh")
    except Exception as exc:  # trimesh raises many types for bad files
        raise ValueError(f"could not read mesh file {path}: {type(exc).__name__}: {exc}") from exc
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValueError(f"mesh file {path} did not load as a triangle mesh (got {type(mesh).__name__})")
    if len(mesh.vertices) == 0 or len(mesh.faces) == 0:
        raise ValueError(f"mesh file {path} contains no triangles (empty, or not a valid {path.suffix} file)")
    mesh.apply_transform(pose_matrix @ scale_matrix)
    if require_watertight:
        _check_watertight(mesh, name=str(path))
        if mesh.volume < 0:
            mesh.invert()
    return mesh


def pose_to_matrix(pose) -> np.ndarray:
    """Return the 4x4 rigid transform for ``pose`` (None, 7-sequence xyz+xyzw quaternion, or 4x4)."""
    if pose is None:
        return np.eye(4)
    arr = np.asarray(pose, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"pose contains non-finite values: {pose!r}")
    if arr.shape == (7,):
        quat = arr[3:]
        norm = np.linalg.norm(quat)
        if norm < 1e-12:
            raise ValueError(
                f"pose quaternion (qx, qy, qz, qw) = {tuple(quat)} has zero norm; "
                "use (0, 0, 0, 1) for no rotation"
            )
        x, y, z, w = quat / norm
        matrix = np.eye(4)
        matrix[:3, :3] = [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
        matrix[:3, 3] = arr[:3]
        return matrix
    if arr.shape == (4, 4):
        if not np.allclose(arr[3], [0.0, 0.0, 0.0, 1.0]):
            raise ValueError(f"pose matrix must have last row (0, 0, 0, 1), got {arr[3].tolist()}")
        rot = arr[:3, :3]
        if not np.allclose(rot.T @ rot, np.eye(3), atol=_ROTATION_TOL) or np.linalg.det(rot) <= 0:
            raise ValueError(
                "pose matrix rotation block is not a proper rotation (orthonormal, det +1); "
                "pass scaling through `scale` instead"
            )
        return arr.copy()
    raise ValueError(
        f"pose must be None, 7 numbers (x, y, z, qx, qy, qz, qw) or a 4x4 matrix; got shape {arr.shape}"
    )


def _scale_matrix(scale) -> np.ndarray:
    """Return the 4x4 diagonal matrix for a scalar or per-axis ``scale``."""
    factors = np.asarray(scale, dtype=np.float64)
    if factors.shape == ():
        factors = np.full(3, float(factors))
    if factors.shape != (3,):
        raise ValueError(f"scale must be a number or 3 numbers, got shape {factors.shape}")
    if not np.all(np.isfinite(factors)) or np.any(factors <= 0):
        raise ValueError(f"scale factors must be positive and finite, got {factors.tolist()}")
    return np.diag([*factors, 1.0])


def _check_watertight(mesh: trimesh.Trimesh, name: str = "mesh") -> None:
    """Raise ValueError unless ``mesh`` is a closed triangle mesh."""
    if not isinstance(mesh, trimesh.Trimesh):
        raise TypeError(f"expected a trimesh.Trimesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0:
        raise ValueError(f"{name} contains no triangles")
    if not mesh.is_watertight:
        raise ValueError(
            f"{name} is not watertight: volume sampling and signed distance need a closed mesh. "
            "Close it first (e.g. trimesh.repair.fill_holes(mesh), or fix it in a mesh editor)."
        )


# --------------------------------------------------------------------------------------------
# signed distance grid


@dataclass(frozen=True, eq=False)
class SDFGrid:
    """Signed distance in metres at nodes ``origin + spacing * (i, j, k)``; negative inside.

    ``values`` has shape (nx, ny, nz), at least 2 nodes per axis, and is stored read-only.
    """

    origin: np.ndarray  # (3,) position of node (0, 0, 0) [m]
    spacing: float  # node spacing [m]
    values: np.ndarray  # (nx, ny, nz) signed distance [m], negative inside

    def __post_init__(self):
        origin = np.array(self.origin, dtype=np.float64)
        values = np.asarray(self.values, dtype=np.float64).view()
        spacing = float(self.spacing)
        if origin.shape != (3,) or not np.all(np.isfinite(origin)):
            raise ValueError(f"SDFGrid origin must be 3 finite numbers, got {self.origin!r}")
        if not (np.isfinite(spacing) and spacing > 0):
            raise ValueError(f"SDFGrid spacing must be positive, got {self.spacing!r}")
        if values.ndim != 3 or min(values.shape) < 2:
            raise ValueError(f"SDFGrid values must be 3-D with >= 2 nodes per axis, got {values.shape}")
        origin.flags.writeable = False
        values.flags.writeable = False
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "spacing", spacing)
        object.__setattr__(self, "values", values)

    @property
    def shape(self) -> tuple[int, int, int]:
        """Nodes per axis (nx, ny, nz)."""
        return self.values.shape

    @property
    def upper(self) -> np.ndarray:
        """Position of the last node (nx-1, ny-1, nz-1) [m]."""
        return self.origin + self.spacing * (np.array(self.shape) - 1)

    def sample(self, points) -> np.ndarray:
        """Signed distance [m] at ``points`` (N, 3) by trilinear interpolation; returns (N,).

        Outside the grid box the value is extrapolated as ``sdf(q) + |p - q|``, where ``q`` is
        ``p`` clamped onto the box: continuous across the box, and positive as long as the box
        boundary lies outside the mesh (``mesh_sdf_grid`` pads the box for this). It grows with
        the right slope but is only an upper bound on the true distance far from the box.
        """
        pts = np.asarray(points, dtype=np.float64)
        single = pts.ndim == 1
        pts = np.atleast_2d(pts)
        if pts.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {np.shape(points)}")
        clamped = np.clip(pts, self.origin, self.upper)
        outside = np.linalg.norm(pts - clamped, axis=1)
        u = (clamped - self.origin) / self.spacing  # continuous node index
        n = np.array(self.shape)
        i0 = np.clip(np.floor(u).astype(np.int64), 0, n - 2)
        t = np.clip(u - i0, 0.0, 1.0)
        v = self.values
        result = np.zeros(len(pts))
        for dx in (0, 1):
            wx = t[:, 0] if dx else 1.0 - t[:, 0]
            for dy in (0, 1):
                wy = t[:, 1] if dy else 1.0 - t[:, 1]
                for dz in (0, 1):
                    wz = t[:, 2] if dz else 1.0 - t[:, 2]
                    result += wx * wy * wz * v[i0[:, 0] + dx, i0[:, 1] + dy, i0[:, 2] + dz]
        result += outside
        return result[0] if single else result


def mesh_sdf_grid(mesh: trimesh.Trimesh, spacing: float, padding: int = 3, cache_dir=None) -> SDFGrid:
    """Tabulate the signed distance of a closed mesh on a grid (cached on disk).

    The grid covers ``mesh.bounds`` grown by ``padding * spacing`` on every side, with nodes
    ``spacing`` metres apart. Values are negative inside the mesh. See the module docstring for
    the cache (``cache_dir`` defaults to ``$FLUIDLAB_CACHE_DIR`` or ``~/.cache/fluidlab/sdf``).
    """
    spacing = _check_spacing(spacing)
    if int(padding) != padding or padding < 0:
        raise ValueError(f"padding must be a non-negative whole number of cells, got {padding!r}")
    padding = int(padding)
    mesh = _outward(mesh)

    origin = mesh.bounds[0] - padding * spacing
    extent = mesh.bounds[1] - mesh.bounds[0] + 2 * padding * spacing
    shape = tuple(int(n) for n in np.ceil(extent / spacing - 1e-9).astype(np.int64) + 1)
    shape = tuple(max(n, 2) for n in shape)
    _check_node_count(shape, spacing, "SDF grid")

    cache_path = _cache_dir(cache_dir) / f"sdf_{_cache_key(mesh, spacing, padding)}.npz"
    cached = _read_cache(cache_path, shape)
    if cached is not None:
        return SDFGrid(origin=origin, spacing=spacing, values=cached)

    axes = [origin[d] + spacing * np.arange(shape[d]) for d in range(3)]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    values = np.empty(len(nodes))
    for start in range(0, len(nodes), QUERY_CHUNK):
        chunk = nodes[start : start + QUERY_CHUNK]
        values[start : start + QUERY_CHUNK] = -trimesh.proximity.signed_distance(mesh, chunk)
    values = values.reshape(shape)
    _write_cache(cache_path, values)
    return SDFGrid(origin=origin, spacing=spacing, values=values)


def _outward(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Check ``mesh`` is closed and return it with outward faces (a copy if it was inverted)."""
    _check_watertight(mesh)
    if mesh.volume < 0:
        mesh = mesh.copy()
        mesh.invert()
    return mesh


def _check_spacing(spacing) -> float:
    """Return ``spacing`` as a float, or raise unless it is positive and finite."""
    value = float(spacing)
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"spacing must be a positive length in metres, got {spacing!r}")
    return value


def _check_node_count(shape, spacing: float, what: str) -> None:
    """Raise with a suggested spacing if ``shape`` has more than MAX_GRID_NODES nodes."""
    count = int(np.prod(shape, dtype=np.int64))
    if count > MAX_GRID_NODES:
        suggestion = spacing * (count / MAX_GRID_NODES) ** (1.0 / 3.0)
        raise ValueError(
            f"{what} would have {shape[0]}x{shape[1]}x{shape[2]} = {count} nodes (limit 256^3); "
            f"raise the spacing from {spacing:g} m to about {suggestion:.3g} m or more"
        )


# --------------------------------------------------------------------------------------------
# cache


def _cache_dir(cache_dir) -> Path:
    """Resolve the cache folder: argument, else $FLUIDLAB_CACHE_DIR, else ~/.cache/fluidlab/sdf."""
    if cache_dir is None:
        cache_dir = os.environ.get(CACHE_ENV_VAR) or Path.home() / ".cache" / "fluidlab" / "sdf"
    return Path(cache_dir).expanduser()


def _cache_key(mesh: trimesh.Trimesh, spacing: float, padding: int) -> str:
    """sha256 of the mesh arrays and grid parameters."""
    digest = hashlib.sha256(CACHE_FORMAT.encode())
    digest.update(np.ascontiguousarray(mesh.vertices, dtype="<f8").tobytes())
    digest.update(np.ascontiguousarray(mesh.faces, dtype="<i8").tobytes())
    digest.update(f"spacing={spacing!r};padding={padding}".encode())
    return digest.hexdigest()


def _read_cache(path: Path, shape) -> np.ndarray | None:
    """Return cached values of the expected shape, or None if absent or unusable."""
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            if str(data["format"]) != CACHE_FORMAT:
                raise ValueError(f"format {data['format']!s}")
            values = np.array(data["values"], dtype=np.float64)
        if values.shape != tuple(shape) or not np.all(np.isfinite(values)):
            raise ValueError(f"values of shape {values.shape}, expected {tuple(shape)}")
    except Exception as exc:  # any damage to the file means: recompute
        warnings.warn(f"ignoring unreadable SDF cache {path} ({exc}); recomputing", RuntimeWarning, stacklevel=3)
        return None
    return values


def _write_cache(path: Path, values: np.ndarray) -> None:
    """Write ``values`` to ``path`` atomically; warn (do not fail) if the folder is not writable."""
    from fluidlab_core.files import atomic_path

    try:
        with atomic_path(path, suffix=".npz") as tmp:
            np.savez(tmp, format=np.array(CACHE_FORMAT), values=values)
    except OSError as exc:
        warnings.warn(f"could not write SDF cache {path} ({exc})", RuntimeWarning, stacklevel=3)


# --------------------------------------------------------------------------------------------
# volume sampling


def sample_mesh_volume(
    mesh: trimesh.Trimesh, spacing: float, rng: np.random.Generator | None = None, jitter: float = 0.0
) -> np.ndarray:
    """Particle positions (N, 3) [m] filling a closed mesh, one per lattice cell of size ``spacing``.

    Candidates are cell centres ``mesh.bounds[0] + spacing * (i + 1/2, j + 1/2, k + 1/2)``;
    those inside the mesh are kept, then each is moved by uniform noise in
    ``[-jitter * spacing, +jitter * spacing]`` per axis drawn from ``rng`` (required when
    ``jitter > 0``; ``0 <= jitter <= 0.5``). Each point stands for a volume ``spacing**3``, so
    ``len(points) * spacing**3`` approximates ``mesh.volume``.

    Cost: ``mesh.contains`` casts a ray per candidate, a few thousand points per second with
    trimesh's pure-Python ray engine and far faster when ``embreex`` is installed.
    """
    spacing = _check_spacing(spacing)
    jitter = float(jitter)
    if not (0.0 <= jitter <= 0.5):
        raise ValueError(f"jitter is a fraction of the spacing in [0, 0.5], got {jitter!r}")
    if jitter > 0 and rng is None:
        raise ValueError("jitter > 0 needs a seeded generator: pass rng=np.random.default_rng(seed)")
    mesh = _outward(mesh)

    lower, upper = mesh.bounds
    shape = tuple(int(n) for n in np.maximum(np.ceil((upper - lower) / spacing - 1e-9), 1).astype(np.int64))
    _check_node_count(shape, spacing, "sampling lattice")
    axes = [lower[d] + spacing * (np.arange(shape[d]) + 0.5) for d in range(3)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    inside = np.zeros(len(centres), dtype=bool)
    for start in range(0, len(centres), QUERY_CHUNK):
        inside[start : start + QUERY_CHUNK] = mesh.contains(centres[start : start + QUERY_CHUNK])
    points = centres[inside]
    if jitter > 0:
        points = points + rng.uniform(-jitter * spacing, jitter * spacing, size=points.shape)
    return points
