"""From a Trajectory to a verified joint velocity stream: `plan(trajectory) -> Plan`.

    tool poses (base frame)  -- Trajectory.poses(), moved by the task's scene pose if given in "scene"
      -> approach segment       a straight Cartesian line (quintic timing) from the start posture's tool pose
      -> IK (kinematics.py)     DLS differential IK with joint-limit and posture terms in the null space
      -> feasibility pass       uniform time scale + smooth start/stop ramps; where the joint path's corners are
                                too sharp to follow at that scale, it is filtered over up to the window of
                                the scale's acceleration bound (timescale.py)
      -> Ruckig (smoothing.py)  jerk-limited following at the control rate (jerk also bounded by the torque rate)
      -> commands               v_k = (q_{k+1} - q_k) / T: integrating the held commands reproduces q_k exactly
      -> verify (verify.py)     every 1 ms tick under the hold model, against limits x margin; joint torques and
                                torque rates of the smooth profile (dynamics.py); clearance of the links from the
                                table, the task's container and each other (collision.py)
      -> tool-path error        FK of the executed 1 ms positions against the planned, timed tool path

Nothing is returned unless every stage passes; a refusal raises a PlanningError subclass whose message
names the problem. Units: SI (m, s, rad). Frames: the robot base frame `<robot>_link0`; tool poses are the
mounting's tool frame (robot_models/mounting.json). See docs/execution.md.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation

from fluidlab_core.trajectory import Trajectory
from fluidlab_ros.collision import CollisionModel
from fluidlab_ros.dynamics import DynamicModel, Payload, torque_rate_jerk
from fluidlab_ros.errors import CollisionError, InvalidInputError, LimitError, PathError
from fluidlab_ros.frames import interpolate_poses, pose_to_se3, rotation_angle, se3_to_pose
from fluidlab_ros.kinematics import DifferentialIK, IKOptions
from fluidlab_ros.mounting import Mounting, load_mounting
from fluidlab_ros.robot import READY_Q, Robot
from fluidlab_ros.smoothing import JerkLimitedFollower
from fluidlab_ros.timescale import TimeMap, choose_time_map, followable_path
from fluidlab_ros.verify import ticks_per_command, verify

PLAN_FRACTION = 0.9  # the smoothing stage plans within 90 % of (margin x limit); the verifier checks margin x limit
TIME_MAP_SHARE = 0.9  # the time map uses 90 % of the smoothing stage's acceleration budget, leaving it headroom
BASE_FRAMES = ("fr3_link0", "panda_link0", "base")  # both arms' base frames are the same physical frame


@dataclass
class PlanReport:
    robot: str
    control_rate: float  # Hz
    margin: float  # fraction of every official limit the plan may use
    position_margin: float  # rad kept from each joint's position limits
    tolerate_lost_command: bool
    time_scale: float  # >= 1: how much slower than the trajectory the task segment runs (outside the ramps)
    time_scale_binding: str  # what set the scale
    velocity_ratio: float  # peak joint speed / planning limit at scale 1
    acceleration_ratio: float  # peak windowed joint acceleration / its budget at scale 1
    ramp_in: float  # s, smooth start of the task segment
    ramp_out: float  # s, smooth stop
    trajectory_duration: float  # s, as written in the trajectory
    approach_duration: float  # s
    task_duration: float  # s, wall time of the task segment after scaling and ramps
    total_duration: float  # s, of the whole command stream
    ik_residual_position: float  # m, worst over all samples
    ik_residual_rotation: float  # rad
    peak: dict = field(default_factory=dict)  # quantity -> peak fraction of the official limit (max over joints)
    peak_per_joint: dict = field(default_factory=dict)
    tool_path_error: float = 0.0  # m, max |planned - executed| tool position over the task segment (1 ms)
    tool_path_error_rms: float = 0.0  # m
    tool_orientation_error: float = 0.0  # rad, max over the task segment
    approach_path_error: float = 0.0  # m
    lagging_ticks: int = 0  # control ticks where smoothing could not follow the reference exactly
    planning_time: float = 0.0  # s of wall time for plan()
    stage_times: dict = field(default_factory=dict)  # s per stage: ik, time_scaling, smoothing, verify (of which
    # torque and collision), path_error
    payload_mass: float = 0.0  # kg, the point mass at the tool frame in the torque model
    jerk_budget: list = field(default_factory=list)  # rad/s^3 per joint the smoothing used (torque rate included)
    smoothing_passes: int = 1  # 2 or 3: the kinematic jerk budget let the torques change too fast
    peak_torque: list = field(default_factory=list)  # N m per joint, max |tau| (fractions: peak["torque"])
    peak_torque_rate: list = field(default_factory=list)  # N m/s per joint (fractions: peak["torque_rate"])
    clearance: float = 0.0  # m, required between the links and the table, the container and each other
    min_clearance: dict = field(default_factory=dict)  # "table", the container's name, "self" -> least distance, m
    min_clearance_at: dict = field(default_factory=dict)  # same keys -> "<link> at t = ... s"
    collision_sample_spacing: float = 0.0  # m, largest motion of a link capsule between two checked samples
    path_filter: float = 0.0  # s of trajectory time: width of the box filter on the task's joint path (0: none)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class Plan:
    """A verified command stream: send `velocities[k]` at time `times[k]` (s from the start), in the order of
    `joint_names`. `positions[k]` is where the arm is at `times[k]` when the commands are held for each 1 ms
    tick; positions[0] = q_start. The last command is zero and the arm is then at rest."""

    robot: str
    joint_names: tuple[str, ...]
    control_rate: float
    q_start: np.ndarray
    times: np.ndarray  # (K,)
    velocities: np.ndarray  # (K, dof) rad/s
    positions: np.ndarray  # (K + 1, dof) rad
    task_start_time: float  # s: the trajectory's first pose is reached here (the fluid starts moving)
    task_end_time: float
    task_time_map: TimeMap  # wall time since task_start_time -> trajectory time
    report: PlanReport

    @property
    def duration(self) -> float:
        return len(self.velocities) / self.control_rate


def command_budgets(lim, control_rate: float, margin: float = 0.8, tolerate_lost_command: bool = True):
    """(acceleration, jerk) per joint that a smooth command profile at `control_rate` may use so that the
    arm, holding each command for 1000 / rate ticks of 1 ms, sees at most margin x its limits (and, with
    `tolerate_lost_command`, also when one command is lost and the next doubles the step). Used by the
    planner and by the stop ramp (stopping.py)."""
    n_hold = ticks_per_command(control_rate, lim.check_period)
    a_eff = lim.acceleration.copy() if n_hold == 1 else np.minimum(lim.acceleration, lim.jerk * lim.check_period) / n_hold
    if tolerate_lost_command:
        a_eff = np.minimum(lim.acceleration, lim.jerk * lim.check_period) / (2 * n_hold)
    return PLAN_FRACTION * margin * a_eff, PLAN_FRACTION * margin * lim.jerk


def _task_poses(traj: Trajectory, mounting: Mounting, robot: Robot) -> np.ndarray:
    if traj.frame_id in BASE_FRAMES or traj.frame_id == robot.base_frame:
        poses = traj.poses()
    elif traj.frame_id == "scene":
        scene = pose_to_se3(mounting.scene_origin)
        poses = np.array([se3_to_pose(scene * pose_to_se3(p)) for p in traj.poses()])
    else:
        raise InvalidInputError(f"trajectory frame_id {traj.frame_id!r} is not the robot base frame "
                                f"({robot.base_frame}) or 'scene'")
    if not np.all(np.isfinite(poses)):
        raise InvalidInputError(f"tool pose {int(np.argwhere(~np.isfinite(poses))[0][0])} is NaN or infinite")
    return poses


def _approach_poses(start: np.ndarray, goal: np.ndarray, dt: float, speed: float, angular_speed: float):
    """Straight line and constant-axis rotation from start to goal with quintic (rest-to-rest) timing whose
    peak speed is `speed` m/s / `angular_speed` rad/s; samples every dt. Returns (poses, dt, speed profile
    in [0, 1] per sample, used to fade the IK's null-space motion in and out with the tool's motion)."""
    dist = np.linalg.norm(goal[:3] - start[:3])
    r0, r1 = Rotation.from_quat(start[3:]), Rotation.from_quat(goal[3:])
    rotvec = (r1 * r0.inv()).as_rotvec()
    angle = np.linalg.norm(rotvec)
    duration = max(0.5, 1.875 * dist / speed, 1.875 * angle / angular_speed)
    n = int(np.ceil(duration / dt))
    x = np.arange(n + 1) / n
    s = x ** 3 * (10 - 15 * x + 6 * x ** 2)
    poses = np.empty((n + 1, 7))
    poses[:, :3] = start[:3] + s[:, None] * (goal[:3] - start[:3])
    poses[:, 3:] = (Rotation.from_rotvec(s[:, None] * rotvec) * r0).as_quat()
    poses[-1] = goal
    return poses, duration / n, 16 * x ** 2 * (1 - x) ** 2


class _Segment:
    """IK samples of one segment, their spline q(r) and time map t -> r. `q` is the joint path the arm is
    to follow: for the task, the IK samples as timescale.followable_path returns them, with its spline (fitted
    here otherwise)."""

    def __init__(self, name, poses, dt, q, tmap: TimeMap, spline: CubicSpline | None = None):
        self.name, self.poses, self.dt, self.q, self.tmap = name, poses, dt, q, tmap
        if spline is None:
            r = np.arange(len(q)) * dt
            spline = CubicSpline(r, q, axis=0, bc_type="not-a-knot")  # ends need not be at rest: ramps
        self.spline = spline

    def reference(self, t):
        r, rd, rdd = self.tmap(t)
        d1 = self.spline(r, 1)
        return self.spline(r), d1 * rd[:, None], self.spline(r, 2) * (rd ** 2)[:, None] + d1 * rdd[:, None]


def plan(trajectory: Trajectory, robot: str | Robot = "fr3", mounting: Mounting | str | None = None,
         control_rate: float = 500.0, margin: float = 0.8, position_margin: float = 0.03, q_start=None,
         tolerate_lost_command: bool = True, max_time_scale: float = 10.0, accel_window: float = 0.05,
         max_path_error: float = 0.002, max_orientation_error: float = 0.02, approach_speed: float = 0.25,
         approach_angular_speed: float = 0.5, ik_options: IKOptions = IKOptions(), payload: Payload | None = None,
         clearance: float | None = None) -> Plan:
    """Plan the execution of `trajectory` on the arm; see the module docstring.

    robot: "fr3" (default) or "panda", or a Robot whose tool frame is already mounted.
    mounting: the task's mounting (default: robot_models/mounting.json entry of trajectory.task).
    control_rate: Hz of the command stream (must divide 1 kHz). margin: fraction of every official limit the
    stream may reach (position: position_margin rad from the limits). q_start: the arm's joint positions
    when execution begins (default: the ready posture READY_Q); the plan first moves the tool from there to
    the trajectory's first pose along a straight line (the approach segment). tolerate_lost_command: keep
    the jerk and acceleration within margin x limit even if one command is lost or overtaken by the next
    (the arm then sees two commands' change in one 1 ms tick); this halves the acceleration budget.
    max_time_scale: refuse
    trajectories that would need a larger slow-down. max_path_error / max_orientation_error: refuse when the
    executed tool path leaves the planned one by more (m / rad). payload: the load at the tool frame in the torque
    model (default robot_models/<robot>/inertials.json's: 0.5 kg at the tool frame's origin). clearance: m the
    arm's links must keep from the table, the task's container and each other (default collision.json's, 10 mm).
    """
    t_begin = time.perf_counter()
    if not 0 < margin <= 1:
        raise InvalidInputError(f"margin must be in (0, 1], got {margin}")
    if not isinstance(trajectory, Trajectory):
        raise InvalidInputError(f"expected a fluidlab_core.trajectory.Trajectory, got {type(trajectory).__name__}")
    for name, arr in (("twists", trajectory.twists), ("initial_pose", trajectory.initial_pose)):
        bad = np.argwhere(~np.isfinite(np.asarray(arr, dtype=float)))
        if len(bad):
            raise InvalidInputError(f"trajectory {name} holds NaN or infinity at index {tuple(int(i) for i in bad[0])}")
    if isinstance(mounting, str) or mounting is None:
        try:
            mounting = load_mounting(mounting or trajectory.task)
        except KeyError as err:
            raise InvalidInputError(str(err.args[0])) from None
    if isinstance(robot, str):
        try:
            robot = Robot(robot, mounting.flange_to_tool)
        except ValueError as err:
            raise InvalidInputError(str(err)) from None
    lim = robot.limits
    try:
        ticks_per_command(control_rate, lim.check_period)  # refuses rates that do not divide 1 kHz
    except ValueError as err:
        raise InvalidInputError(str(err)) from None
    period = 1.0 / control_rate

    q_start = READY_Q.copy() if q_start is None else np.asarray(q_start, dtype=float)
    if q_start.shape != (robot.dof,) or not np.all(np.isfinite(q_start)):
        raise InvalidInputError(f"q_start must be {robot.dof} finite joint positions")
    if np.any(q_start < lim.lower + position_margin) or np.any(q_start > lim.upper - position_margin):
        raise InvalidInputError(f"q_start {np.round(q_start, 4).tolist()} is outside the joint limits less "
                                f"{position_margin} rad")

    a_plan, j_plan = command_budgets(lim, control_rate, margin, tolerate_lost_command)
    try:
        dynamics = DynamicModel(robot, payload)
        collision = CollisionModel(robot, mounting, clearance)
    except ValueError as err:
        raise InvalidInputError(str(err)) from None

    def v_plan(q):
        lo, hi = lim.velocity_bounds(q)
        return PLAN_FRACTION * margin * lo, PLAN_FRACTION * margin * hi

    stages = {"ik": 0.0, "time_scaling": 0.0}
    mark = time.perf_counter()

    def lap(name):
        nonlocal mark
        now = time.perf_counter()
        stages[name] = stages.get(name, 0.0) + now - mark
        mark = now

    # tool poses and IK
    task_poses = _task_poses(trajectory, mounting, robot)
    ik = DifferentialIK(robot, ik_options)
    start_pose = se3_to_pose(robot.frame_placement(q_start))
    segments: list[_Segment] = []
    q_now = q_start
    res_p, res_r = 0.0, 0.0
    needs_approach = np.linalg.norm(start_pose[:3] - task_poses[0, :3]) > 1e-6 or rotation_angle(
        Rotation.from_quat(start_pose[3:]), Rotation.from_quat(task_poses[0, 3:])) > 1e-6
    if needs_approach:
        app_poses, app_dt, app_speed = _approach_poses(start_pose, task_poses[0], min(trajectory.dt, 0.01), approach_speed,
                                            approach_angular_speed)
        app = ik.track(app_poses, q_now, app_dt, q_posture=q_start, what="approach", null_weight=app_speed)
        lap("ik")
        _check_positions(app.q, lim, position_margin, "approach")
        q_now = app.q[-1]
        res_p, res_r = max(res_p, app.residual_position.max()), max(res_r, app.residual_rotation.max())
    task = ik.track(task_poses, q_now, trajectory.dt, q_posture=q_now, what="trajectory")
    res_p, res_r = max(res_p, task.residual_position.max()), max(res_r, task.residual_rotation.max())
    lap("ik")
    _check_positions(task.q, lim, position_margin)
    path_q = np.vstack([app.q, task.q]) if needs_approach else task.q

    def timed_segments(jerk):
        segs = []
        if needs_approach:
            tm, sc = choose_time_map(app.q, app_dt, v_plan, TIME_MAP_SHARE * a_plan, jerk, accel_window,
                                     max_time_scale)
            if not np.isfinite(sc.scale) or sc.scale > max_time_scale:
                raise LimitError(f"the approach to the first pose needs a {sc.scale:.3g}x slow-down ({sc.binding})")
            segs.append(_Segment("approach", app_poses, app_dt, app.q, tm))
        tm, sc = choose_time_map(task.q, trajectory.dt, v_plan, TIME_MAP_SHARE * a_plan, jerk, accel_window,
                                 max_time_scale)
        if not np.isfinite(sc.scale) or sc.scale > max_time_scale:
            raise LimitError(f"the trajectory is too fast for the {robot.name}: it needs a {sc.scale:.3g}x slow-down "
                             f"({sc.binding}; peak joint speed {sc.velocity_ratio:.3g}x and windowed acceleration "
                             f"{sc.acceleration_ratio:.3g}x the planning limits), more than max_time_scale = "
                             f"{max_time_scale}", scale=sc.scale)
        # the joint path the arm can follow at this scale and jerk: the IK samples, filtered where their
        # corners are too sharp (timescale.followable_path)
        task_q, m, spline = followable_path(task.q, trajectory.dt, tm.scale, TIME_MAP_SHARE * a_plan, jerk,
                                            accel_window)
        segs.append(_Segment("task", task_poses, trajectory.dt, task_q, tm, spline))
        return segs, tm, sc, (2 * m + 1) * trajectory.dt if m else 0.0

    def smoothed(segs, jerk):
        """Reference at the control ticks, then jerk-limited smoothing."""
        starts = np.cumsum([0.0] + [sg.tmap.duration for sg in segs])
        total = starts[-1]

        def reference(t: float):
            k = min(int(np.searchsorted(starts[1:-1], t, side="right")), len(segs) - 1)
            p, v, a = segs[k].reference(np.array([t - starts[k]]))
            return p[0], v[0], a[0]

        ticks = np.minimum(np.arange(1, int(np.ceil(total / period - 1e-9)) + 1) * period, total)
        seg_of_tick = np.minimum(np.searchsorted(starts[1:-1], ticks, side="right"), len(segs) - 1)
        at_ticks = [np.empty((len(ticks), robot.dof)) for _ in range(3)]
        for k, (seg, t0) in enumerate(zip(segs, starts[:-1])):
            m = seg_of_tick == k
            for dst, val in zip(at_ticks, seg.reference(ticks[m] - t0)):
                dst[m] = val
        follower = JerkLimitedFollower(robot.dof, period, a_plan, jerk, v_plan)
        return starts, follower.run(q_start, reference, total, at_ticks)

    # Time scaling and smoothing at the kinematic jerk budget; if the joint torques then change faster than
    # PLAN_FRACTION x margin x dtau_max (dynamics.py, (2)), again with each joint's jerk bounded by the torque
    # rate (torque_rate_jerk), and, should that not suffice, once more with the jerk scaled down by the excess.
    rate_budget = PLAN_FRACTION * margin
    smoothing_passes, rate_first = 0, 0.0
    for smoothing_passes in range(1, 4):
        segments, tmap, sr, path_filter = timed_segments(j_plan)
        lap("time_scaling")
        try:
            starts, sm = smoothed(segments, j_plan)
        except LimitError as err:
            if smoothing_passes == 1:
                raise
            raise LimitError(f"the joint torques would change faster than {rate_budget:.2g} x their rate limit "
                             f"({rate_first:.3g} x at the kinematic jerk budget), and the smoothing at the jerk that "
                             f"keeps them within it ({np.round(j_plan, 0).tolist()} rad/s^3) fails: {err}",
                             **err.details) from None
        lap("smoothing")
        tau_s = dynamics.torques(sm.position, sm.velocity, sm.acceleration)
        rate_frac = float(np.max(np.abs(np.diff(tau_s, axis=0)) / period / dynamics.effort_rate, initial=0.0))
        if smoothing_passes == 1:
            rate_first = rate_frac
        if rate_frac <= rate_budget or smoothing_passes == 3:
            break
        if smoothing_passes == 1:
            j_plan = torque_rate_jerk(dynamics, path_q, j_plan, margin, PLAN_FRACTION)
        else:
            j_plan = j_plan * (0.95 * rate_budget / rate_frac)
        lap("smoothing")
    commands = np.vstack([np.diff(sm.position, axis=0) / period, np.zeros((1, robot.dof))])
    positions = np.vstack([sm.position, sm.position[-1:]])
    lap("smoothing")

    ver = verify(commands, q_start, control_rate, lim, margin, position_margin, tolerate_lost_command, robot,
                 dynamics=dynamics, collision=collision, smooth=(sm.position, sm.velocity, sm.acceleration))
    lap("verify")
    stages.update(ver.check_times)
    if not ver.ok:
        if len(ver.collision_violations) == len(ver.violations):
            raise CollisionError("the motion would bring the arm too close to an obstacle: "
                                 + "; ".join(ver.violations), violations=ver.violations)
        note = "" if smoothing_passes == 1 else (
            f" (smoothed with the joint jerk reduced to {np.round(j_plan, 0).tolist()} rad/s^3: at the kinematic "
            f"jerk budget the joint torques changed {rate_first:.3g} x their rate limit)")
        raise LimitError("the command stream would violate the arm's limits: " + "; ".join(ver.violations) + note,
                         violations=ver.violations)

    # tool-path error: executed (FK of the 1 ms hold-model positions) against the planned, timed tool path
    tau = lim.check_period
    t_ms = np.arange(len(ver.positions)) * tau
    fl_rot = Rotation.from_matrix(ver.flange_rotations)
    ft = robot.flange_to_tool
    exec_p = ver.flange_positions + fl_rot.apply(ft.translation)
    exec_r = fl_rot * Rotation.from_matrix(ft.rotation)
    errors = {}
    seg_of_ms = np.searchsorted(starts[1:-1], t_ms, side="right")
    for k, (seg, t0) in enumerate(zip(segments, starts[:-1])):
        m = seg_of_ms == k
        r, _, _ = seg.tmap(t_ms[m] - t0)
        plan_p, plan_r = interpolate_poses(seg.poses, seg.dt, r)
        errors[seg.name] = (np.linalg.norm(exec_p[m] - plan_p, axis=1), rotation_angle(plan_r, exec_r[m]))
    e_p, e_r = errors["task"]
    app_err = float(errors["approach"][0].max()) if "approach" in errors else 0.0
    if e_p.max() > max_path_error or e_r.max() > max_orientation_error or app_err > max_path_error:
        raise PathError(f"the executable motion leaves the planned tool path by {e_p.max() * 1e3:.3g} mm and "
                        f"{np.degrees(e_r.max()):.3g} deg (approach {app_err * 1e3:.3g} mm); tolerance "
                        f"{max_path_error * 1e3:.3g} mm, {np.degrees(max_orientation_error):.3g} deg",
                        tool_path_error=float(e_p.max()))

    lap("path_error")
    peak = ver.summary()
    report = PlanReport(
        robot=robot.name, control_rate=control_rate, margin=margin, position_margin=position_margin,
        tolerate_lost_command=tolerate_lost_command, time_scale=float(sr.scale), time_scale_binding=sr.binding,
        velocity_ratio=sr.velocity_ratio, acceleration_ratio=sr.acceleration_ratio, ramp_in=tmap.ramp_in,
        ramp_out=tmap.ramp_out, trajectory_duration=trajectory.duration,
        approach_duration=float(starts[1]) if len(segments) == 2 else 0.0, task_duration=tmap.duration,
        total_duration=len(commands) * period, ik_residual_position=float(res_p), ik_residual_rotation=float(res_r),
        peak=peak, peak_per_joint={k: np.atleast_1d(v).tolist() for k, v in ver.peak.items()},
        tool_path_error=float(e_p.max()), tool_path_error_rms=float(np.sqrt(np.mean(e_p ** 2))),
        tool_orientation_error=float(e_r.max()), approach_path_error=app_err, lagging_ticks=len(sm.lagging_ticks),
        planning_time=time.perf_counter() - t_begin, stage_times=stages, payload_mass=float(dynamics.payload.mass),
        jerk_budget=j_plan.tolist(), smoothing_passes=smoothing_passes, peak_torque=ver.torque.peak_torque.tolist(),
        peak_torque_rate=ver.torque.peak_torque_rate.tolist(), clearance=collision.clearance,
        min_clearance=dict(ver.collision.minimum), min_clearance_at=dict(ver.collision.where),
        collision_sample_spacing=ver.collision.sample_spacing, path_filter=path_filter)
    return Plan(robot=robot.name, joint_names=robot.joint_names, control_rate=control_rate, q_start=q_start,
                times=np.arange(len(commands)) * period, velocities=commands, positions=positions,
                task_start_time=float(starts[-2]), task_end_time=float(starts[-1]), task_time_map=tmap,
                report=report)


def _check_positions(q: np.ndarray, lim, pad: float, what: str = "trajectory"):
    out = (q < lim.lower + pad) | (q > lim.upper - pad)
    if np.any(out):
        i, j = (int(v) for v in np.argwhere(out)[0])
        raise LimitError(f"{what} step {i}: {lim.joint_names[j]} would reach {q[i, j]:.4f} rad, within "
                         f"{pad} rad of its limit [{lim.lower[j]}, {lim.upper[j]}]", step=i, joint=j)
