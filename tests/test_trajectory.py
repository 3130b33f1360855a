"""The trajectory file format: exact round trips, clear refusals, atomic writes, and poses that match the
simulator's tool motion."""
import json
import os

import numpy as np
import pytest

import fluidlab_core as fl
from fluidlab_core import materials as M
from fluidlab_core.trajectory import Trajectory, TrajectoryError, check_name, path_for


def _trajectory(n=20, seed=0):
    rng = np.random.default_rng(seed)
    twists = np.zeros((n, 6))
    twists[:, :2] = rng.uniform(-0.05, 0.05, size=(n, 2))
    twists[:, 5] = rng.uniform(-1.0, 1.0, size=n)
    return Trajectory(task="Mixing", dt=2e-3, tool="stick", initial_pose=(0.05, 0.05, 0.06, 0, 0, 0, 1),
                      twists=twists, method="dp", seed=seed, loss_history=[3.0, 2.5, 2.25], metadata={"size": "small"})


def test_round_trip_is_exact(tmp_path):
    traj = _trajectory()
    path = traj.save(path_for(tmp_path, "Mixing", "run-1"))
    assert path == tmp_path / "Mixing" / "run-1.json"
    back = Trajectory.load(path)
    np.testing.assert_array_equal(back.twists, traj.twists)
    np.testing.assert_array_equal(back.initial_pose, traj.initial_pose)
    assert (back.task, back.tool, back.dt, back.method, back.seed) == ("Mixing", "stick", 2e-3, "dp", 0)
    assert back.loss_history == [3.0, 2.5, 2.25] and back.metadata == {"size": "small"}
    doc = json.loads(path.read_text())
    assert doc["format"] == "fluidlab-trajectory" and doc["version"] == 1 and doc["frame_id"] == "fr3_link0"
    assert doc["units"]["linear_velocity"] == "m/s" and doc["software_version"] == fl.__version__


@pytest.mark.parametrize("change, message", [
    ({"format": "other"}, "not a trajectory file"),
    ({"version": 2}, "unsupported trajectory version 2"),
    ({"twists": [[0.0] * 5]}, r"twists must have shape \(N, 6\)"),
    ({"twists": [[0.0] * 6, [0.0, float("nan"), 0, 0, 0, 0]]}, "NaN or infinity .first at index .1, 1"),
    ({"twists": [["a"] * 6]}, "twists must be numbers"),
    ({"twists": []}, r"twists must have shape|twists is empty"),
    ({"dt": -1}, "dt must be a positive"),
    ({"initial_pose": [0, 0, 0, 0, 0, 0, 0]}, "zero quaternion"),
    ({"units": {"time": "ms"}}, "units"),
])
def test_bad_documents_are_refused_with_the_reason(tmp_path, change, message):
    doc = _trajectory().to_dict()
    doc.update(change)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(TrajectoryError, match=message):
        Trajectory.load(path)


def test_missing_fields_and_files():
    doc = _trajectory().to_dict()
    del doc["twists"], doc["dt"]
    with pytest.raises(TrajectoryError, match="missing dt, twists"):
        Trajectory.from_dict(doc)
    with pytest.raises(FileNotFoundError):
        Trajectory.load("/nonexistent/trajectory.json")


@pytest.mark.parametrize("name", ["../etc", "a/b", "", ".hidden", "x" * 200, "a\\b", "Mixing_dp.report"])
def test_names_with_path_separators_are_refused(name):
    with pytest.raises(TrajectoryError, match="not allowed"):
        check_name(name)


def test_a_failed_write_leaves_no_partial_file(tmp_path, monkeypatch):
    path = tmp_path / "Mixing" / "run.json"
    _trajectory(seed=1).save(path)
    before = path.read_text()

    def broken_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(OSError, match="disk full"):
        _trajectory(seed=2).save(path)
    assert path.read_text() == before
    assert sorted(p.name for p in path.parent.iterdir()) == ["run.json"]


def test_poses_match_the_simulated_tool():
    """Integrating a trajectory's twists gives the tool poses the simulator goes through with those actions."""
    traj = _trajectory(n=10)
    scene = fl.Scene(lower=(0, 0, 0), upper=(0.1, 0.1, 0.1), grid_res=16, dt=traj.dt, substeps=13)
    scene.add_particles(fl.Box((0, 0, 0), (0.1, 0.1, 0.02)), M.WATER, name="water")
    scene.add_tool(fl.Cylinder((0, 0, 0), 0.01, 0.04), pose=traj.initial_pose, name="stick")
    sim = scene.build()
    poses = traj.poses()
    for i, twist in enumerate(traj.twists):
        sim.step(twist)
        got, want = sim.tool_pose("stick"), poses[i + 1]
        np.testing.assert_allclose(got[:3], want[:3], atol=1e-12)
        assert abs(abs(np.dot(got[3:], want[3:])) - 1.0) < 1e-12  # same rotation (q and -q alike)
