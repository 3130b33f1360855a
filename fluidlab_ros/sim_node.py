"""sim_node: the simulated twin, and the bridge from optimised trajectories to a Franka arm.

    ros2 run fluidlab_ros sim_node --ros-args -p mode:=twin          (after a colcon build on ROS 2 Jazzy)
    sim_node --ros-args -p mode:=robot -p command_topic:=/my_velocity_controller/commands   (pip install)

Interfaces (all under the node's name, `~/` = /sim_node/ by default; types in fluidlab_msgs and
common_interfaces):
  actions   ~/optimise  fluidlab_msgs/action/Optimise   optimiser in a worker process; feedback each iteration
            ~/execute   fluidlab_msgs/action/Execute    plan (fluidlab_ros.pipeline), then stream at control_rate;
                                                        every execution is recorded (rosbag2 MCAP, recording.py)
            ~/replay    fluidlab_msgs/action/Replay     a recording into the fluid, compared with the plan
  services  ~/list_trajectories  fluidlab_msgs/srv/ListTrajectories
            ~/get_trajectory     fluidlab_msgs/srv/GetTrajectory
            ~/stop               std_srvs/srv/Trigger     ramp the arm to rest and abort the execute goal
            ~/arm                std_srvs/srv/SetBool     robot mode: allow (true) / forbid (false) commands
  topics    ~/commands           std_msgs/Float64MultiArray  every command sent (rad/s, controller joint order)
            <command_topic>      the same, to the JointGroupVelocityController; robot mode only, only when armed
            ~/twin/joint_states  sensor_msgs/JointState      the twin arm (rad, rad/s)
            ~/tool_pose          geometry_msgs/PoseStamped   the tool in <robot>_link0 (twin or measured arm)
            ~/tracking_error     std_msgs/Float64            m, |planned - measured| tool position while streaming
            ~/particles          sensor_msgs/PointCloud2     the twin's fluid (x, y, z float32 in <robot>_link0)
            /diagnostics         diagnostic_msgs/DiagnosticArray  mode, armed, reflex, late ticks, joint-state age
  subscribed <joint_state_topic> sensor_msgs/JointState      robot mode: the measured arm

Safety (docs/ros.md): nothing is sent unless the whole plan passed the verifier; bad input aborts the goal
with a message before anything is sent; cancel, ~/stop, a joint-state gap longer than joint_state_timeout
(robot mode), a control tick later than late_tick_limit, disarming or shutting the node down all end the
stream with a jerk-limited ramp to rest (fluidlab_ros.stopping). The twin applies libfranka's checks to what
it receives and reports a reflex the way the arm would.

Bad input on an action is answered by accepting the goal and aborting it at once with the reason in
result.message (a rejected goal carries no reason to the client); a goal arriving while another of the same
kind runs is rejected.
"""
from __future__ import annotations

import dataclasses
import json
import math
import multiprocessing as mp
import queue
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import rclpy
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.signals import SignalHandlerOptions

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path as PathMsg
from sensor_msgs.msg import JointState, PointCloud2
from std_msgs.msg import Float64, Float64MultiArray, String
from visualization_msgs.msg import MarkerArray
from std_srvs.srv import SetBool, Trigger

from fluidlab_msgs.action import Execute, Optimise, Replay
from fluidlab_msgs.msg import TrajectoryInfo
from fluidlab_msgs.srv import GetTrajectory, ListTrajectories

from fluidlab_ros.errors import PlanningError
from fluidlab_ros.frames import se3_to_pose
from fluidlab_ros.messages import marker, point_cloud, pose_msg, velocity_command
from fluidlab_ros.mounting import load_mounting
from fluidlab_ros.schedule import Schedule
from fluidlab_ros.robot import READY_Q, Robot
from fluidlab_ros.stopping import stop_ramp
from fluidlab_ros.stream import (DONE, HANDSHAKE, HEARTBEAT, INDEX, LATE_TICKS, MAX_LATE, T0, RunBuffer, StreamProcess,
                                 udp_only, row_state, rows_for, write_row)
from fluidlab_core.trajectory_store import StoreError, TrajectoryStore
from fluidlab_ros.twin import TwinArm
from fluidlab_ros import workers

MODES = ("twin", "robot")
PLAN_PICKUP_TIMEOUT = 5.0  # s the stream process may take to take a plan (nothing is sent meanwhile)
HANDSHAKE_TIMEOUT = 10.0  # s for a new stream process's publishers to be matched and acknowledged (stream.handshake)
STATE_EVERY = 5  # a recording holds every command, and the arm states and tool poses of every 5th
TARGETS = ("twin", "robot")


# The node's parameters: name -> (default, what it sets). SimNode declares them from here and `sim_node --help`
# prints them (docs/ros.md has the same table with more words).
PARAMETERS = {
    "robot_model": ("fr3", "fr3 or panda (robot_models/)"),
    "mode": ("twin", "twin: no hardware; robot: command the real arm (after ~/arm)"),
    "control_rate": (500.0, "Hz of the command stream; must divide 1 kHz"),
    "command_topic": ("/fluidlab_velocity_controller/commands", "the JointGroupVelocityController's command topic"),
    "controller_joint_names": ([""], "the controller's joint order (default: the robot's)"),
    "joint_state_topic": ("/franka/joint_states", "measured joint states (robot mode)"),
    "joint_state_qos": ("best_effort", "best_effort or reliable"),
    "joint_state_timeout": (0.1, "s without a joint state before the motion stops (robot mode)"),
    "late_tick_limit": (0.02, "s: a control tick later than this stops the motion"),
    "trajectory_folder": ("trajectories", "folder of trajectories (<folder>/<Task>/<name>.json)"),
    "margin": (0.8, "fraction of every official limit a plan may use"),
    "max_path_error": (0.005, "m: refuse a plan whose executed tool path leaves the trajectory's by more"),
    "max_orientation_error": (0.05, "rad: the same for the tool's orientation"),
    "fluid_twin": (True, "simulate the task's fluid with the executed tool motion"),
    "fluid_record_timeout": (180.0, "s an execution's result waits for the fluid twin to reach the end of the "
                                    "motion, so that its recording holds the whole execution"),
    "arch": ("cpu", "Taichi backend of the worker processes (cpu, cuda, auto)"),
    "precision": ("f32", "f32 or f64 in the worker processes"),
    "state_publish_rate": (50.0, "Hz of the twin joint states and tool pose"),
    "twin_initial_positions": (READY_Q.tolist(), "the twin arm's joint positions at start (rad)"),
    "cancel_timeout": (0.5, "s an optimiser gets to stop after a cancel before it is terminated"),
    "realtime_priority": (10, "SCHED_FIFO priority of the command-stream process (0: normal scheduling)"),
    "feedback_gain": (2.0, "1/s: position feedback on the verified profile (0: off)"),
    "feedback_max_velocity": (0.05, "rad/s: the largest feedback correction"),
    "record": (True, "record every execution as rosbag2 MCAP (docs/replay.md)"),
    "recording_folder": ("recordings", "where recordings go"),
}


def parameters_help() -> str:
    """The parameter table for `sim_node --help`."""
    width = max(map(len, PARAMETERS))
    lines = ["Parameters (--ros-args -p name:=value; defaults in brackets):"]
    for name, (default, what) in PARAMETERS.items():
        lines.append(f"  {name:<{width}}  {what} [{default}]")
    return "\n".join(lines)


@dataclass
class Stream:
    """One command stream in flight (the execute goal's): the stream process sends it (fluidlab_ros.stream);
    the node's follower thread reads its RunBuffer and fills these in."""

    plan: object
    to_robot: bool
    buf: object = None  # stream.RunBuffer shared with the stream process
    proc: object = None  # the stream.StreamProcess that sends it
    index: int = 0  # commands sent
    outcome: str = ""  # why it ended: "done", or the stop reason
    reflex: str = ""
    phase: str = "approach"
    late_ticks: int = 0  # ticks later than half a period
    max_late: float = 0.0  # s
    done: threading.Event = field(default_factory=threading.Event)
    recorder: object = None  # recording.Recorder, or None
    planned_tool: np.ndarray | None = None  # (K + 1, 7) tool poses of the plan's positions
    fk: object = None  # a Robot with the task's tool frame for the stream thread (pinocchio data is per thread)
    metadata: dict | None = None  # the recording's metadata; the stream thread adds the start time
    recorded: int = 0  # commands recorded
    start_ns: int = 0  # wall-clock time of command 0 (ns)
    fluid_epoch: int = -1  # the fluid twin's epoch of this execution (its reset); -1: no fluid twin
    fluid_final: threading.Event = field(default_factory=threading.Event)  # the fluid's final state arrived
    fluid_clouds: int = 0  # particle clouds recorded
    fluid_pending: list = field(default_factory=list)  # clouds that came before the recording's metadata
    mirror: tuple = (-1, None)  # (k, twin q as plan command k went out) of the last plan row the follower read

    # The goal's thread, the node's shutdown and the follower thread all reach the buffer; the follower closes
    # it when the stream ends. The lock keeps a stop request or a read from meeting a buffer half closed (CI
    # once: the goal's loop read the stop flag just after the follower closed the buffer of a killed stream
    # process, and the goal died with an AttributeError instead of reporting the stop).
    _buf_lock: threading.Lock = field(default_factory=threading.Lock)
    _final_stop_reason: str = ""  # the buffer's stop reason when it was closed

    def request_stop(self, reason: str):
        """Ask the stream for a ramp to rest (the first reason is kept); a stream that has ended ignores it."""
        with self._buf_lock:
            if self.buf is not None:
                self.buf.request_stop(reason)

    @property
    def stop_reason(self) -> str:
        with self._buf_lock:
            return self.buf.stop_reason() if self.buf is not None else self._final_stop_reason

    def close_buffer(self):
        """The stream has ended: keep its stop reason and release the shared buffer."""
        with self._buf_lock:
            buf, self.buf = self.buf, None
            if buf is not None:
                self._final_stop_reason = buf.stop_reason()
                buf.close()


class SimNode(Node):
    def __init__(self, **kwargs):
        super().__init__("sim_node", **kwargs)
        def p(name):
            return self.declare_parameter(name, PARAMETERS[name][0])
        self.robot_model = p("robot_model").value
        self.mode = p("mode").value
        self.control_rate = float(p("control_rate").value)
        self.command_topic = p("command_topic").value
        controller_joints = list(p("controller_joint_names").value)
        self.joint_state_topic = p("joint_state_topic").value
        js_qos = p("joint_state_qos").value
        self.joint_state_timeout = float(p("joint_state_timeout").value)
        self.late_tick_limit = float(p("late_tick_limit").value)
        folder = p("trajectory_folder").value
        self.margin = float(p("margin").value)
        # optimised trajectories change the tool velocity at every task step (corners every few ms) that a
        # jerk-limited arm rounds off; the shipped ones leave their path by 1.5-3.7 mm (docs/ros.md)
        self.max_path_error = float(p("max_path_error").value)
        self.max_orientation_error = float(p("max_orientation_error").value)
        self.fluid_twin = bool(p("fluid_twin").value)
        self.arch = p("arch").value
        self.precision = p("precision").value
        state_rate = float(p("state_publish_rate").value)
        q_init = list(p("twin_initial_positions").value)
        self.cancel_timeout = float(p("cancel_timeout").value)
        self.realtime_priority = int(p("realtime_priority").value)
        self.feedback_gain = float(p("feedback_gain").value)
        self.feedback_max_velocity = float(p("feedback_max_velocity").value)
        self.record = bool(p("record").value)
        self.recording_folder = Path(p("recording_folder").value).expanduser().resolve()
        # how long an execution's result waits for the fluid twin to reach the end of the motion, so that its
        # recording holds the fluid of the whole execution (a first execution waits for the twin's compile)
        self.fluid_record_timeout = float(p("fluid_record_timeout").value)

        if self.mode not in MODES:
            raise ValueError(f"parameter mode must be one of {MODES}, got {self.mode!r}")
        if js_qos not in ("best_effort", "reliable"):
            raise ValueError(f"parameter joint_state_qos must be 'best_effort' or 'reliable', got {js_qos!r}")
        self.robot = Robot(self.robot_model)  # raises with the known models on a bad name
        self.limits = self.robot.limits
        from fluidlab_ros.verify import ticks_per_command
        ticks_per_command(self.control_rate, self.limits.check_period)  # refuses rates that do not divide 1 kHz
        names = self.robot.joint_names
        if controller_joints == [""] or not controller_joints:
            controller_joints = list(names)
        if sorted(controller_joints) != sorted(names):
            raise ValueError(f"controller_joint_names {controller_joints} must be a permutation of {list(names)}")
        self.controller_order = np.array([names.index(j) for j in controller_joints])
        self.controller_joints = controller_joints
        self.store = TrajectoryStore(folder)
        self.twin = TwinArm(self.limits, np.asarray(q_init, dtype=float))
        self.twin.reset(q_init, time.monotonic())

        self._lock = threading.Lock()
        # goal acceptance checks and sets the running flags under this lock: the executor calls goal callbacks
        # on several threads, and two goals of one kind checked together must not both be accepted
        self._claims = threading.Lock()
        self.armed = False
        self.stream: Stream | None = None
        self.optimising = False
        self._planning = False  # an execute goal is between acceptance and its stream
        self.measured_q: np.ndarray | None = None
        self.measured_v: np.ndarray | None = None
        self.measured_time = -math.inf
        self.last_reflex = ""
        self._fluid = None  # (task, size, process, inbox, outbox)
        self._recording: Stream | None = None  # the execution whose fluid is being recorded (outlives its stream)
        self._fluid_lock = threading.Lock()
        self._mp = mp.get_context("spawn")

        cb = ReentrantCallbackGroup()
        timers = MutuallyExclusiveCallbackGroup()
        # a deep history: a reliable subscriber that stalls (a loaded machine) still gets every command
        self.pub_commands = self.create_publisher(Float64MultiArray, "~/commands", 1000)
        self.pub_controller = (self.create_publisher(Float64MultiArray, self.command_topic, 1000)
                               if self.mode == "robot" else None)
        self.pub_twin_js = self.create_publisher(JointState, "~/twin/joint_states", 10)
        self.pub_tool = self.create_publisher(PoseStamped, "~/tool_pose", 10)
        self.pub_tracking = self.create_publisher(Float64, "~/tracking_error", 10)
        self.pub_particles = self.create_publisher(PointCloud2, "~/particles", 2)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        # for RViz / Foxglove: latched (transient local) so that a viewer started later still gets them
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
        self.pub_markers = self.create_publisher(MarkerArray, "~/scene_markers", latched)
        self.pub_path = self.create_publisher(PathMsg, "~/planned_path", latched)
        self.pub_description = self.create_publisher(String, "~/robot_description", latched)
        import robot_models
        self.pub_description.publish(String(data=robot_models.urdf_path(self.robot_model).read_text()))
        self._scene = None  # the fluid worker's scene description (colours, statics, tools)
        self._markers: MarkerArray | None = None  # built from it once; the tool markers move
        self._marker_pose = np.zeros(7)
        self._state_ticks = 0
        if self.mode == "robot":
            qos = qos_profile_sensor_data if js_qos == "best_effort" else QoSProfile(
                depth=10, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
            self.create_subscription(JointState, self.joint_state_topic, self._on_joint_state, qos,
                                     callback_group=cb)
        # The goal services keep 100 requests (rclpy's default keeps 10): a burst of goals from several clients
        # beyond that was dropped unanswered (a test's 20 Execute goals: some never got a response), where each
        # must get its rejection.
        requests = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                              durability=DurabilityPolicy.VOLATILE)
        servers = {"goal_service_qos_profile": requests, "result_service_qos_profile": requests,
                   "cancel_service_qos_profile": requests, "cancel_callback": lambda _: CancelResponse.ACCEPT,
                   "callback_group": cb}
        ActionServer(self, Optimise, "~/optimise", execute_callback=self._optimise,
                     goal_callback=self._optimise_goal, **servers)
        ActionServer(self, Execute, "~/execute", execute_callback=self._execute, goal_callback=self._execute_goal,
                     **servers)
        ActionServer(self, Replay, "~/replay", execute_callback=self._replay, goal_callback=self._replay_goal,
                     **servers)
        self.replaying = False
        self.create_service(ListTrajectories, "~/list_trajectories", self._list, callback_group=cb)
        self.create_service(GetTrajectory, "~/get_trajectory", self._get, callback_group=cb)
        self.create_service(Trigger, "~/stop", self._stop, callback_group=cb)
        self.create_service(SetBool, "~/arm", self._arm, callback_group=cb)
        self.create_timer(1.0 / state_rate, self._publish_state, callback_group=timers)
        self.create_timer(1.0, self._publish_diagnostics, callback_group=timers)
        self._state_robot = None  # the arm with the last executed task's tool frame, for the state timer
        self._closing = threading.Event()  # set by shutdown(): the particle thread ends before rclpy does
        self._particle_thread = threading.Thread(target=self._particle_loop, daemon=True)
        self._particle_thread.start()
        # the command stream's own process (fluidlab_ros.stream), started now so that its publishers are
        # discovered long before the first command; replaced if it dies
        self._stream_config = {
            "robot_model": self.robot_model, "mode": self.mode, "node_name": self.get_name(),
            "commands_topic": self.pub_commands.topic_name,
            "controller_topic": self.pub_controller.topic_name if self.pub_controller is not None else "",
            "joint_state_topic": self.joint_state_topic, "joint_state_qos": js_qos,
            "realtime_priority": self.realtime_priority}
        self._stream_proc = self._start_stream_process()
        self.get_logger().info(
            f"sim_node up: mode {self.mode}, robot {self.robot_model}, {self.control_rate:g} Hz, trajectories in "
            f"{self.store.folder}" + (f", commands to {self.command_topic} when armed, joint states from "
                                      f"{self.joint_state_topic}" if self.mode == "robot" else ""))

    # --- measured arm ----------------------------------------------------------------------------------
    def _on_joint_state(self, msg: JointState):
        names = self.robot.joint_names
        try:
            idx = [list(msg.name).index(j) for j in names]
        except ValueError:
            return  # another arm's or a gripper's joint states
        q = np.array([msg.position[i] for i in idx])
        v = np.array([msg.velocity[i] for i in idx]) if len(msg.velocity) == len(msg.name) else None
        with self._lock:
            self.measured_q, self.measured_v, self.measured_time = q, v, time.monotonic()
        stream = self.stream
        if stream is not None and stream.recorder is not None:
            out = JointState(name=list(names), position=q.tolist(), velocity=[] if v is None else v.tolist())
            out.header = msg.header
            stream.recorder.put("/sim_node/measured_joint_states", out, time.time_ns())

    def _joint_state_age(self) -> float:
        return time.monotonic() - self.measured_time

    def _arm_positions(self) -> np.ndarray:
        """The arm the node acts on: measured in robot mode, the twin otherwise."""
        if self.mode == "robot":
            with self._lock:
                return None if self.measured_q is None else self.measured_q.copy()
        return self.twin.state()[0]

    # --- services ----------------------------------------------------------------------------------------
    def _info_msg(self, info) -> TrajectoryInfo:
        return TrajectoryInfo(name=info.name, task=info.task, method=info.method, seed=info.seed, steps=info.steps,
                              dt=info.dt, duration=info.duration, final_loss=info.final_loss)

    def _list(self, request, response):
        infos, problems = self.store.list(request.task)
        for line in problems:
            self.get_logger().warn(f"skipping an unusable trajectory file: {line}")
        response.trajectories = [self._info_msg(i) for i in infos]
        return response

    def _get(self, request, response):
        try:
            loaded = self.store.read(request.name)
            response.info = self._info_msg(self.store.info(loaded.path, loaded.trajectory))
            response.document = loaded.data.decode()
            response.success, response.message = True, str(loaded.path)
        except StoreError as err:
            response.success, response.message = False, str(err)
        return response

    def _stop(self, request, response):
        stream = self.stream
        if stream is None:
            response.success, response.message = True, "the arm is not being commanded; nothing to stop"
            return response
        stream.request_stop("stopped by ~/stop")
        response.success, response.message = True, "ramping the arm to rest"
        return response

    def _no_controller(self) -> str:
        """Why commands to the robot would reach no controller, or '': nothing subscribes to command_topic. A
        controller that came up in the middle of a stream would take its first command mid-motion, a velocity
        step from rest; so a robot goal needs the controller there before it starts (and the stream's handshake
        then waits for it to hear the stream from its first command, stream.handshake)."""
        if self.pub_controller is None or self.pub_controller.get_subscription_count() > 0:
            return ""
        return (f"nothing subscribes to {self.pub_controller.topic_name} (is the velocity controller loaded and "
                f"active?)")

    def _arm(self, request, response):
        if self.mode != "robot":
            if request.data and self.twin.reflex is not None:
                self.twin.recover()
                response.success, response.message = True, "twin mode: cleared the twin's reflex (error recovery)"
            else:
                response.success = True
                response.message = "twin mode: commands go to the twin only; arming is for robot mode"
            return response
        if request.data:
            age = self._joint_state_age()
            if age > self.joint_state_timeout:
                response.success = False
                response.message = (f"cannot arm: no joint states on {self.joint_state_topic} for "
                                    f"{age:.3g} s (timeout {self.joint_state_timeout} s)")
                return response
            missing = self._no_controller()
            if missing:
                response.success, response.message = False, f"cannot arm: {missing}"
                return response
            self.armed = True
            response.success, response.message = True, "armed: ~/execute goals with target 'robot' may command the arm"
            self.get_logger().info("armed")
        else:
            self.armed = False
            stream = self.stream
            if stream is not None and stream.to_robot:
                stream.request_stop("disarmed")
            response.success, response.message = True, "disarmed"
            self.get_logger().info("disarmed")
        return response

    # --- optimise ----------------------------------------------------------------------------------------
    def _claim(self, flag: str, what: str) -> GoalResponse:
        """Accept a goal if no other of its kind runs (the attribute `flag` says), and mark that one runs."""
        with self._claims:
            if getattr(self, flag):
                self.get_logger().warn(f"rejected a {what} goal: another one is running")
                return GoalResponse.REJECT
            setattr(self, flag, True)
        return GoalResponse.ACCEPT

    def _optimise_goal(self, goal):
        return self._claim("optimising", "optimise")

    def _check_optimise(self, g) -> dict:
        from fluidlab_core import tasks
        from fluidlab_core.optim import METHODS
        from fluidlab_core.tasks import SIZES

        if g.task not in tasks.names():
            raise ValueError(f"unknown task {g.task!r}; tasks: {', '.join(tasks.names())}")
        size = g.size or "small"
        if size not in SIZES:
            raise ValueError(f"unknown size {g.size!r}; sizes: {', '.join(SIZES)}")
        if g.method not in METHODS:
            raise ValueError(f"unknown method {g.method!r}; methods: {', '.join(METHODS)}")
        task = tasks.make(g.task, size=size)
        if g.budget < task.horizon:
            raise ValueError(f"budget {g.budget} simulated steps is less than one rollout of {g.task} ({size}): "
                             f"{task.horizon} steps")
        if g.seed < 0:
            raise ValueError(f"seed must be non-negative, got {g.seed}")
        name = g.name or f"{g.task}_{g.method}_seed{g.seed}_{size}_{time.strftime('%Y%m%d-%H%M%S', time.gmtime())}"
        path = self.store.new_path(g.task, name)
        return {"task": g.task, "size": size, "method": g.method, "budget": int(g.budget), "seed": int(g.seed),
                "name": name, "path": str(path)}

    def _optimise(self, goal_handle):
        result = Optimise.Result()
        try:
            try:
                request = self._check_optimise(goal_handle.request)
            except (ValueError, StoreError) as err:
                result.message = str(err)
                self.get_logger().warn(f"optimise goal refused: {err}")
                goal_handle.abort()
                return result
            out, stop = self._mp.Queue(), self._mp.Event()
            proc = self._mp.Process(target=workers.optimise_worker, name="fluidlab-optimise",
                                    args=(request, out, stop, str(self.store.folder), self.arch, self.precision),
                                    daemon=True)
            proc.start()
            self.get_logger().info(f"optimising {request['task']} ({request['size']}) with {request['method']}, "
                                   f"budget {request['budget']}, seed {request['seed']} in process {proc.pid}")
            t0 = time.monotonic()

            def feedback(msg):
                goal_handle.publish_feedback(Optimise.Feedback(iteration=msg["iteration"], loss=msg["loss"],
                                                               best_loss=msg["best_loss"],
                                                               elapsed=time.monotonic() - t0))

            outcome, msg = self._pump(goal_handle, proc, out, stop, feedback)
            if outcome == "result":
                result.trajectory_name, result.final_loss = msg["name"], msg["final_loss"]
                result.message = (f"saved {msg['path']} after {msg['iterations']} iterations in "
                                  f"{time.monotonic() - t0:.1f} s")
                self.get_logger().info(result.message)
                goal_handle.succeed()
            elif outcome == "cancelled":
                result.message = f"cancelled after {time.monotonic() - t0:.1f} s; nothing saved"
                goal_handle.canceled()
            else:
                result.message = f"optimisation failed: {msg}"
                self.get_logger().error(result.message)
                goal_handle.abort()
            return result
        finally:
            self.optimising = False

    def _pump(self, goal_handle, proc, out, stop, on_feedback):
        """Relay a worker process's messages to its goal until it ends. Returns ("result", message),
        ("cancelled", None) or ("failed", reason). On cancel, `stop` (an Event the worker reads between
        iterations) is set, and the process is terminated if it has not ended within cancel_timeout (a
        simulation step does not look at it)."""
        cancel_at = None
        while True:
            if goal_handle.is_cancel_requested and cancel_at is None:
                if stop is not None:
                    stop.set()
                cancel_at = time.monotonic()
            if cancel_at is not None and (stop is None or not proc.is_alive()
                                          or time.monotonic() - cancel_at > self.cancel_timeout):
                if proc.is_alive():
                    # terminated, and reaped beside the goal: a loaded machine can take a second or more to end a
                    # process, which the cancel's reply must not wait for (nothing it would save is kept)
                    proc.terminate()
                    threading.Thread(target=proc.join, args=(10.0,), daemon=True, name="reap-optimiser").start()
                else:
                    proc.join(2.0)
                return "cancelled", None
            try:
                msg = out.get(timeout=0.05)
            except queue.Empty:
                if not proc.is_alive() and out.empty():
                    return "failed", f"the worker process ended unexpectedly (exit code {proc.exitcode})"
                continue
            if msg["kind"] == "feedback":
                on_feedback(msg)
            elif msg["kind"] == "result":
                proc.join(5.0)
                return "result", msg
            elif msg["kind"] == "error":
                proc.join(5.0)
                self.get_logger().error(msg["message"] + "\n" + msg.get("traceback", ""))
                return "failed", msg["message"]
            # "cancelled": the worker saw the stop event; the cancel branch above ends the goal

    # --- replay ------------------------------------------------------------------------------------------
    def _replay_goal(self, goal):
        return self._claim("replaying", "replay")

    def _replay(self, goal_handle):
        from fluidlab_ros.replay import parse_disturbance

        g = goal_handle.request
        result = Replay.Result()
        try:
            path = Path(g.recording_path).expanduser()
            if not path.is_absolute():
                path = self.recording_folder / path
            if not g.recording_path or not path.is_dir():
                raise ValueError(f"no recording folder at {path}")
            # a client may read and write only under the recording folder (a goal is not a shell)
            if not path.resolve().is_relative_to(self.recording_folder):
                raise ValueError(f"recording {path} is outside the recording folder {self.recording_folder}")
            parse_disturbance(g.disturbance)  # refuses unknown keys before any work
            out_dir = Path(g.out_dir).expanduser() if g.out_dir else path / "replay"
            if not out_dir.is_absolute():
                out_dir = path / out_dir
            if not out_dir.resolve().is_relative_to(self.recording_folder):
                raise ValueError(f"out_dir {out_dir} is outside the recording folder {self.recording_folder}")
        except ValueError as err:
            self.replaying = False
            result.message = str(err)
            goal_handle.abort()
            return result
        out = self._mp.Queue()
        proc = self._mp.Process(target=workers.replay_worker, name="fluidlab-replay", daemon=True,
                                args=(str(path), str(out_dir), g.disturbance, out, self.arch, self.precision))
        proc.start()
        try:
            outcome, msg = self._pump(goal_handle, proc, out, None, lambda m: goal_handle.publish_feedback(
                Replay.Feedback(phase=m["phase"], progress=m["progress"])))
            if outcome == "result":
                rep = msg["report"]
                result.success, result.report_path = True, msg["report_path"]
                result.loss_planned, result.loss_replayed = rep["loss_planned"], rep["loss_replayed"]
                result.tool_path_error = rep["tool_path_error_task_max"]
                result.message = (f"loss planned {rep['loss_planned']:.6g}, replayed {rep['loss_replayed']:.6g}; "
                                  f"tool path error {rep['tool_path_error_task_max'] * 1e3:.3g} mm"
                                  + ("" if rep["closed"] else "; the recording was never closed (crash?)"))
                goal_handle.succeed()
            elif outcome == "cancelled":
                result.message = "cancelled"
                goal_handle.canceled()
            else:
                result.message = f"replay failed: {msg}"
                goal_handle.abort()
            return result
        finally:
            proc.join(5.0)
            self.replaying = False

    # --- execute -----------------------------------------------------------------------------------------
    def _execute_goal(self, goal):
        # an execution runs until its recording has the fluid's final state (`_recording`), after its stream
        with self._claims:
            if self.stream is not None or self._planning or self._recording is not None:
                self.get_logger().warn("rejected an execute goal: another one is running")
                return GoalResponse.REJECT
            self._planning = True
        return GoalResponse.ACCEPT

    def _prepare(self, g):
        """Check an execute goal and plan it; raises ValueError / StoreError / PlanningError with the reason."""
        from fluidlab_ros.pipeline import plan

        target = g.target or "twin"
        if target not in TARGETS:
            raise ValueError(f"unknown target {g.target!r}; targets: {', '.join(TARGETS)}")
        if target == "robot":
            if self.mode != "robot":
                raise ValueError("target 'robot' needs the node in robot mode (parameter mode:=robot)")
            if not self.armed:
                raise ValueError("target 'robot': the node is not armed; call ~/arm with data: true first")
            age = self._joint_state_age()
            if age > self.joint_state_timeout:
                raise ValueError(f"target 'robot': no joint states on {self.joint_state_topic} for {age:.3g} s")
            missing = self._no_controller()
            if missing:
                raise ValueError(f"target 'robot': {missing}")
        scale = 1.0 if g.speed_scale == 0 else float(g.speed_scale)
        if not (0 < scale <= 1):
            raise ValueError(f"speed_scale must be in (0, 1] (0 means 1), got {g.speed_scale}")
        loaded = self.store.read(g.trajectory_name)
        traj = loaded.trajectory
        if scale != 1.0:  # the same poses, slower: every twist times s, every step dt / s
            traj = dataclasses.replace(traj, dt=traj.dt / scale, twists=traj.twists * scale)
        if self.twin.reflex is not None:
            self.get_logger().warn(f"twin error recovery before a new goal ({self.twin.reflex.message()})")
            self.twin.recover()
        q_start = self._arm_positions()
        if q_start is None:
            raise ValueError("no measured joint positions yet")
        if target == "robot":
            self.twin.reset(q_start, time.monotonic())  # the twin mirrors the arm it shadows
        try:
            mounting = load_mounting(traj.task)
        except KeyError as err:
            raise ValueError(str(err.args[0])) from None
        pl = plan(traj, self.robot_model, mounting, control_rate=self.control_rate, margin=self.margin,
                  q_start=q_start, max_path_error=self.max_path_error,
                  max_orientation_error=self.max_orientation_error)
        return loaded, traj, mounting, pl, target

    def _execute(self, goal_handle):
        g = goal_handle.request
        result = Execute.Result()
        goal_handle.publish_feedback(Execute.Feedback(progress=0.0, tracking_error=0.0, phase="planning"))
        try:
            loaded, traj, mounting, pl, target = self._prepare(g)
        except (ValueError, StoreError, PlanningError) as err:
            self._planning = False
            result.success, result.message = False, str(err)
            self.get_logger().warn(f"execute goal refused, nothing sent: {err}")
            goal_handle.abort()
            return result
        rep = pl.report
        result.duration, result.time_scale = float(pl.duration), float(rep.time_scale)
        summary = (f"{g.trajectory_name}: {pl.duration:.2f} s of commands ({len(pl.velocities)} at "
                   f"{self.control_rate:g} Hz), time scale {rep.time_scale:.3g}, peak "
                   + ", ".join(f"{k} {v:.0%}" for k, v in rep.peak.items() if k in
                               ("velocity", "acceleration", "jerk")) + f" of the limits, tool-path error "
                   f"{rep.tool_path_error * 1e3:.3g} mm")
        if g.dry_run:
            self._planning = False
            result.success, result.message = True, "dry run, nothing sent: " + summary
            goal_handle.succeed()
            return result

        stream = Stream(plan=pl, to_robot=(target == "robot"))
        fk = Robot(self.robot_model, mounting.flange_to_tool)
        stream.fk = Robot(self.robot_model, mounting.flange_to_tool)  # the stream thread's own (pinocchio data)
        pos, rot = fk.tool_positions_rotations(pl.positions)
        from scipy.spatial.transform import Rotation
        stream.planned_tool = np.hstack([pos, Rotation.from_matrix(rot).as_quat()])
        self._state_robot = Robot(self.robot_model, mounting.flange_to_tool)  # the state timer's own
        path_msg = PathMsg()
        path_msg.header.frame_id = self.robot.base_frame
        path_msg.header.stamp = self.get_clock().now().to_msg()
        path_msg.poses = [pose_msg(p, self.robot.base_frame, 0)
                          for p in np.vstack([stream.planned_tool[:-1:10], stream.planned_tool[-1:]])]
        self.pub_path.publish(path_msg)
        if self.record:
            try:
                stream.recorder = self._open_recording(g)
            except Exception as err:  # noqa: BLE001 - refuse to move without the record that was asked for
                self._planning = False
                result.success, result.message = False, f"cannot open the recording, nothing sent: {err}"
                self.get_logger().error(result.message)
                goal_handle.abort()
                return result
        if stream.recorder is not None:
            stream.metadata = self._recording_metadata(g, loaded, mounting, pl, target)
            self._recording = stream  # before the fluid's reset: its first cloud comes within milliseconds
        sp = self._stream_proc
        if not sp.wait_ready(30.0):
            self._planning = False
            if self._recording is stream:
                self._recording = None
            if stream.recorder is not None:
                stream.recorder.close()
            self._stream_proc = self._start_stream_process()
            result.success, result.message = False, ("the command stream process is not running (it did not start "
                                                     "within 30 s); nothing sent; a new one is starting")
            self.get_logger().error(result.message)
            goal_handle.abort()
            return result
        if self.fluid_twin:
            self._fluid_reset(traj, stream)
        stream.proc = sp
        stream.buf = RunBuffer(rows_for(len(pl.velocities), self.control_rate), self.limits.dof)
        self.stream = stream
        self._planning = False
        thread = threading.Thread(target=self._follow, args=(stream, traj), name="stream-follower", daemon=True)
        self.get_logger().info(f"executing on the {target}: {summary}")
        thread.start()
        plan_tool = None
        worst = 0.0
        while not stream.done.wait(0.1):
            if goal_handle.is_cancel_requested:
                stream.request_stop("cancelled")
            fluid = self._fluid
            if stream.fluid_epoch >= 0 and fluid is not None and not fluid[2].is_alive():
                stream.request_stop(f"the fluid twin's worker process died (exit code {fluid[2].exitcode})")
            if stream.to_robot:  # the measured arm now, against the plan's command now
                k, q = min(stream.index, len(pl.positions) - 1), self._arm_positions()
            else:  # the twin after the last row the follower read, against that row's command: the follower may
                # be behind the stream (a loaded node), and a mirror from then against the plan of now would
                # count the lag as error (67 mm once, at 1 kHz under load)
                k, q = stream.mirror  # (the twin when command k went out: planned at positions[k])
            err = 0.0
            if q is not None:
                plan_tool = fk.frame_placement(pl.positions[k]).translation
                err = float(np.linalg.norm(fk.frame_placement(q).translation - plan_tool))
                worst = max(worst, err) if not stream.stop_reason else worst
            self.pub_tracking.publish(Float64(data=err))
            goal_handle.publish_feedback(Execute.Feedback(progress=stream.index / len(pl.velocities),
                                                          tracking_error=err, phase=stream.phase))
        thread.join()
        self.stream = None
        result.max_tracking_error = worst
        note = ""
        if stream.recorder is not None:
            note = self._record_fluid_to_the_end(stream, goal_handle)
            if self._recording is stream:
                self._recording = None
            path = stream.recorder.close()
            result.recording_path = str(path)
            note = f"; recorded in {path}{note}" + (f" (recording problem: {stream.recorder.error})"
                                                     if stream.recorder.error else "")
        if stream.outcome == "done":
            result.success = True
            result.message = (f"done: {summary}; max tracking error {worst * 1e3:.3g} mm; "
                              f"{stream.late_ticks} late ticks (max {stream.max_late * 1e3:.3g} ms)" + note)
            goal_handle.succeed()
        else:
            result.success = False
            result.message = (f"stopped after {stream.index} of {len(pl.velocities)} commands: {stream.outcome}"
                              + (f" ({stream.reflex})" if stream.reflex else "")
                              + ("; the arm was ramped to rest" if stream.index else
                                 "; nothing of the plan was sent (the arm stayed at rest)") + note)
            if stream.outcome == "cancelled" and goal_handle.is_cancel_requested:
                goal_handle.canceled()
            else:
                goal_handle.abort()
        self.get_logger().info(result.message)
        return result

    def _record_fluid_to_the_end(self, stream: Stream, goal_handle) -> str:
        """Wait (at most fluid_record_timeout) until the fluid twin has stepped every pose of the execution and
        sent its final state, so that the recording holds the fluid up to the end of the motion; returns a note
        for the result message."""
        if stream.fluid_epoch < 0:
            return ""
        fluid = self._fluid
        if fluid is None or not fluid[2].is_alive():
            return f"; the fluid twin is not running: {stream.fluid_clouds} particle clouds recorded"
        fluid[3].put({"kind": "final", "stamp": time.time_ns(), "epoch": stream.fluid_epoch})
        t0 = time.monotonic()
        while not stream.fluid_final.wait(0.5):
            waited = time.monotonic() - t0
            if waited > self.fluid_record_timeout or not fluid[2].is_alive():
                why = "it stopped" if not fluid[2].is_alive() else f"not within {self.fluid_record_timeout:g} s"
                self.get_logger().warn(f"the recording closes without the fluid's final state ({why})")
                return (f"; the fluid twin did not reach the end of the motion ({why}): {stream.fluid_clouds} "
                        f"particle clouds recorded")
            goal_handle.publish_feedback(Execute.Feedback(progress=1.0, tracking_error=0.0,
                                                          phase="recording the fluid"))
        return f"; {stream.fluid_clouds} particle clouds of the fluid twin recorded, to the end of the motion"

    # --- the command stream ------------------------------------------------------------------------------
    def _open_recording(self, g):
        from fluidlab_ros.recording import Recorder

        stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
        folder = self.recording_folder / f"{stamp}_{g.trajectory_name}"
        n = 1
        while folder.exists():
            n += 1
            folder = self.recording_folder / f"{stamp}_{g.trajectory_name}_{n}"
        return Recorder(folder)

    def _recording_metadata(self, g, loaded, m, pl, target: str) -> dict:
        import hashlib

        from fluidlab_core import __version__
        scale = 1.0 if g.speed_scale == 0 else float(g.speed_scale)
        T = 1.0 / self.control_rate
        times = np.arange(len(pl.velocities) + 1) * T
        r = np.full(len(times), np.nan)
        seg = (times >= pl.task_start_time) & (times <= pl.task_end_time)
        r[seg] = pl.task_time_map(times[seg] - pl.task_start_time)[0] * scale  # in the file's own time
        meta = {"format": "fluidlab-recording", "version": 1, "trajectory_name": g.trajectory_name,
                "trajectory_sha256": hashlib.sha256(loaded.data).hexdigest(),
                "trajectory_document": json.loads(loaded.data),
                "robot": self.robot_model, "joint_names": list(self.robot.joint_names),
                "controller_joint_names": list(self.controller_joints), "control_rate": self.control_rate,
                "mode": self.mode, "target": target, "speed_scale": scale,
                "mounting": {"task": m.task, "scene_origin": m.scene_origin.tolist(),
                             "flange_to_tool": m.flange_to_tool.tolist()},
                "software_version": __version__,
                "task_start_time": pl.task_start_time, "task_end_time": pl.task_end_time,
                "plan_times": times.tolist(), "plan_traj_times": [None if np.isnan(v) else float(v) for v in r],
                "plan_report": json.loads(json.dumps(pl.report.to_dict(), default=float)),
                "q_start": pl.q_start.tolist()}
        return meta

    def _record(self, stream: Stream, i: int, fk: Robot):
        """Row i of the run buffer (a command that went out, k >= 0 of the plan or -1 of a ramp): record it, and
        with every STATE_EVERY-th the arm states and tool poses."""
        rec, buf = stream.recorder, stream.buf
        stamp = int(buf.stamp[i])
        rec.put("/sim_node/commands", velocity_command(buf.command[i], self.controller_order), stamp)
        stream.recorded += 1
        if (stream.recorded - 1) % STATE_EVERY:
            return  # states and poses at control_rate / STATE_EVERY
        names = list(self.robot.joint_names)
        js = JointState(name=names, position=buf.q[i].tolist(), velocity=buf.v[i].tolist())
        js.header.stamp.sec, js.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        rec.put("/sim_node/twin/joint_states", js, stamp)
        if self.mode != "robot" or not stream.to_robot:
            rec.put("/sim_node/measured_joint_states", js, stamp)
        k = int(buf.k[i])
        if k >= 0:
            pj = JointState(name=names, position=stream.plan.positions[k].tolist())
            pj.header.stamp = js.header.stamp
            rec.put("/sim_node/planned_joint_states", pj, stamp)
            rec.put("/sim_node/planned_tool_pose", pose_msg(stream.planned_tool[k], self.robot.base_frame, stamp), stamp)
        arm_q = buf.q[i] if not stream.to_robot else self._arm_positions()
        if arm_q is not None:
            rec.put("/sim_node/tool_pose", pose_msg(se3_to_pose(fk.frame_placement(arm_q)), self.robot.base_frame,
                                                     stamp), stamp)

    def _send(self, stream: Stream, command: np.ndarray, now: float) -> str:
        """Publish one command from this process (the take-over ramp after the stream process failed), give it
        to the twin and write its row; returns a reason to stop, or ''."""
        msg = velocity_command(command, self.controller_order)
        self.pub_commands.publish(msg)
        if stream.to_robot and self.pub_controller is not None:
            self.pub_controller.publish(msg)
        try:
            reflex = write_row(stream.buf, -1, command, self.twin, now)
        except RuntimeError:  # the buffer is full: the command went out all the same
            reflex = self.twin.command(command, now)
        if reflex is not None:
            self.last_reflex = reflex.message()
            stream.reflex = reflex.message()
            return "the twin arm stopped with a reflex"
        return ""

    def _start_stream_process(self) -> StreamProcess:
        sp = StreamProcess(self._mp, self._stream_config)

        def report():
            if sp.wait_ready(60.0):
                self.get_logger().info(f"command stream process {sp.ready['pid']} ready: {sp.ready['realtime']}")
                if not sp.ready["realtime"].startswith("SCHED_FIFO") and self.realtime_priority > 0:
                    self.get_logger().warn(f"the command stream runs with {sp.ready['realtime']}")
            elif not self._closing.is_set():
                self.get_logger().error("the command stream process did not start")
        threading.Thread(target=report, daemon=True).start()
        return sp

    def _follow(self, stream: Stream, traj):
        """The node's side of a stream: hand the plan to the stream process, then, once a control period,
        read the rows it wrote (record them, feed the fluid twin, mirror the twin arm) and watch it. If the
        process dies, or its heartbeat is older than late_tick_limit (a stall), the node kills it, sends the
        stop ramp itself from the last command, and starts a new stream process."""
        from multiprocessing.connection import wait

        pl, buf, sp = stream.plan, stream.buf, stream.proc
        T = 1.0 / self.control_rate
        n_task0 = int(round(pl.task_start_time * self.control_rate))
        n_task1 = int(round(pl.task_end_time * self.control_rate))
        fluid_every = max(1, int(round(traj.dt * self.control_rate)))
        # the first command's deadline: 50 ms from now, or later if the stream process takes the plan later (a
        # loaded machine: nothing has been sent, so a late start is harmless); it reports the one it chose (T0)
        t0 = time.monotonic() + 0.05

        def start(t0_actual: float):
            start_wall = time.time() + (t0_actual - time.monotonic())  # the same instant on both clocks
            stream.start_ns = int(start_wall * 1e9)
            if stream.recorder is not None:
                stream.metadata.update(start_time=start_wall, start_time_iso=time.strftime(
                    "%Y-%m-%dT%H:%M:%S", time.gmtime(start_wall)) + "Z",
                    publisher_handshake_s=float(buf.floats[HANDSHAKE]))
                stream.recorder.write_metadata(stream.metadata)
        job = {"buffer": buf.spec(), "velocities": pl.velocities, "positions": pl.positions,
               "control_rate": self.control_rate, "controller_order": self.controller_order,
               "to_robot": stream.to_robot, "mode": self.mode, "late_tick_limit": self.late_tick_limit,
               "joint_state_timeout": self.joint_state_timeout, "joint_state_topic": self.joint_state_topic,
               "n_task0": n_task0, "twin": self.twin.snapshot(), "feedback_gain": self.feedback_gain,
               "feedback_max_velocity": self.feedback_max_velocity, "margin": self.margin, "t0": t0,
               # who must hear the plan from its first command: whoever the node's own publishers reach
               "subscribers": {"commands": self.pub_commands.get_subscription_count(),
                               "controller": (self.pub_controller.get_subscription_count()
                                              if self.pub_controller is not None else 0)},
               "handshake_timeout": HANDSHAKE_TIMEOUT}
        sp.jobs.put(job)
        seen = 0
        failure = ""
        started = False
        pickup_limit = time.monotonic() + PLAN_PICKUP_TIMEOUT + HANDSHAKE_TIMEOUT
        try:
            while True:
                died = wait([sp.proc.sentinel], timeout=T)
                if not started:
                    if buf.floats[T0] > 0:  # the stream process took the plan (and set the heartbeat first)
                        started = True
                        start(float(buf.floats[T0]))
                    elif died:
                        pass  # handled below
                    elif time.monotonic() > pickup_limit:
                        failure = (f"the command stream process did not take the plan within "
                                   f"{PLAN_PICKUP_TIMEOUT + HANDSHAKE_TIMEOUT:g} s (its handshake included); "
                                   f"at most one zero command was sent")
                        break
                    else:
                        continue
                seen = self._drain(stream, seen, n_task0, n_task1, fluid_every)
                try:
                    msg = sp.results.get_nowait()
                except (queue.Empty, OSError, ValueError, EOFError):
                    msg = None
                if msg is not None and msg.get("kind") == "done":
                    seen = self._drain(stream, seen, n_task0, n_task1, fluid_every)
                    self.twin.restore(msg["twin"])
                    stream.outcome = msg["outcome"]
                    if msg["reflex"] is not None:
                        stream.reflex = self.last_reflex = msg["reflex"].message()
                    break
                stall = time.monotonic() - float(buf.floats[HEARTBEAT])
                stalled = not buf.ints[DONE] and stall > self.late_tick_limit + T
                # A process found dead once its heartbeat is stale died (after the wait above, while this thread
                # drained); report that, not a stall (a killed one was once reported as stalled, on a machine
                # loaded by two CPU-bound jobs beside the tests).
                if died or (stalled and wait([sp.proc.sentinel], timeout=0)):
                    sp.proc.join(1.0)  # the sentinel is ready before the exit code is collected
                    failure = f"the command stream process died (exit code {sp.proc.exitcode})"
                    break
                if stalled:
                    failure = (f"the command stream process stalled: no command for {stall * 1e3:.0f} ms "
                               f"(late_tick_limit {self.late_tick_limit * 1e3:g} ms)")
                    break
            if failure:
                if not started:
                    start(time.monotonic())
                self._take_over(stream, failure, n_task0, n_task1, fluid_every, seen)
            if stream.outcome != "done":
                self.get_logger().warn(f"the stream stopped: {stream.outcome}")
        except Exception as err:  # noqa: BLE001 - the goal must learn why and the arm must get a stop
            stream.outcome = f"internal error following the command stream: {err!r}"
            self.get_logger().error(stream.outcome)
            sp.kill()
            self._stream_proc = self._start_stream_process()
            try:
                self._send(stream, np.zeros(self.limits.dof), time.monotonic())
            except Exception:  # noqa: BLE001
                pass
        finally:
            stream.late_ticks, stream.max_late = int(buf.ints[LATE_TICKS]), float(buf.floats[MAX_LATE])
            stream.phase = "done"
            stream.close_buffer()
            stream.done.set()

    def _take_over(self, stream: Stream, failure: str, n_task0: int, n_task1: int, fluid_every: int, seen: int):
        """The stream process failed mid-stream: kill it (a stalled one must never resume sending), ramp the
        arm to rest from this process, and start a new stream process for the next goal."""
        self.get_logger().error(f"{failure}; the node sends the stop ramp")
        stream.proc.kill()
        self._stream_proc = self._start_stream_process()
        buf = stream.buf
        n = buf.count
        self._drain(stream, seen, n_task0, n_task1, fluid_every)
        last = buf.command[n - 1].copy() if n else np.zeros(self.limits.dof)
        prev = buf.command[n - 2].copy() if n > 1 else np.zeros(self.limits.dof)
        if n:  # the arm held the last command since it went out; the twin goes on from there
            self.twin.restore(row_state(buf, n - 1))
        stream.outcome = failure
        stream.phase = "stopping"
        T = 1.0 / self.control_rate
        clock = Schedule(T, time.monotonic())
        for command in stop_ramp(last, prev, self.control_rate, self.limits, self.margin):
            now, _ = clock.wait()
            if self._send(stream, command, now):
                break
        self._drain(stream, n, n_task0, n_task1, fluid_every)

    def _drain(self, stream: Stream, seen: int, n_task0: int, n_task1: int, fluid_every: int) -> int:
        """Read the rows written since `seen`: record them, send the fluid twin the tool poses it steps to,
        mirror the twin arm; returns the new count."""
        buf = stream.buf
        n = buf.count
        if n <= seen:
            return seen
        fk = stream.fk
        for i in range(seen, n):
            if stream.recorder is not None:
                self._record(stream, i, fk)
            k = int(buf.k[i])
            if self.fluid_twin and n_task0 <= k < n_task1 and (k - n_task0) % fluid_every == 0:
                q = buf.q[i] if not stream.to_robot else self._arm_positions()
                if q is not None and self._fluid is not None:
                    self._fluid[3].put({"kind": "pose", "pose": se3_to_pose(fk.frame_placement(q)).tolist(),
                                        "last": k + fluid_every >= n_task1, "epoch": self._fluid_epoch.value,
                                        "stamp": int(buf.stamp[i])})
        if not buf.ints[DONE]:
            self.twin.restore(row_state(buf, n - 1))
        plan_rows = np.nonzero(buf.k[seen:n] >= 0)[0]
        if len(plan_rows):
            i = seen + int(plan_rows[-1])
            stream.mirror = (int(buf.k[i]), buf.q[i].copy())
        stream.index = int(buf.ints[INDEX])
        stream.phase = buf.phase
        stream.late_ticks, stream.max_late = int(buf.ints[LATE_TICKS]), float(buf.floats[MAX_LATE])
        return n

    # --- the twin's fluid --------------------------------------------------------------------------------
    def _fluid_reset(self, traj, stream: Stream):
        """Start the task's fluid worker if needed and reset it for this execution: a new epoch, which the
        stream takes before the reset goes out (its clouds are recorded by epoch)."""
        size = traj.metadata.get("size", "small") if isinstance(traj.metadata, dict) else "small"
        with self._fluid_lock:
            if self._fluid is not None and (self._fluid[0], self._fluid[1]) != (traj.task, size):
                self._fluid_quit()
            if self._fluid is None or not self._fluid[2].is_alive():
                inbox, outbox = self._mp.Queue(), self._mp.Queue()
                inbox.cancel_join_thread()  # never wait at exit to hand poses to a worker that is gone
                self._fluid_stop, self._fluid_epoch = self._mp.Event(), self._mp.Value("i", 0)
                proc = self._mp.Process(target=workers.fluid_worker, name="fluidlab-twin-fluid", daemon=True,
                                        args=(traj.task, size, inbox, outbox, self.arch, self.precision),
                                        kwargs={"stop": self._fluid_stop, "epoch": self._fluid_epoch})
                proc.start()
                self._fluid = (traj.task, size, proc, inbox, outbox)
                self.get_logger().info(f"started the twin's fluid ({traj.task}, {size}) in process {proc.pid}")
            with self._fluid_epoch.get_lock():
                self._fluid_epoch.value += 1
                stream.fluid_epoch = self._fluid_epoch.value
            self._fluid[3].put({"kind": "reset", "tool_position": traj.initial_pose[:3].tolist(),
                                "epoch": stream.fluid_epoch})

    def _fluid_quit(self):
        if self._fluid is None:
            return
        _, _, proc, inbox, _ = self._fluid
        self._fluid_stop.set()
        proc.join(2.0)
        if proc.is_alive():
            proc.terminate()
            proc.join(2.0)
        self._fluid = None

    def _particle_loop(self):
        while rclpy.ok() and not self._closing.is_set():
            fluid = self._fluid
            if fluid is None:
                time.sleep(0.2)
                continue
            try:
                msg = fluid[4].get(timeout=0.2)
            except (queue.Empty, OSError, ValueError):
                continue
            if msg["kind"] == "compiling":
                self.get_logger().info("the twin's fluid is compiling its kernels (about a minute on two cores the "
                                       "first time; Taichi caches them)")
            if msg["kind"] == "ready":
                self._scene = msg
                self._build_markers(msg)
                self.get_logger().info(f"the twin's fluid is ready ({msg['n']} particles; first step "
                                       f"{msg.get('compile_seconds', 0.0):.1f} s, compilation included)")
            if msg["kind"] == "particles":
                colors = msg.get("colors", self._scene["colors"] if self._scene is not None else None)
                self.pub_particles.publish(point_cloud(msg["positions"], self.robot.base_frame,
                                                       self.get_clock().now().to_msg(), colors))
                rec = self._recording
                if rec is not None and rec.recorder is not None and msg.get("epoch") == rec.fluid_epoch:
                    rec.fluid_pending.append(msg)
                    if rec.start_ns:  # the stream has started and written the metadata: record what came
                        for m in rec.fluid_pending:
                            self._record_cloud(rec, m)
                        rec.fluid_pending.clear()
            elif msg["kind"] == "error":
                self.get_logger().error(f"the twin's fluid failed: {msg['message']}")

    def _record_cloud(self, rec: Stream, msg: dict):
        """Record a particle cloud of the execution's fluid, stamped with the time the arm was at the pose the
        fluid was stepped to (the initial state: the stream's start), however late the worker computed it."""
        from fluidlab_ros.recording import downsample

        stamp = int(msg.get("stamp") or rec.start_ns)
        cloud = point_cloud(downsample(msg["positions"]), self.robot.base_frame, None)
        cloud.header.stamp.sec, cloud.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        rec.recorder.put("/sim_node/particles", cloud, stamp)
        rec.fluid_clouds += 1
        if msg.get("final"):
            rec.fluid_final.set()

    # --- state publishing ----------------------------------------------------------------------------------
    def _publish_state(self):
        now = time.monotonic()
        self.twin.advance(now)
        q, v = self.twin.state()
        stamp = self.get_clock().now().to_msg()
        js = JointState(name=list(self.robot.joint_names), position=q.tolist(), velocity=v.tolist())
        js.header.stamp = stamp
        self.pub_twin_js.publish(js)
        arm_q = self._arm_positions()
        if arm_q is None:
            return
        # the tool frame of the task last executed (the flange before any); this thread's own Robot
        tool = self._state_robot or self.robot
        pose = se3_to_pose(tool.frame_placement(arm_q))
        ps = pose_msg(pose, self.robot.base_frame, 0)
        ps.header.stamp = stamp
        self.pub_tool.publish(ps)
        self._state_ticks += 1
        if self._markers is not None and self._state_ticks % 5 == 0 and not np.allclose(pose, self._marker_pose):
            self._marker_pose = pose
            for m in self._markers.markers:
                if m.id >= 100:  # the tool moves with the arm
                    m.pose = ps.pose
                    m.header.stamp = stamp
            self.pub_markers.publish(self._markers)

    def _build_markers(self, scene: dict):
        """Containers and other statics (grey) and the tool (its colour, at the arm's tool pose) as sphere
        lists of their point samples, in the base frame; ids: statics 0.., tools 100... Built once per scene;
        the state timer then only moves the tool markers."""
        stamp = self.get_clock().now().to_msg()
        out = MarkerArray()
        d = scene["dx"]
        for i, (name, pts) in enumerate(scene["statics"]):
            out.markers.append(marker(i, name, pts[:: max(1, len(pts) // 3000)], (0.72, 0.72, 0.74, 0.35), d,
                                      self.robot.base_frame, stamp))
        for i, (name, pts, color) in enumerate(scene["tools"]):
            out.markers.append(marker(100 + i, name, pts[:: max(1, len(pts) // 3000)], (*color, 1.0), 0.5 * d,
                                      self.robot.base_frame, stamp))
        self._markers, self._marker_pose = out, np.zeros(7)  # the next state tick places the tool and publishes

    def _publish_diagnostics(self):
        stream = self.stream
        reflex = self.twin.reflex
        level = DiagnosticStatus.ERROR if reflex else DiagnosticStatus.OK
        if level == DiagnosticStatus.OK and self.mode == "robot" and self._joint_state_age() > self.joint_state_timeout:
            level = DiagnosticStatus.WARN
        values = {"mode": self.mode, "armed": str(self.armed), "streaming": str(stream is not None),
                  "twin_reflex": reflex.message() if reflex else "", "last_reflex": self.last_reflex,
                  "late_ticks": str(stream.late_ticks if stream else 0),
                  "joint_state_age": f"{self._joint_state_age():.3f}" if self.mode == "robot" else "n/a"}
        st = DiagnosticStatus(level=level, name="sim_node", hardware_id=self.robot_model,
                              message="reflex" if reflex else "ok",
                              values=[KeyValue(key=k, value=v) for k, v in values.items()])
        arr = DiagnosticArray(status=[st])
        arr.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(arr)

    def shutdown(self, timeout: float = 5.0):
        """Ramp any motion to rest, end the workers."""
        stream = self.stream
        if stream is not None:
            stream.request_stop("node shutting down")
            stream.done.wait(timeout)
        self._stream_proc.close()
        with self._fluid_lock:
            self._fluid_quit()
        self._closing.set()
        self._particle_thread.join(2.0)


def main(args=None):
    # The follower thread (and a take-over stop ramp) must get the GIL back within a fraction of a control
    # period; CPython's default switch interval (5 ms) let executor threads hold it for up to 2.5 periods.
    sys.setswitchinterval(2e-4)
    from rclpy.utilities import remove_ros_args

    argv = sys.argv if args is None else ["sim_node", *args]
    own = remove_ros_args(argv)[1:]  # what is left outside --ros-args ... (parameters go inside: -p name:=value)
    if own and own[0] in ("-h", "--help"):
        print(__doc__)
        print(parameters_help())
        return 0
    if own:
        print(f"sim_node: unknown arguments {own}; set parameters with --ros-args -p name:=value (sim_node --help)",
              file=sys.stderr)
        return 2
    udp_only()  # the stream process's transport, so that readers get its commands and the take-over in order
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        node = SimNode()
    except (ValueError, KeyError, FileNotFoundError) as err:
        print(f"sim_node: {err}", flush=True)
        rclpy.shutdown()
        return 2
    executor = MultiThreadedExecutor(num_threads=4)
    executor.add_node(node)
    spin = threading.Thread(target=executor.spin, daemon=True)
    spin.start()
    try:
        stop.wait()
        node.get_logger().info("shutting down: ramping any motion to rest")
        node.shutdown()
    finally:
        # every thread that calls into rclpy ends before the node and the context go: a CI run once ended in
        # "terminate called without an active exception" (SIGABRT) at this point, under load
        executor.shutdown(timeout_sec=5.0)
        spin.join(5.0)
        node.destroy_node()
        rclpy.shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
