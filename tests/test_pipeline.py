"""The execution pipeline (fluidlab_ros): robot models, IK, time scaling, smoothing and the 1 ms verifier.

Every accepted plan is re-checked here by code that does not use the pipeline's own verifier or kinematics:
the commands are held for 1 ms ticks and differenced (velocity, acceleration, jerk, the FR3's position-based
velocity limits written from Franka's formula), and the tool path comes from a numpy product of Franka's DH
table. So a pipeline that reported success wrongly would fail these tests.
"""
import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import robot_models
from fluidlab_core.trajectory import Trajectory
from fluidlab_ros.errors import InvalidInputError, LimitError, PlanningError, UnreachableError
from fluidlab_ros.mounting import load_mounting, tasks
from fluidlab_ros.pipeline import plan
from fluidlab_ros.robot import READY_Q, load_robot
from fluidlab_ros.stopping import stop_ramp
from fluidlab_ros.timescale import box_filter, windowed_acceleration
from fluidlab_ros.verify import verify

from .conftest import report

# Franka's modified DH table (a_{i-1}, d_i, alpha_{i-1}), then the flange offset d = 0.107 m
DH = [(0.0, 0.333, 0.0), (0.0, 0.0, -math.pi / 2), (0.0, 0.316, math.pi / 2), (0.0825, 0.0, math.pi / 2),
      (-0.0825, 0.384, -math.pi / 2), (0.0, 0.0, math.pi / 2), (0.088, 0.0, math.pi / 2)]
TOOL = np.array([0.0, 0.0, 0.15, 1.0, 0.0, 0.0, 0.0])  # the Mixing mounting, written out here on purpose
MARGIN = 0.8
CENTER = np.array([0.5, 0.0, 0.05])  # tool tip 5 cm above the cup's base at (0.5, 0, 0)


def dh_link_frames(q) -> list[np.ndarray]:
    """4x4 frames of links 1..7 from the modified DH product RotX(alpha) TransX(a) RotZ(q) TransZ(d)."""
    def rx(al):
        c, s = math.cos(al), math.sin(al)
        return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])

    def rz(th):
        c, s = math.cos(th), math.sin(th)
        return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])

    def tr(x, z):
        m = np.eye(4)
        m[0, 3], m[2, 3] = x, z
        return m

    t, frames = np.eye(4), []
    for (a, d, al), qi in zip(DH, q):
        t = t @ rx(al) @ tr(a, 0.0) @ rz(qi) @ tr(0.0, d)
        frames.append(t)
    return frames


def dh_flange(q) -> np.ndarray:
    """4x4 flange pose: link 7's frame, then d = 0.107 m along its z."""
    t = dh_link_frames(q)[-1].copy()
    t[:3, 3] += 0.107 * t[:3, 2]
    return t


def dh_tool_position(q) -> np.ndarray:
    t = dh_flange(q)
    return t[:3, 3] + t[:3, :3] @ TOOL[:3]


def fr3_velocity_bounds(q):
    """Franka's FR3 position-based velocity limits (documentation 'Limits for Franka Research 3')."""
    q = np.asarray(q)
    vmax = np.array([2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26])
    k = np.array([12.0, 5.17, 7.0, 8.0, 34.0, 11.0, 34.0])
    o = np.array([0.30, 0.20, 0.20, 0.30, 0.35, 0.35, 0.35])
    qu = np.array([2.7501, 1.7918, 2.9065, -0.1458, 2.8101, 4.5205, 3.0196])
    ql = np.array([-2.7501, -1.7918, -2.9065, -3.0481, -2.8101, 0.54092, -3.0196])
    hi = np.minimum(vmax, np.maximum(0, -o + np.sqrt(np.maximum(0, k * (qu - q)))))
    lo = np.maximum(-vmax, np.minimum(0, o - np.sqrt(np.maximum(0, k * (q - ql)))))
    return lo, hi


FR3 = dict(lower=np.array([-2.7437, -1.7837, -2.9007, -3.0421, -2.8065, 0.5445, -3.0159]),
           upper=np.array([2.7437, 1.7837, 2.9007, -0.1518, 2.8065, 4.5169, 3.0159]),
           acceleration=np.full(7, 10.0), jerk=np.full(7, 5000.0))


def independent_check(p, margin=MARGIN, lost_command=True):
    """Hold each command for 1 ms ticks and check the FR3's limits by finite differences, also when one
    command is lost (the next then brings two commands' change in one tick); returns the 1 ms positions."""
    n = int(round(1000 / p.control_rate))
    v = np.repeat(p.velocities, n, axis=0)
    q = p.q_start + 1e-3 * np.vstack([np.zeros((1, 7)), np.cumsum(v, axis=0)])
    v_ext = np.vstack([np.zeros((2, 7)), v, np.zeros((2, 7))])
    acc = np.diff(v_ext, axis=0) / 1e-3
    jerk = np.diff(acc, axis=0) / 1e-3
    assert np.all(np.isfinite(v))
    assert np.all(q > FR3["lower"]) and np.all(q < FR3["upper"])
    lo, hi = fr3_velocity_bounds(q[:-1])
    assert np.all(v <= margin * hi + 1e-12) and np.all(v >= margin * lo - 1e-12)
    assert np.all(np.abs(acc) <= margin * FR3["acceleration"])
    assert np.all(np.abs(jerk) <= margin * FR3["jerk"])
    assert np.all(p.velocities[-1] == 0.0)
    if lost_command:
        c = np.vstack([np.zeros((1, 7)), p.velocities, np.zeros((1, 7))])
        jump = np.abs(c[2:] - c[:-2])
        assert np.all(jump / 1e-3 <= margin * FR3["acceleration"])
        assert np.all(jump / 1e-6 <= margin * FR3["jerk"])
    return q


def tool_path_error(p, traj: Trajectory) -> float:
    """Max distance between the tool tip (DH FK of the executed positions at the command ticks of the task
    segment) and the trajectory's pose at the same time (the plan's time map)."""
    poses = traj.poses()
    k = np.nonzero((p.times >= p.task_start_time) & (p.times <= p.task_end_time))[0]
    r = p.task_time_map(p.times[k] - p.task_start_time)[0]
    i = np.minimum((r / traj.dt).astype(int), traj.n_steps - 1)
    f = (r - i * traj.dt) / traj.dt
    planned = poses[i, :3] + f[:, None] * (poses[i + 1, :3] - poses[i, :3])
    executed = np.array([dh_tool_position(q) for q in p.positions[k]])
    return float(np.linalg.norm(executed - planned, axis=1).max())


def circle(radius=0.03, period=4.0, duration=4.0, dt=0.002, abrupt=False, task="Mixing"):
    """A stirring circle around CENTER; gentle: speed eased in and out over 1 s; abrupt: full speed at once."""
    n = int(round(duration / dt))
    t = np.arange(n) * dt
    w = 2 * np.pi / period
    tw = np.zeros((n, 6))
    tw[:, 0], tw[:, 1] = -radius * w * np.sin(w * t), radius * w * np.cos(w * t)
    if not abrupt:
        env = np.clip(np.minimum(t, duration - t) / 1.0, 0, 1)
        tw[:, :3] *= (env ** 2 * (3 - 2 * env))[:, None]
    return Trajectory(task=task, dt=dt, tool="stick", initial_pose=[*(CENTER + [radius, 0, 0]), 0, 0, 0, 1],
                      twists=tw)


def spin(rate, duration=4.0, dt=0.002):
    """The tool turning about its vertical axis at `rate` rad/s: joint 7 heads towards its limit."""
    n = int(round(duration / dt))
    tw = np.zeros((n, 6))
    tw[:, 5] = rate
    return Trajectory(task="Mixing", dt=dt, tool="stick", initial_pose=[*CENTER, 0, 0, 0, 1], twists=tw)


# --- robot models -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["fr3", "panda"])
def test_urdf_forward_kinematics_match_the_dh_table(name):
    robot = load_robot(name)
    assert robot.joint_names == tuple(f"{name}_joint{i}" for i in range(1, 8))
    rng = np.random.default_rng(1)
    worst = 0.0
    for _ in range(50):
        q = rng.uniform(robot.limits.lower, robot.limits.upper)
        worst = max(worst, np.abs(robot.frame_placement(q, robot.flange_id).homogeneous - dh_flange(q)).max())
    report(f"{name} FK vs DH", max_abs_difference=worst)
    assert worst < 1e-9


def test_urdf_matches_example_robot_data_panda():
    pin = pytest.importorskip("pinocchio")
    import glob
    import os
    import sys

    found = glob.glob(os.path.join(sys.prefix, "lib", "python*", "site-packages", "cmeel.prefix", "share",
                                   "example-robot-data", "robots", "panda_description", "urdf", "panda.urdf"))
    if not found:
        pytest.skip("example-robot-data is not installed")
    ref = pin.buildModelFromUrdf(found[0])
    ref_data = ref.createData()
    robot = load_robot("fr3")
    rng = np.random.default_rng(2)
    for _ in range(20):
        q = rng.uniform(-2.5, 2.5, 7)
        pin.framesForwardKinematics(ref, ref_data, np.concatenate([q, np.zeros(ref.nq - 7)]))
        expected = ref_data.oMf[ref.getFrameId("panda_link8")].homogeneous
        assert np.abs(robot.frame_placement(q, robot.flange_id).homogeneous - expected).max() < 1e-9


def test_limits_differ_between_fr3_and_panda_and_fr3_velocity_shrinks_near_limits():
    fr3, panda = load_robot("fr3").limits, load_robot("panda").limits
    assert fr3.jerk.tolist() == [5000.0] * 7 and panda.jerk[1] == 3750.0
    assert fr3.velocity[4] == 5.26 and panda.velocity[4] == 2.61
    assert panda.position_based_velocity is None
    rng = np.random.default_rng(3)
    q = rng.uniform(fr3.lower, fr3.upper, size=(200, 7))
    for a, b in zip(fr3.velocity_bounds(q), fr3_velocity_bounds(q)):
        np.testing.assert_allclose(a, b, atol=1e-12)
    lo, hi = fr3.velocity_bounds(fr3.upper)
    assert np.all(hi < 0.4) and np.all(lo < -1.0)  # at the upper limit: hardly any speed further up
    np.testing.assert_array_equal(panda.velocity_bounds(panda.upper)[1], panda.velocity)


def test_every_task_has_a_mounting_and_unknown_tasks_are_named():
    assert {"LatteArtStir", "Mixing", "GatheringEasy", "GatheringHard"} <= set(tasks())
    m = load_mounting("Mixing")
    np.testing.assert_allclose(m.scene_origin[:3], [0.5, 0.0, 0.0])
    np.testing.assert_allclose(m.flange_to_tool, TOOL)
    with pytest.raises(KeyError, match="known tasks are"):
        load_mounting("NoSuchTask")
    assert robot_models.urdf_path("fr3").is_file() and json.loads(robot_models.limits_path("panda").read_text())


# --- the verifier's hold model ------------------------------------------------------------------------------


def test_hold_model_turns_500hz_acceleration_into_jerk():
    """At 500 Hz each command is held for two 1 ms ticks: a ramp of 3 rad/s^2 reaches the arm as steps that
    difference to 6000 rad/s^3 (> 5000), while the same ramp at 1 kHz is fine (the notes' arithmetic)."""
    lim = load_robot("fr3").limits
    for rate, ok in ((500, False), (1000, True)):
        t = np.arange(int(0.2 * rate)) / rate
        v = np.zeros((len(t), 7))
        v[:, 0] = 3.0 * np.minimum(t, 0.2 - t - 1 / rate)  # up and down at 3 rad/s^2
        v[-1] = 0.0
        res = verify(v, READY_Q, rate, lim, margin=1.0, tolerate_lost_command=False)
        assert res.ok == ok, res.violations
        if not ok:
            assert "fr3_joint1 jerk" in res.violations[0]


def test_verifier_refuses_a_velocity_jump_and_nan():
    lim = load_robot("fr3").limits
    v = np.zeros((50, 7))
    v[10:40, 3] = 0.5
    assert not verify(v, READY_Q, 500, lim).ok
    v = np.zeros((50, 7))
    v[5, 0] = np.nan
    assert "NaN" in verify(v, READY_Q, 500, lim).violations[0]


# --- whole plans ------------------------------------------------------------------------------------------


def test_gentle_trajectory_is_verified_and_follows_the_path_within_1mm():
    traj = circle()
    p = plan(traj)
    independent_check(p)
    err = tool_path_error(p, traj)
    r = p.report
    report("gentle", tool_path_error_mm=err * 1e3, pipeline_error_mm=r.tool_path_error * 1e3,
           time_scale=r.time_scale, duration=p.duration, planning_s=r.planning_time, peak_jerk=r.peak["jerk"])
    assert err < 1e-3 and r.tool_path_error < 1e-3
    assert r.time_scale == 1.0  # gentle: no slow-down
    assert p.joint_names[0] == "fr3_joint1" and p.velocities.shape[1] == 7
    assert np.allclose(p.positions[0], READY_Q)
    assert r.approach_duration > 0 and p.task_start_time == pytest.approx(r.approach_duration)
    assert max(r.peak.values()) <= MARGIN


def test_abrupt_start_gets_a_smooth_ramp_and_stays_on_the_path():
    traj = circle(abrupt=True)
    p = plan(traj)
    independent_check(p)
    err = tool_path_error(p, traj)
    report("abrupt", tool_path_error_mm=err * 1e3, ramp_in=p.report.ramp_in, ramp_out=p.report.ramp_out)
    assert p.report.ramp_in > 0.05 and p.report.ramp_out > 0.05
    assert err < 1e-3


def test_too_fast_trajectory_is_slowed_down_until_it_fits():
    traj = circle(radius=0.05, period=0.5, duration=2.0, abrupt=True)
    p = plan(traj)
    independent_check(p)
    err = tool_path_error(p, traj)
    report("too fast", time_scale=p.report.time_scale, binding=p.report.time_scale_binding,
           task_duration=p.report.task_duration, tool_path_error_mm=err * 1e3)
    assert p.report.time_scale > 1.5 and p.report.task_duration > 1.5 * traj.duration
    assert err < 1e-3


def test_box_filter_acceleration_is_the_windowed_acceleration_and_keeps_ends_lines_and_speeds():
    """The pipeline filters a joint path with sharp corners so that its acceleration is what the time
    scaling bounded: the windowed acceleration over the box's width (exactly, away from the ends)."""
    rng = np.random.default_rng(0)
    dt, m = 0.004, 6
    qd = rng.normal(size=(200, 3))  # piecewise-constant velocities, as from twists
    q = np.vstack([np.zeros((1, 3)), np.cumsum(qd, axis=0) * dt])
    f = box_filter(q, m)
    acc = np.diff(f, 2, axis=0) / dt ** 2  # acc[j] at sample j + 1, as windowed_acceleration's j
    w = windowed_acceleration(qd, dt, (2 * m + 1) * dt)
    inner = slice(2 * m, -2 * m)
    assert np.abs(acc[inner] - w[inner]).max() < 1e-9 * np.abs(w).max()
    assert np.abs(acc).max() < 0.5 * np.abs(np.diff(q, 2, axis=0) / dt ** 2).max()  # the corners are gone
    assert np.array_equal(f[0], q[0]) and np.array_equal(f[-1], q[-1])
    assert np.abs(np.diff(f, axis=0)).max() <= np.abs(np.diff(q, axis=0)).max() + 1e-15
    line = 0.3 + np.outer(np.arange(50) * dt, [1.0, -2.0, 0.5])
    assert np.allclose(box_filter(line, m), line, atol=1e-14)
    assert np.array_equal(box_filter(q, 0), q)


def test_plans_from_where_a_stop_left_the_arm_keep_to_the_tool_path():
    """The node plans each goal from where the arm is. After a stop mid-trajectory the same trajectory, planned
    again from the stopping point, used to leave its tool path by 2.3-15.7 mm depending chaotically on where
    the stop came (a goal in CI was refused at 15.4 mm): the jerk-limited follower cut the corners of the
    IK path's piecewise-constant twists. With those corners filtered (timescale.followable_path) it is
    0.71-0.72 mm from 116 stopping points of this plan; these four gave 15-16 mm before."""
    traj = Trajectory.load(Path(__file__).resolve().parents[1] / "trajectories/Mixing/Mixing_dp_seed0_small.json")
    traj = dataclasses.replace(traj, dt=traj.dt / 0.5, twists=traj.twists * 0.5)  # speed_scale 0.5, as the node
    node = dict(max_path_error=0.005, max_orientation_error=0.05)
    first = plan(traj, **node)
    lim = load_robot("fr3").limits
    errors = []
    for k in (200, 660, 950, 1425):
        ramp = stop_ramp(first.velocities[k - 1], first.velocities[k - 2], first.control_rate, lim, MARGIN)
        q = first.positions[k] + ramp.sum(axis=0) / first.control_rate
        p = plan(traj, q_start=q, **node)
        assert np.allclose(p.positions[0], q)
        errors.append(tool_path_error(p, traj))
    independent_check(p)
    report("after a stop", tool_path_error_mm=[round(e * 1e3, 3) for e in errors],
           path_filter_ms=p.report.path_filter * 1e3)
    assert max(errors) < 1.5e-3 and max(errors) - min(errors) < 0.2e-3, errors
    assert 0 < p.report.path_filter <= 0.06


def test_far_too_fast_trajectory_is_refused():
    with pytest.raises(LimitError, match="slow-down"):
        plan(circle(radius=0.1, period=0.25, duration=1.0, abrupt=True))


def test_near_joint_limit_respects_position_based_velocity_limits():
    p = plan(spin(0.80))
    q = independent_check(p)  # includes the FR3's position-based velocity bounds at every 1 ms tick
    room = np.minimum(q - FR3["lower"], FR3["upper"] - q).min(axis=0)
    report("near limit", joint7_room_rad=room[6], peak_position=p.report.peak["position"],
           peak_velocity=p.report.peak["velocity"])
    assert room[6] < 0.1 and p.report.peak["position"] > 0.95  # joint 7 really came close to its limit


def test_past_a_joint_limit_is_refused_naming_the_joint():
    with pytest.raises(LimitError, match="fr3_joint7"):
        plan(spin(0.9))


def test_unreachable_pose_is_refused_with_step_and_residual():
    n = 1000
    tw = np.zeros((n, 6))
    tw[:, 0] = 0.5  # 1 m forward in 2 s: out of reach
    traj = Trajectory(task="Mixing", dt=0.002, tool="stick", initial_pose=[*CENTER, 0, 0, 0, 1], twists=tw)
    with pytest.raises(UnreachableError, match=r"trajectory step \d+ .*residual") as err:
        plan(traj)
    assert err.value.details["step"] > 0 and err.value.details["residual_position"] > 1e-4


def test_nan_and_bad_inputs_are_refused():
    traj = circle()
    traj.twists[100, 2] = np.nan  # after validation, as a caller could
    with pytest.raises(InvalidInputError, match="NaN"):
        plan(traj)
    with pytest.raises(InvalidInputError, match="control rate"):
        plan(circle(), control_rate=300)
    with pytest.raises(InvalidInputError, match="frame_id"):
        plan(Trajectory(task="Mixing", dt=0.002, tool="stick", initial_pose=[*CENTER, 0, 0, 0, 1],
                        twists=np.zeros((10, 6)), frame_id="world"))
    assert issubclass(InvalidInputError, PlanningError)


def test_panda_plans_with_its_own_joint_names_and_limits():
    traj = circle()
    p = plan(traj, robot="panda")
    assert p.joint_names[0] == "panda_joint1"
    lim = load_robot("panda").limits
    v = np.repeat(p.velocities, 2, axis=0)
    acc = np.diff(np.vstack([np.zeros((1, 7)), v, np.zeros((1, 7))]), axis=0) / 1e-3
    assert np.all(np.abs(v) <= MARGIN * lim.velocity) and np.all(np.abs(acc) <= MARGIN * lim.acceleration)
    assert tool_path_error(p, traj) < 1e-3


def test_scene_frame_trajectories_are_moved_by_the_mounting():
    base = circle()
    scene = Trajectory(task="Mixing", dt=base.dt, tool="stick", twists=base.twists, frame_id="scene",
                       initial_pose=np.concatenate([base.initial_pose[:3] - [0.5, 0.0, 0.0], base.initial_pose[3:]]))
    p = plan(scene)
    assert tool_path_error(p, base) < 1e-3
    assert Rotation.from_matrix(dh_flange(p.positions[-1])[:3, :3]).as_matrix()[2, 2] < -0.99  # flange down
