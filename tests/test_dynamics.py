"""The dynamic twin's checks (fluidlab_ros/dynamics.py, collision.py): joint torques, torque rates and clearances
of every plan, without ROS.

Physics is checked against code that does not use the model under test: the gravity torques against the
gradient of a potential energy summed from the inertials file over link frames from Franka's DH table (not
Pinocchio), the full RNEA torques against the energy balance d(T + V)/dt = tau . qd along a motion, and the
capsule distances against coal's GJK (where installed). Then whole plans: an arm link driven into the cup or
onto the table is refused naming the link, the obstacle and the time; a fast motion with a heavier payload that
the kinematic limits allow is refused for joint 2's torque while the same motion slower passes; the shipped
trajectories pass with the default margins, except the two whose refusal this check found (see
docs/execution.md, "Dynamics and collisions").
"""
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import pytest

import robot_models
from fluidlab_core.trajectory import Trajectory
from fluidlab_ros.collision import CollisionModel, Obstacle, capsule_capsule, capsule_obstacle
from fluidlab_ros.dynamics import DynamicModel, Payload, check_torques, load_inertials
from fluidlab_ros.errors import CollisionError, LimitError
from fluidlab_ros.limits import JointLimits
from fluidlab_ros.mounting import load_mounting
from fluidlab_ros.pipeline import plan
from fluidlab_ros.robot import READY_Q, Robot

from .conftest import report
from .test_pipeline import TOOL, dh_flange, dh_link_frames

ROOT = Path(__file__).resolve().parents[1]
G = 9.81


# --- independent kinematics and energy ------------------------------------------------------------------------


def dh_frames_and_tool(q):
    """4x4 frames of links 1..7 and of the tool (TOOL on the flange) from the modified DH product."""
    tool = dh_flange(q)
    tool[:3, 3] += TOOL[2] * tool[:3, 2]
    return dh_link_frames(q), tool


def potential_energy(robot: str, q) -> float:
    """V = sum_i m_i g z_i (J) over links 1..7 and the default payload at the tool frame, from the data file."""
    doc = json.loads(robot_models.inertials_path(robot).read_text())
    frames, tool = dh_frames_and_tool(q)
    v = 0.0
    for i, f in enumerate(frames, start=1):
        link = doc["links"][f"{robot}_link{i}"]
        v += link["mass"] * G * (f[:3, :3] @ np.array(link["com"]) + f[:3, 3])[2]
    return v + doc["payload"]["mass"] * G * tool[2, 3]


def model(robot="fr3", payload=None):
    return DynamicModel(Robot(robot, TOOL), payload)


# --- the model ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("robot", ["fr3", "panda"])
def test_inertials_and_torque_limits_are_physical_and_sourced(robot):
    doc = load_inertials(robot)  # refuses non-physical inertias
    assert doc["source"] and doc["licence"] and doc["payload"]["mass"] == 0.5
    total = sum(link["mass"] for name, link in doc["links"].items() if name != f"{robot}_link0")
    lim = JointLimits.load(robot)
    assert lim.effort.tolist() == [87.0] * 4 + [12.0] * 3 and lim.effort_rate.tolist() == [1000.0] * 7
    report(f"{robot} inertials", moving_mass_kg=total)
    assert 14.0 < total < 18.0  # Franka: about 18 kg of arm, of which the base link is the rest
    if robot == "fr3":
        assert "franka_description" in doc["source"] and "inertials.yaml" in doc["source"]


def test_link_frames_are_those_of_the_inertials_source():
    """The inertials are given in each link's frame: the URDF's link frames must be example-robot-data's Panda
    frames (where the Panda's numbers come from), for every link, not only the flange."""
    pin = pytest.importorskip("pinocchio")
    found = sorted(Path(sys.prefix).glob("lib/python*/site-packages/cmeel.prefix/share/example-robot-data/robots/"
                                         "panda_description/urdf/panda.urdf"))
    if not found:
        pytest.skip("example-robot-data is not installed")
    ref = pin.buildModelFromUrdf(str(found[0]))
    ref_data = ref.createData()
    robot = Robot("panda")
    data = robot.model.createData()
    rng = np.random.default_rng(7)
    for q in rng.uniform(-2.5, 2.5, (10, 7)):
        pin.forwardKinematics(ref, ref_data, np.concatenate([q, np.zeros(ref.nq - 7)]))
        pin.forwardKinematics(robot.model, data, q)
        for j in range(1, 8):
            np.testing.assert_allclose(data.oMi[j].homogeneous,
                                       ref_data.oMi[ref.getJointId(f"panda_joint{j}")].homogeneous, atol=1e-12)


@pytest.mark.parametrize("robot", ["fr3", "panda"])
def test_static_torques_are_the_gradient_of_the_potential_energy(robot):
    """At rest, tau = g(q) = dV/dq with V summed independently (DH frames, inertials file, payload at the tool);
    about joint 1 (vertical axis) gravity has no moment, in any posture."""
    dyn = model(robot)
    rng = np.random.default_rng(4)
    lim = dyn.limits
    worst, h = 0.0, 1e-6
    for q in [READY_Q, *rng.uniform(lim.lower, lim.upper, size=(6, 7))]:
        tau = dyn.torques(q, np.zeros(7), np.zeros(7))[0]
        np.testing.assert_allclose(tau, dyn.gravity(q)[0], atol=1e-10)
        grad = np.array([(potential_energy(robot, q + h * e) - potential_energy(robot, q - h * e)) / (2 * h)
                         for e in np.eye(7)])
        worst = max(worst, np.abs(tau - grad).max())
        assert abs(tau[0]) < 1e-9
        assert dyn.potential_energy(q) == pytest.approx(potential_energy(robot, q), abs=1e-9)
    report(f"{robot} gravity vs dV/dq", max_abs_difference_Nm=worst,
           joint2_at_ready_Nm=dyn.gravity(READY_Q)[0][1])
    assert worst < 1e-5


def test_rnea_torques_balance_the_energy_along_a_motion():
    """int tau . qd dt = Delta (T + V) along q(t) = q0 + A sin(w t): RNEA (Newton-Euler) against the mass
    matrix of the composite rigid body algorithm and the independent potential energy."""
    dyn = model("fr3")
    t = np.linspace(0.0, 1.0, 4001)
    amp, w = np.array([0.4, 0.3, -0.3, 0.5, 0.6, -0.4, 0.8]), np.array([3.0, 4.0, 5.0, 3.5, 6.0, 5.5, 7.0])
    q = READY_Q + amp * np.sin(w * t[:, None])
    qd = amp * w * np.cos(w * t[:, None])
    qdd = -amp * w ** 2 * np.sin(w * t[:, None])
    tau = dyn.torques(q, qd, qdd)
    power = np.einsum("ij,ij->i", tau, qd)
    h = t[1] - t[0]
    work = h / 3 * (power[0] + power[-1] + 4 * power[1:-1:2].sum() + 2 * power[2:-1:2].sum())  # Simpson

    def energy(k):
        return 0.5 * qd[k] @ dyn.mass_matrix(q[k]) @ qd[k] + potential_energy("fr3", q[k])

    delta = energy(-1) - energy(0)
    scale = np.sum(np.abs(power)) * h
    report("energy balance", work_J=work, delta_energy_J=delta, abs_work_J=scale)
    assert abs(work - delta) < 1e-6 * scale


def test_torque_check_names_joint_time_and_limit():
    dyn = model("fr3", Payload(0.5))
    q = np.tile(READY_Q, (5, 1))
    qdd = np.zeros((5, 7))
    qdd[3, 1] = 60.0  # a spike on joint 2
    res = check_torques(dyn, q, np.zeros((5, 7)), qdd, 0.002, margin=0.8, t0=0.0)
    assert not res.ok
    assert res.violations[0].startswith("fr3_joint2 torque") and "t = 0.006 s" in res.violations[0]
    assert "exceeds 0.8 x 87 N m" in res.violations[0]
    assert "fr3_joint2 torque rate" in res.violations[1]


# --- distances ------------------------------------------------------------------------------------------------


def _coal_transform(coal, a, b):
    """coal's capsules and cylinders lie along their local z, centred: the frame that puts one on [a, b]."""
    z = (b - a) / np.linalg.norm(b - a)
    x = np.cross(z, [1.0, 0, 0] if abs(z[0]) < 0.9 else [0, 1.0, 0])
    x /= np.linalg.norm(x)
    return coal.Transform3s(np.column_stack([x, np.cross(z, x), z]), 0.5 * (a + b))


def test_capsule_distances_agree_with_coal():
    coal = pytest.importorskip("coal")
    rng = np.random.default_rng(5)
    n = 200
    a1, b1, a2, b2 = (rng.uniform(-0.15, 0.15, (n, 3)) for _ in range(4))
    r1, r2 = rng.uniform(0.01, 0.05, n), rng.uniform(0.01, 0.05, n)
    ours = capsule_capsule(a1, b1, r1, a2, b2, r2)
    cyl = Obstacle("cup", "cylinder", np.eye(3), np.array([0.02, -0.01, 0.03]), (0.045, 0.03))
    box = Obstacle("tank", "box", np.eye(3), np.array([0.0, 0.02, 0.0]), (0.08, 0.06, 0.035))
    worst, separated = 0.0, 0
    req = coal.DistanceRequest()
    req.gjk_tolerance = 1e-10

    def dist(s1, t1, s2, t2):
        return coal.distance(s1, t1, s2, t2, req, coal.DistanceResult())  # a result keeps its minimum: a new one

    for k in range(n):
        c1 = coal.Capsule(r1[k], np.linalg.norm(b1[k] - a1[k]))
        c2 = coal.Capsule(r2[k], np.linalg.norm(b2[k] - a2[k]))
        ref = dist(c1, _coal_transform(coal, a1[k], b1[k]), c2, _coal_transform(coal, a2[k], b2[k]))
        worst = max(worst, abs(ours[k] - ref))
        for ob, shape in ((cyl, coal.Cylinder(0.045, 0.06)), (box, coal.Box(0.16, 0.12, 0.07))):
            d = capsule_obstacle(a1[k] + 0.2, b1[k] + 0.2, r1[k], ob)[0]
            ref = dist(c1, _coal_transform(coal, a1[k] + 0.2, b1[k] + 0.2), shape, coal.Transform3s(np.eye(3), ob.center))
            if ref > 1e-4:
                separated += 1
                worst = max(worst, abs(d - ref))
            else:
                assert d < 1e-4  # touching or overlapping for both
    report("capsule distances vs coal", max_abs_difference_m=worst, separated_obstacle_cases=separated)
    assert worst < 1e-6 and separated > 100


def test_bounded_evaluation_finds_the_same_minimum_and_every_violation():
    rng = np.random.default_rng(6)
    a, b = rng.uniform(-0.2, 0.3, (2, 3000, 3))
    r = rng.uniform(0.02, 0.06, 3000)
    cyl = Obstacle("cup", "cylinder", np.eye(3), np.zeros(3), (0.045, 0.03))
    for fast, full in ((capsule_obstacle(a, b, r, cyl, floor=0.01), capsule_obstacle(a, b, r, cyl)),
                       (capsule_capsule(a, b, r, b[::-1], a[::-1] + 0.01, r, floor=0.01),
                        capsule_capsule(a, b, r, b[::-1], a[::-1] + 0.01, r))):
        assert fast.min() == pytest.approx(full.min(), abs=1e-12)
        np.testing.assert_array_equal(fast < 0.01, full < 0.01)
        assert np.all(fast <= full + 1e-12)


def test_self_collision_is_found_and_named():
    """The wrist folded back against the base column (joint 4 near its limit, joint 2 leaning back): link 7's
    capsules overlap link 1's; at the ready posture every pair is 0.24 m apart or more."""
    robot = Robot("fr3", TOOL)
    cm = CollisionModel(robot, load_mounting("Mixing"))
    q = np.array([1.61, -1.12, 2.09, -2.91, -2.61, 3.75, -0.89])
    res = cm.check(np.vstack([READY_Q, q]), np.array([0.0, 1.0]), refine=False)
    assert not res.ok and res.minimum["self"] < -0.03
    assert "fr3_link1 and fr3_link7 overlap each other" in " ".join(res.violations), res.violations
    assert "t = 1.000 s" in res.where["self"]
    ready = cm.check(READY_Q[None], np.zeros(1))
    report("self collision", folded_m=res.minimum["self"], ready_m=ready.minimum["self"],
           table_ready_m=ready.minimum["table"])
    assert ready.ok and ready.minimum["self"] > 0.2


# --- whole plans ----------------------------------------------------------------------------------------------


def descent(x, y, depth, duration=1.0, dt=0.002, z0=0.05):
    """The stick's tip going straight down by `depth` m from (x, y, z0), smoothly started and stopped."""
    n = int(round(duration / dt))
    env = np.sin(np.pi * np.arange(n) * dt / duration) ** 2
    tw = np.zeros((n, 6))
    tw[:, 2] = -depth / (env.sum() * dt) * env
    return Trajectory(task="Mixing", dt=dt, tool="stick", initial_pose=[x, y, z0, 0, 0, 0, 1], twists=tw)


def test_arm_driven_into_the_cup_is_refused_naming_link_obstacle_and_time():
    """The stick's tip pushed 15 cm down on the cup's axis (the stick itself is not modelled: it belongs in
    the cup): the wrist, link 7, enters the cup."""
    with pytest.raises(CollisionError, match=r"fr3_link7 overlaps the cup by [\d.]+ mm at t = [\d.]+ s "
                                             r"\(clearance 10 mm") as err:
        plan(descent(0.5, 0.0, 0.15))
    report("into the cup", message=str(err.value))


def test_arm_driven_onto_the_table_is_refused():
    with pytest.raises(CollisionError, match=r"fr3_link7 comes within [\d.]+ mm of the table at t = ([\d.]+) s") \
            as err:
        plan(descent(0.5, 0.25, 0.18))
    t = float(err.value.args[0].split("t = ")[1].split(" s")[0])
    assert t > 2.0  # in the descent, after the approach from the ready posture
    assert isinstance(err.value.details["violations"], list)


def oscillation(slow=1.0):
    """The stick bobbing up and down 5 cm at 1 Hz, 0.6 m in front of the base (joint 2 carries the load)."""
    n, dt, w = 1000, 0.002, 2 * np.pi
    t = np.arange(n) * dt
    tw = np.zeros((n, 6))
    tw[:, 2] = 0.05 * w * np.cos(w * t) * np.clip(np.minimum(t, n * dt - t) / 0.3, 0, 1)
    traj = Trajectory(task="Mixing", dt=dt, tool="stick", initial_pose=[0.6, 0.0, 0.2, 0, 0, 0, 1], twists=tw)
    return dataclasses.replace(traj, dt=dt * slow, twists=tw / slow)


def test_fast_motion_within_kinematic_limits_is_refused_for_joint_torque():
    """At 1 kHz (acceleration budget 7.2 rad/s^2) with 5 kg at the tool, the bobbing motion needs more than
    0.8 x 87 N m on joint 2 (77 N m): refused for that alone (no kinematic violation), while the same path 3x
    slower, with the same payload, passes (66 N m, of which gravity 64): the excess is the dynamics. (With 3 kg
    it was refused too until the pipeline filtered the joint path's corners (timescale.followable_path): the
    follower's corner cutting had added 15 N m; the filtered motion needs 63 N m.)"""
    fast = dict(payload=Payload(5.0), control_rate=1000, tolerate_lost_command=False, max_path_error=0.05,
                max_orientation_error=0.5)
    with pytest.raises(LimitError, match=r"fr3_joint2 torque -?[\d.]+ N m at t = [\d.]+ s exceeds 0.8 x 87 N m") as err:
        plan(oscillation(), **fast)
    violations = err.value.details["violations"]
    assert violations and all(" torque" in v for v in violations), violations
    slow = plan(oscillation(slow=3.0), **fast)
    gravity = np.abs(model("fr3", Payload(5.0)).gravity(slow.positions[::10])).max(axis=0)
    report("torque", refused=violations[0], slow_peak_joint2=slow.report.peak_per_joint["torque"][1],
           gravity_peak_joint2_Nm=gravity[1])
    assert slow.report.peak["torque"] <= 0.8 and gravity[1] < 0.8 * 87


SHIPPED = sorted(p for p in (ROOT / "trajectories").glob("*/*_small.json"))
# The check first refused two of them; the mountings were changed instead of the check (docs/execution.md):
# - IceCreamDynamic: the FR3's link-7 connector housing passed 1.9 mm from the nozzle (modelled as a 9 mm column
#   60 mm up from its exit) with the cone held 60 mm off its axis; FLANGE_TO_CONE now holds it 100 mm off (32 mm);
# - Pouring: the same housing, hanging below the glass's axis, went 19 mm into the table; the receiving cup now
#   stands on a 40 mm riser (mounting.json table_height -0.04: 21 mm clear).
# All of them plan within the node's 5 mm tool-path tolerance (0.0-1.9 mm). Transporting's left its trajectory by
# 9.6 mm until the pipeline filtered the joint path's corners (timescale.followable_path); it is 1.1 mm now.


@pytest.mark.parametrize("path", SHIPPED, ids=[p.parent.name for p in SHIPPED])
def test_shipped_trajectories_with_the_default_margins(path):
    traj = Trajectory.load(path)
    p = plan(traj, max_path_error=0.005, max_orientation_error=0.05)  # the node's tolerances
    r = p.report
    report(traj.task, peak_torque=r.peak["torque"], peak_torque_rate=r.peak["torque_rate"],
           joint2_Nm=r.peak_torque[1], **{f"clearance_{k}_mm": v * 1e3 for k, v in r.min_clearance.items()},
           passes=r.smoothing_passes, spacing_mm=r.collision_sample_spacing * 1e3, path_mm=r.tool_path_error * 1e3,
           filter_ms=r.path_filter * 1e3)
    assert r.peak["torque"] <= 0.8 and r.peak["torque_rate"] <= 0.8
    assert min(r.min_clearance.values()) >= r.clearance == 0.01
    assert r.collision_sample_spacing <= 0.002 and r.payload_mass == 0.5
