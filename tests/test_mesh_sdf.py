"""Mesh loading, signed distance grids and volume sampling against analytic shapes."""
import math
import time

import numpy as np
import pytest
import trimesh

from fluidlab_core.shapes.mesh_sdf import SDFGrid, load_mesh, mesh_sdf_grid, sample_mesh_volume

RADIUS = 0.05  # sphere radius [m]
BOX_EXTENTS = (0.10, 0.06, 0.04)  # box edge lengths [m]
SPACING = 0.005  # grid / lattice spacing [m]
SPHERE_FILL_SPACING = 0.00625  # coarser lattice for the sphere fill: mesh.contains is slow without embree


@pytest.fixture
def sphere_path(tmp_path):
    path = tmp_path / "sphere.obj"
    trimesh.creation.icosphere(subdivisions=3, radius=RADIUS).export(path)
    return path


@pytest.fixture
def box_path(tmp_path):
    path = tmp_path / "box.stl"
    trimesh.creation.box(extents=BOX_EXTENTS).export(path)
    return path


@pytest.fixture(scope="module")
def sphere_sdf(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sphere_sdf")
    path = folder / "sphere.obj"
    trimesh.creation.icosphere(subdivisions=3, radius=RADIUS).export(path)
    return mesh_sdf_grid(load_mesh(path), SPACING, cache_dir=folder / "cache")


# ------------------------------------------------------------------------------------ loading


def test_load_mesh_scale_then_translate(box_path):
    mesh = load_mesh(box_path, pose=(1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0), scale=2.0)
    np.testing.assert_allclose(mesh.extents, 2 * np.array(BOX_EXTENTS), atol=1e-9)
    np.testing.assert_allclose(mesh.bounds.mean(axis=0), [1.0, 2.0, 3.0], atol=1e-9)


def test_load_mesh_rotation_about_z_swaps_xy_extents(box_path):
    half = math.sqrt(0.5)
    # unnormalised quaternion on purpose: load_mesh normalises it
    rotated = load_mesh(box_path, pose=(0.0, 0.0, 0.0, 0.0, 0.0, 3 * half, 3 * half))
    ex, ey, ez = BOX_EXTENTS
    np.testing.assert_allclose(rotated.extents, [ey, ex, ez], atol=1e-9)

    matrix = np.eye(4)
    matrix[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    matrix[:3, 3] = [0.5, 0.0, 0.0]
    from_matrix = load_mesh(box_path, pose=matrix)
    np.testing.assert_allclose(from_matrix.extents, [ey, ex, ez], atol=1e-9)
    np.testing.assert_allclose(from_matrix.bounds.mean(axis=0), [0.5, 0.0, 0.0], atol=1e-9)


def test_load_mesh_per_axis_scale(box_path):
    mesh = load_mesh(box_path, scale=(1.0, 2.0, 0.5))
    ex, ey, ez = BOX_EXTENTS
    np.testing.assert_allclose(mesh.extents, [ex, 2 * ey, 0.5 * ez], atol=1e-9)
    assert mesh.volume > 0


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        load_mesh(tmp_path / "nope.obj")


def test_unreadable_or_empty_file(tmp_path):
    garbage = tmp_path / "garbage.stl"
    garbage.write_bytes(b"\x00\x01 not a mesh at all")
    with pytest.raises(ValueError, match="garbage.stl"):
        load_mesh(garbage)
    empty = tmp_path / "empty.obj"
    empty.write_text("# no geometry\n")
    with pytest.raises(ValueError, match="empty.obj"):
        load_mesh(empty)
    unknown = tmp_path / "mesh.xyz123"
    unknown.write_text("1 2 3\n")
    with pytest.raises(ValueError, match="could not read mesh file"):
        load_mesh(unknown)


@pytest.mark.parametrize(
    "pose, message",
    [
        ((0, 0, 0, 0, 0, 0, 0), "quaternion"),
        ((0, 0, 0, 0, 0, 1), "7 numbers"),
        (np.diag([2.0, 2.0, 2.0, 1.0]), "rotation"),
        ((0, 0, float("nan"), 0, 0, 0, 1), "non-finite"),
    ],
)
def test_bad_pose(box_path, pose, message):
    with pytest.raises(ValueError, match=message):
        load_mesh(box_path, pose=pose)


@pytest.mark.parametrize("scale", [0.0, -1.0, (1.0, 0.0, 1.0), (1.0, 2.0)])
def test_bad_scale(box_path, scale):
    with pytest.raises(ValueError, match="scale"):
        load_mesh(box_path, scale=scale)


def test_non_watertight_mesh(tmp_path):
    box = trimesh.creation.box(extents=BOX_EXTENTS)
    open_box = trimesh.Trimesh(box.vertices, box.faces[1:], process=False)
    path = tmp_path / "open_box.obj"
    open_box.export(path)
    with pytest.raises(ValueError, match="watertight.*fill_holes"):
        load_mesh(path)
    loaded = load_mesh(path, require_watertight=False)
    assert not loaded.is_watertight
    with pytest.raises(ValueError, match="closed mesh"):
        mesh_sdf_grid(loaded, SPACING, cache_dir=tmp_path)
    with pytest.raises(ValueError, match="closed mesh"):
        sample_mesh_volume(loaded, SPACING)


# -------------------------------------------------------------------------------- signed distance


def test_sphere_sdf_matches_analytic(sphere_sdf):
    assert sphere_sdf.values.min() < 0 < sphere_sdf.values.max()
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(64, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    radii = np.concatenate([[0.3, 0.6, 0.9, 1.0, 1.1, 1.3], rng.uniform(0.2, 1.4, 58)]) * RADIUS
    points = directions * radii[:, None]
    got = sphere_sdf.sample(points)
    np.testing.assert_allclose(got, radii - RADIUS, atol=0.5 * SPACING)
    assert np.all(got[radii < 0.8 * RADIUS] < 0) and np.all(got[radii > 1.2 * RADIUS] > 0)
    # at the nodes themselves the only error is the facetting of the icosphere
    nodes = sphere_sdf.origin + SPACING * np.argwhere(np.ones(sphere_sdf.shape, dtype=bool))
    exact = np.linalg.norm(nodes, axis=1) - RADIUS
    np.testing.assert_allclose(sphere_sdf.values.ravel(), exact, atol=0.05 * SPACING)


def test_grid_covers_padded_bounds(sphere_sdf):
    assert np.all(sphere_sdf.origin <= -RADIUS - 3 * SPACING + 1e-12)
    assert np.all(sphere_sdf.upper >= RADIUS + 3 * SPACING - 1e-12)


def test_sample_outside_grid_extrapolates(sphere_sdf):
    far = np.array([[1.0, 0.0, 0.0], [0.0, -0.5, 0.3]])
    got = sphere_sdf.sample(far)
    exact = np.linalg.norm(far, axis=1) - RADIUS
    assert np.all(got >= exact - 1e-9)  # distance to the box + boundary value: an upper bound
    np.testing.assert_allclose(got, exact, rtol=0.25)
    # continuous across the grid boundary
    edge = np.array([sphere_sdf.upper[0], 0.0, 0.0])
    eps = 1e-9 * np.array([1.0, 0.0, 0.0])
    assert abs(sphere_sdf.sample(edge + eps) - sphere_sdf.sample(edge - eps)) < 1e-6
    assert np.ndim(sphere_sdf.sample(edge)) == 0


def test_sdf_grid_is_frozen_and_validated():
    grid = SDFGrid(origin=np.zeros(3), spacing=1.0, values=np.zeros((2, 2, 2)))
    with pytest.raises(AttributeError):
        grid.spacing = 2.0
    with pytest.raises(ValueError):
        grid.values[0, 0, 0] = 1.0
    with pytest.raises(ValueError, match="spacing"):
        SDFGrid(origin=np.zeros(3), spacing=0.0, values=np.zeros((2, 2, 2)))
    with pytest.raises(ValueError, match="3-D"):
        SDFGrid(origin=np.zeros(3), spacing=1.0, values=np.zeros((2, 2)))


def test_sdf_grid_trilinear_is_exact_for_linear_fields():
    axes = np.meshgrid(*[np.arange(4) * 0.1 for _ in range(3)], indexing="ij")
    values = 1.0 + 2.0 * axes[0] - 3.0 * axes[1] + 0.5 * axes[2]
    grid = SDFGrid(origin=np.zeros(3), spacing=0.1, values=values)
    points = np.random.default_rng(1).uniform(0.0, 0.3, size=(50, 3))
    expected = 1.0 + points @ np.array([2.0, -3.0, 0.5])
    np.testing.assert_allclose(grid.sample(points), expected, atol=1e-12)


def test_sdf_cache_reused_and_corrupt_file_recomputed(box_path, tmp_path):
    cache = tmp_path / "cache"
    mesh = load_mesh(box_path)
    t0 = time.perf_counter()
    first = mesh_sdf_grid(mesh, SPACING, cache_dir=cache)
    t_compute = time.perf_counter() - t0
    files = list(cache.glob("*.npz"))
    assert len(files) == 1 and not list(cache.glob("*.tmp"))

    t0 = time.perf_counter()
    second = mesh_sdf_grid(mesh, SPACING, cache_dir=cache)
    t_cached = time.perf_counter() - t0
    np.testing.assert_array_equal(first.values, second.values)
    np.testing.assert_array_equal(first.origin, second.origin)
    assert t_cached < t_compute

    # the cache is keyed on the mesh and the grid parameters
    mesh_sdf_grid(mesh, 2 * SPACING, cache_dir=cache)
    mesh_sdf_grid(load_mesh(box_path, pose=(0.01, 0, 0, 0, 0, 0, 1)), SPACING, cache_dir=cache)
    assert len(list(cache.glob("*.npz"))) == 3

    files[0].write_bytes(b"this is not an npz file")
    with pytest.warns(RuntimeWarning, match="SDF cache"):
        third = mesh_sdf_grid(mesh, SPACING, cache_dir=cache)
    np.testing.assert_array_equal(first.values, third.values)
    fourth = mesh_sdf_grid(mesh, SPACING, cache_dir=cache)  # rewritten, reads cleanly again
    np.testing.assert_array_equal(first.values, fourth.values)


def test_cache_dir_from_environment(box_path, tmp_path, monkeypatch):
    monkeypatch.setenv("FLUIDLAB_CACHE_DIR", str(tmp_path / "env_cache"))
    mesh_sdf_grid(load_mesh(box_path), 2 * SPACING)
    assert len(list((tmp_path / "env_cache").glob("sdf_*.npz"))) == 1


def test_box_sdf_inside_and_outside(box_path, tmp_path):
    grid = mesh_sdf_grid(load_mesh(box_path), SPACING, cache_dir=tmp_path)
    half = np.array(BOX_EXTENTS) / 2
    points = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, half[2] + 0.01], [half[0] - 0.01, 0.0, 0.0]])
    np.testing.assert_allclose(grid.sample(points), [-half[2], 0.01, -0.01], atol=0.5 * SPACING)


@pytest.mark.parametrize("spacing, message", [(0.0, "spacing"), (-0.01, "spacing"), (1e-5, "raise the spacing")])
def test_bad_spacing(box_path, tmp_path, spacing, message):
    with pytest.raises(ValueError, match=message):
        mesh_sdf_grid(load_mesh(box_path), spacing, cache_dir=tmp_path)


# ------------------------------------------------------------------------------- volume sampling


def test_box_volume_sampling(box_path):
    points = sample_mesh_volume(load_mesh(box_path), SPACING)
    assert points.shape[1] == 3 and points.dtype == np.float64
    assert abs(len(points) * SPACING**3 / np.prod(BOX_EXTENTS) - 1) < 0.03
    half = np.array(BOX_EXTENTS) / 2
    assert np.all(np.abs(points) < half)


def test_sphere_volume_sampling(sphere_path):
    points = sample_mesh_volume(load_mesh(sphere_path), SPHERE_FILL_SPACING)
    exact = 4.0 / 3.0 * math.pi * RADIUS**3
    assert abs(len(points) * SPHERE_FILL_SPACING**3 / exact - 1) < 0.05
    assert np.all(np.linalg.norm(points, axis=1) < RADIUS)


def test_volume_sampling_jitter_is_seeded_and_bounded(box_path):
    mesh = load_mesh(box_path)
    plain = sample_mesh_volume(mesh, SPACING)
    a = sample_mesh_volume(mesh, SPACING, rng=np.random.default_rng(7), jitter=0.3)
    b = sample_mesh_volume(mesh, SPACING, rng=np.random.default_rng(7), jitter=0.3)
    np.testing.assert_array_equal(a, b)
    assert a.shape == plain.shape
    offset = np.abs(a - plain)
    assert offset.max() <= 0.3 * SPACING + 1e-12 and offset.max() > 0.1 * SPACING
    with pytest.raises(ValueError, match="rng"):
        sample_mesh_volume(mesh, SPACING, jitter=0.3)
    with pytest.raises(ValueError, match="jitter"):
        sample_mesh_volume(mesh, SPACING, rng=np.random.default_rng(0), jitter=0.8)


def test_inward_facing_mesh_keeps_sign_convention(tmp_path):
    box = trimesh.creation.box(extents=BOX_EXTENTS)
    box.invert()
    assert box.volume < 0
    grid = mesh_sdf_grid(box, 2 * SPACING, cache_dir=tmp_path)
    assert grid.sample([0.0, 0.0, 0.0]) < 0 and grid.sample([0.1, 0.1, 0.1]) > 0
    assert box.volume < 0  # the caller's mesh is not modified
