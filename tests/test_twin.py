"""The twin arm (libfranka's 1 ms checks), the stop ramp and the node's trajectory folder, without ROS.

The twin is checked against hand-made command streams whose verdict is known: a verified plan passes and
ends where the plan says; a velocity step, a too-fast joint and a run into a joint limit trip the reflex
libfranka names; a late command is held, not skipped. The stop ramp is checked by the 1 ms verifier from
several moving states, also with a lost command.
"""
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from fluidlab_ros.limits import JointLimits
from fluidlab_ros.pipeline import plan
from fluidlab_ros.robot import READY_Q
from fluidlab_ros.stopping import stop_ramp
from fluidlab_core.trajectory_store import StoreError, TrajectoryStore
from fluidlab_ros.twin import TwinArm
from fluidlab_ros.verify import verify

from .test_pipeline import circle

LIM = JointLimits.load("fr3")
ROOT = Path(__file__).resolve().parents[1]


def feed(twin, commands, rate=500.0, t0=0.0, gaps=None):
    """Send commands at exact 1 / rate spacing (plus optional extra delays {index: seconds}); returns the
    reflex or None and the time of the last command."""
    t = t0
    for k, c in enumerate(commands):
        t += 1.0 / rate + (gaps or {}).get(k, 0.0)
        r = twin.command(c, t)
        if r is not None:
            return r, t
    return None, t


def test_twin_follows_a_verified_plan_to_its_end_without_a_reflex():
    p = plan(circle(duration=2.0), "fr3")
    twin = TwinArm(LIM, p.q_start)
    twin.reset(p.q_start, 0.0)
    reflex, t = feed(twin, p.velocities)
    twin.advance(t + 0.01)
    assert reflex is None
    q, v = twin.state()
    np.testing.assert_allclose(q, p.positions[-1], atol=1e-9)
    assert not v.any()
    assert twin.ticks == round((t + 0.01) / 1e-3)  # the 1 kHz loop ran through every tick


def test_velocity_step_trips_the_discontinuity_reflex_and_stops_the_arm():
    twin = TwinArm(LIM, READY_Q)
    twin.reset(READY_Q, 0.0)
    step = np.zeros(7)
    step[3] = 0.3  # 0.3 rad/s in one 1 ms tick = 300 rad/s^2 against 10
    reflex, _ = feed(twin, [np.zeros(7), step, step])
    assert reflex is not None and reflex.kind == "joint_motion_generator_velocity_discontinuity"
    assert reflex.joint == "fr3_joint4" and reflex.value == pytest.approx(300.0)
    before = twin.state()[0]
    assert twin.command(step, 1.0) is reflex  # ignored until recovery
    twin.advance(1.1)
    np.testing.assert_array_equal(twin.state()[0], before)
    twin.recover()
    assert twin.reflex is None


def test_smooth_run_past_the_velocity_limit_trips_the_velocity_reflex():
    v_target = np.zeros(7)
    v_target[0] = 1.2 * LIM.velocity[0]  # a smooth ramp, within acceleration and jerk, to 120 % of the limit
    up = stop_ramp(v_target, v_target, 500.0, LIM, margin=1.0)[::-1]
    twin = TwinArm(LIM, READY_Q)
    twin.reset(READY_Q, 0.0)
    reflex, _ = feed(twin, np.vstack([up, np.repeat(v_target[None], 50, axis=0)]))
    assert reflex is not None and reflex.kind == "joint_velocity_violation" and reflex.joint == "fr3_joint1"
    assert reflex.value <= v_target[0] + 1e-9 and reflex.value > reflex.limit


def test_constant_speed_into_a_joint_limit_is_stopped_before_the_limit():
    v_target = np.zeros(7)
    v_target[6] = 0.5
    up = stop_ramp(v_target, v_target, 500.0, LIM, margin=1.0)[::-1]
    twin = TwinArm(LIM, READY_Q)
    twin.reset(READY_Q, 0.0)
    reflex, _ = feed(twin, np.vstack([up, np.repeat(v_target[None], 5000, axis=0)]))
    assert reflex is not None and reflex.joint == "fr3_joint7"
    # the FR3's position-based velocity limit (or the position limit itself) stops it inside the range
    assert reflex.kind in ("joint_velocity_violation", "joint_position_limits_violation")
    assert twin.state()[0][6] < LIM.upper[6]


def test_a_late_command_is_held_not_skipped():
    v = np.zeros(7)
    v[1] = 0.05
    ramp = stop_ramp(v, v, 500.0, LIM)[::-1]
    twin = TwinArm(LIM, READY_Q)
    twin.reset(READY_Q, 0.0)
    reflex, t = feed(twin, ramp)
    assert reflex is None
    q1 = twin.state()[0]
    # the next command is 10 ms late: the arm keeps the held velocity for those ticks
    twin.command(v, t + 0.012)
    np.testing.assert_allclose(twin.state()[0][1] - q1[1], 0.05 * 0.012, atol=0.05 * 0.0011)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_stop_ramp_brings_any_moving_state_to_rest_within_the_limits(seed):
    rng = np.random.default_rng(seed)
    v0 = rng.uniform(-0.3, 0.3, 7) * LIM.velocity
    up = stop_ramp(v0, v0, 500.0, LIM)[::-1][1:]  # a verified way of getting to v0 from rest
    ramp = stop_ramp(up[-1], up[-2], 500.0, LIM)
    stream = np.vstack([up, ramp])
    mid = (LIM.lower + LIM.upper) / 2  # room to speed up and stop in every joint
    res = verify(stream, mid, 500.0, LIM, margin=0.8, tolerate_lost_command=True)
    assert res.ok, res.violations
    assert not ramp[-1].any()
    # time-optimal under the budget: no longer than a trapezoid at the acceleration budget plus the jerk phases
    from fluidlab_ros.pipeline import command_budgets

    acc, jerk = command_budgets(LIM, 500.0, 0.8)
    bound = np.max(np.abs(v0) / acc + 2 * acc / jerk) + 0.01
    assert len(ramp) / 500.0 <= bound


def test_store_names_are_unique_file_stems_and_bad_names_are_refused(tmp_path):
    store = TrajectoryStore(ROOT / "trajectories")
    infos, problems = store.list()
    assert not problems
    from fluidlab_core import tasks

    assert {i.task for i in infos} == set(tasks.names())  # one shipped trajectory per registered task
    assert len({i.name for i in infos}) == len(infos)
    info = next(i for i in infos if i.task == "Mixing")
    assert store.load(info.name).task == "Mixing" and np.isfinite(info.final_loss)
    for bad in ("../Mixing/x", "a/b", "", ".hidden", "x" * 200):
        with pytest.raises(StoreError, match="not allowed"):
            store.find(bad)
    with pytest.raises(StoreError, match="no trajectory named 'nope'"):
        store.find("nope")
    # ambiguity and malformed files are named
    for task in ("Mixing", "LatteArtStir"):
        (tmp_path / task).mkdir()
        shutil.copy(info.path, tmp_path / task / "same.json")
    (tmp_path / "Mixing" / "broken.json").write_text("{not json")
    doc = json.loads(info.path.read_text())
    doc["twists"][3][0] = "NaN"
    (tmp_path / "Mixing" / "nan.json").write_text(json.dumps(doc))
    other = TrajectoryStore(tmp_path)
    with pytest.raises(StoreError, match="ambiguous"):
        other.find("same")
    with pytest.raises(StoreError, match="not valid JSON"):
        other.load("broken")
    with pytest.raises(StoreError, match="cannot be used"):
        other.load("nan")
    with pytest.raises(StoreError, match="exists already"):
        other.new_path("Mixing", "same")
    assert other.new_path("Mixing", "fresh") == tmp_path.resolve() / "Mixing" / "fresh.json"
