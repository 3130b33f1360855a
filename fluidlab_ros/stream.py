"""The command stream in a process of its own, and what the node keeps of it.

Why a process. A thread of sim_node's process needs the GIL at every control tick, and the node's other threads
(the executor's callbacks, the recorder, the fluid twin's particle clouds) hold it at normal priority: beside a
Taichi compile, 2,289 of 2,699 ticks of a thread came late, up to 237 ms. A late tick is not harmless: a
JointGroupVelocityController holds the last velocity until the next command, so the arm drifts by
(stall x velocity). The stream process holds nothing but the plan, its publishers, the twin arm (a few
microseconds a tick), in robot mode a joint-state subscription, and a shared buffer; no other code of the
node runs in it, so nothing else can take its GIL. It asks for SCHED_FIFO where the system allows it.

    sim_node process                                       stream process (started with the node, kept)
    ----------------                                       ---------------------------------------------
    StreamProcess.submit(job) ------- queue -------------> a plan: velocities (K, dof), positions (K+1, dof)
    RunBuffer (a file in /dev/shm) <-- every command ----- per command: time, index, command, twin q, v, a
       stop flag + reason ------------------------------>  read at every tick (cancel, ~/stop, disarm)
       heartbeat <---------------------------------------- written at every tick
                                                           before a plan's first command: the handshake
                                                           (every subscriber of the node's publishers has
                                                           matched this process's, and acknowledged a zero)
    Follower (sim_node): reads the buffer at the control rate, records, feeds the fluid twin, mirrors the
    twin arm; watchdog: the process died (its sentinel) or its heartbeat is older than late_tick_limit ->
    kill it, send the stop ramp from the node's own publishers, start a new stream process.

Units: rad, rad/s; times in s on CLOCK_MONOTONIC (the same clock in every process on Linux) and ns since the
epoch for stamps.
"""
from __future__ import annotations

import gc
import os
import signal
import tempfile
import time

import numpy as np

# header slots of a RunBuffer (int64)
COUNT, STOP, INDEX, LATE_TICKS, PHASE, DONE = range(6)
# float64 slots
HEARTBEAT, MAX_LATE, T0, HANDSHAKE = range(4)
PHASES = ("approach", "task", "stopping", "done")
REASON_BYTES = 512


class RunBuffer:
    """One execution's shared record, a memory-mapped file (in /dev/shm where it exists) that the node creates
    and removes and the stream process writes (one writer). A row is written before COUNT moves past it, so a
    reader that reads COUNT first reads whole rows on x86-64, whose stores become visible in program order; a
    weakly ordered CPU (ARM64) gives no such promise without fences, which numpy does not emit: there the
    follower may see a row a moment early (its recording and mirror, not the stream, would be off)."""

    def __init__(self, rows: int, dof: int, path: str | None = None):
        self.rows, self.dof = int(rows), int(dof)
        self.owner = path is None
        if path is None:
            folder = "/dev/shm" if os.path.isdir("/dev/shm") else None
            fd, path = tempfile.mkstemp(prefix="fluidlab_stream_", suffix=".buf", dir=folder)
            os.close(fd)
        self.path = path
        n, d = self.rows, self.dof
        sizes = [("ints", np.int64, (16,)), ("floats", np.float64, (16,)), ("reason", np.uint8, (REASON_BYTES,)),
                 ("stamp", np.int64, (n,)), ("k", np.int64, (n,)), ("tick_time", np.float64, (n,)),
                 ("command", np.float64, (n, d)), ("q", np.float64, (n, d)), ("v", np.float64, (n, d)),
                 ("a", np.float64, (n, d))]
        total = sum(np.dtype(t).itemsize * int(np.prod(s)) for _, t, s in sizes)
        mode = "w+" if self.owner else "r+"
        self._mm = np.memmap(path, dtype=np.uint8, mode=mode, shape=(total,))
        off = 0
        for name, t, s in sizes:
            nbytes = np.dtype(t).itemsize * int(np.prod(s))
            setattr(self, name, self._mm[off:off + nbytes].view(t).reshape(s))
            off += nbytes

    def spec(self) -> dict:
        return {"rows": self.rows, "dof": self.dof, "path": self.path}

    @classmethod
    def attach(cls, spec: dict) -> "RunBuffer":
        return cls(spec["rows"], spec["dof"], spec["path"])

    # --- written by the node -------------------------------------------------------------------------
    def request_stop(self, reason: str):
        """Ask for a ramp to rest; the first reason given is kept."""
        if self.ints[STOP]:
            return
        data = reason.encode()[:REASON_BYTES - 1]
        self.reason[:len(data)] = np.frombuffer(data, np.uint8)
        self.reason[len(data)] = 0
        self.ints[STOP] = 1

    def stop_reason(self) -> str:
        if not self.ints[STOP]:
            return ""
        raw = bytes(self.reason)
        return raw[:raw.index(0)].decode(errors="replace") if 0 in raw else raw.decode(errors="replace")

    # --- read by the node ---------------------------------------------------------------------------
    @property
    def count(self) -> int:
        return int(self.ints[COUNT])

    @property
    def phase(self) -> str:
        return PHASES[int(self.ints[PHASE])]

    def close(self):
        del self.ints, self.floats, self.reason, self.stamp, self.k, self.tick_time, self.command, self.q, self.v
        del self.a
        try:
            self._mm._mmap.close()
        except (BufferError, AttributeError):
            pass  # a view is still alive somewhere; the mapping goes with it
        if self.owner:
            try:
                os.unlink(self.path)
            except FileNotFoundError:
                pass


def write_row(buf: RunBuffer, k: int, command: np.ndarray, twin, now: float):
    """Command k (-1: a ramp command) went out at `now`: the twin arm takes it, and the row records both.
    Returns the twin's reflex, if one happened."""
    i = int(buf.ints[COUNT])
    if i >= buf.rows:
        raise RuntimeError(f"the run buffer is full ({buf.rows} rows)")
    reflex = twin.command(command, now)
    buf.stamp[i] = time.time_ns()
    buf.k[i] = k
    buf.command[i] = command
    buf.q[i], buf.v[i], buf.a[i], buf.tick_time[i] = twin.q, twin.v, twin.a, twin.tick_time
    buf.ints[COUNT] = i + 1
    buf.floats[HEARTBEAT] = time.monotonic()
    return reflex


def row_state(buf: RunBuffer, i: int) -> dict:
    """The twin arm after row i, as TwinArm.snapshot() gives it (the row's command held)."""
    return {"q": buf.q[i].copy(), "v": buf.v[i].copy(), "a": buf.a[i].copy(), "held": buf.command[i].copy(),
            "tick_time": float(buf.tick_time[i]), "reflex": None}


def rows_for(n_commands: int, control_rate: float) -> int:
    """Rows a run may write: the plan's commands, the feedback's ramp-out or a stop ramp (each well under 2 s
    of commands at the arm's acceleration budget), with room to spare."""
    return int(n_commands + 3 * control_rate + 16)


# --- the stream process ----------------------------------------------------------------------------------
def udp_only():
    """Fast DDS over UDP only for this process, unless the user chose its transports (before rclpy.init). Both the
    stream process and sim_node's process call it. Shared memory writes into each reader's port under a lock, and
    a stream process stopped (SIGSTOP, a stall) while it held one delayed the node's take-over ramp to the same
    reader by 2 s. And with the node alone on shared memory, a loaded reader handled the take-over ramp, its final
    zero included, before the stream's last UDP datagrams, then held a stale 0.16 rad/s command; on one transport
    a reader gets both through one socket in send order (tests/ros/test_stream_faults.py)."""
    os.environ.setdefault("FASTDDS_BUILTIN_TRANSPORTS", "UDPv4")


ACK_POLL = 0.05  # s: the handshake looks at the stop request this often while it waits for acknowledgements


def handshake(publishers: list, send_zero, timeout: float, stopped=None) -> str:
    """Make sure every subscriber hears a plan from its first command: '' once it holds, or why not.

    publishers: (publisher, topic, expected) for each topic the plan goes to, where expected is how many
    subscriptions the node's own, long-standing publisher on that topic has matched. This process's publishers
    are new DDS writers whenever the process is new (at start, and after a take-over), and a subscriber that has
    not matched one yet drops what it sends: a controller would see the stream start at its second or third
    command, a velocity step outside the arm's acceleration limit (seen under load in CI, the first command
    after a take-over: 0.028 rad/s from rest, 28 rad/s^2 against 10). So: wait until each publisher has
    matched `expected` subscriptions (the writer's side), then send one zero command (the arm is at rest
    before any plan, so a zero changes nothing) and wait until every matched subscriber acknowledged it (the
    reader's side: a subscriber acknowledges only a writer it has matched). Then the plan starts. Typically
    5 ms when nothing is new, up to seconds (DDS discovery) after a new process or subscriber.

    stopped(): the stop request's reason, or '' (polled every few ms, and every ACK_POLL s while waiting for the
    acknowledgements): a stop (a cancel, ~/stop, a disarm) during the wait ends it at once with that reason, having
    sent nothing, or the zero alone."""
    from rclpy.duration import Duration

    stopped = stopped or (lambda: "")
    deadline = time.monotonic() + timeout
    for pub, topic, expected in publishers:
        while pub.get_subscription_count() < expected:
            reason = stopped()
            if reason:
                return reason
            if time.monotonic() > deadline:
                return (f"the command stream's publisher on {topic} matched {pub.get_subscription_count()} of the "
                        f"{expected} subscribers the node's publisher has within {timeout:g} s; nothing was sent")
            time.sleep(0.002)
    reason = stopped()
    if reason:
        return reason
    send_zero()
    for pub, topic, _ in publishers:
        while True:
            left = deadline - time.monotonic()
            if left <= 0.0:
                return (f"the subscribers of {topic} did not acknowledge the stream's opening zero command within "
                        f"{timeout:g} s; nothing else was sent (the arm stays at rest)")
            if pub.wait_for_all_acked(Duration(nanoseconds=int(min(left, ACK_POLL) * 1e9))):
                break
            reason = stopped()
            if reason:
                return reason
    return ""


def stream_process(config: dict, jobs, results):
    """Entry point of the stream process (multiprocessing, spawn). config: robot_model, mode, node_name,
    commands_topic, controller_topic (or ''), joint_state_topic, joint_state_qos, realtime_priority."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole process group: the node ramps
    udp_only()
    rt = _realtime(int(config["realtime_priority"]))
    import multiprocessing as mp
    import queue
    import threading

    import rclpy
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    from fluidlab_ros.messages import velocity_command

    from fluidlab_ros.limits import JointLimits
    # what run() uses, imported now: a first plan must not wait for imports (hundreds of ms) past its deadline
    import fluidlab_ros.pipeline  # noqa: F401
    import fluidlab_ros.schedule  # noqa: F401
    import fluidlab_ros.stopping  # noqa: F401
    import fluidlab_ros.twin  # noqa: F401

    limits = JointLimits.load(config["robot_model"])
    rclpy.init(args=[], signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(config["node_name"] + "_stream")
    pub = node.create_publisher(Float64MultiArray, config["commands_topic"], 1000)
    pub_ctl = (node.create_publisher(Float64MultiArray, config["controller_topic"], 1000)
               if config["controller_topic"] else None)
    measured = {"q": None, "time": -np.inf}
    spin = None
    if config["mode"] == "robot":
        names = list(limits.joint_names)

        def on_js(msg):
            try:
                idx = [list(msg.name).index(j) for j in names]
            except ValueError:
                return
            measured["q"] = np.array([msg.position[i] for i in idx])
            measured["time"] = time.monotonic()

        qos = qos_profile_sensor_data if config["joint_state_qos"] == "best_effort" else QoSProfile(
            depth=10, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
        node.create_subscription(JointState, config["joint_state_topic"], on_js, qos)
        from rclpy.executors import SingleThreadedExecutor
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        spin = threading.Thread(target=executor.spin, daemon=True)
        spin.start()

    def publish(command: np.ndarray, order: np.ndarray, to_robot: bool):
        msg = velocity_command(command, order)
        pub.publish(msg)
        if to_robot and pub_ctl is not None:
            pub_ctl.publish(msg)

    def shake(job: dict, stopped) -> str:
        pubs = [(pub, config["commands_topic"], int(job["subscribers"]["commands"]))]
        if job["to_robot"] and pub_ctl is not None:
            pubs.append((pub_ctl, config["controller_topic"], int(job["subscribers"]["controller"])))
        return handshake(pubs, lambda: publish(np.zeros(limits.dof), np.asarray(job["controller_order"]),
                                               bool(job["to_robot"])), float(job["handshake_timeout"]), stopped)

    results.put({"kind": "ready", "pid": os.getpid(), "realtime": rt})
    parent = mp.parent_process()
    try:
        while True:
            try:
                job = jobs.get(timeout=0.5)
            except queue.Empty:
                if parent is not None and not parent.is_alive():
                    break  # the node is gone
                continue
            if job is None:
                break
            try:
                out = run(job, limits, publish, measured, shake)
            except Exception as err:  # noqa: BLE001 - the node learns why; the process serves the next plan
                out = {"kind": "done", "outcome": f"internal error in the command stream: {err!r}", "reflex": None}
            results.put(out)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def _realtime(priority: int) -> str:
    """Ask for SCHED_FIFO for this process (its threads inherit it); returns what happened, for the log."""
    if priority <= 0:
        return "normal scheduling (realtime_priority 0)"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return f"SCHED_FIFO priority {priority}"
    except (OSError, AttributeError) as err:
        return (f"normal scheduling: SCHED_FIFO {priority} was refused ({err}); give the user rtprio (limits.conf) "
                f"or the interpreter CAP_SYS_NICE for a stream that other processes cannot delay")


def run(job: dict, limits, publish, measured: dict, shake) -> dict:
    """Stream one verified plan: after the handshake (shake(job, stopped), see handshake()), command k at t0 + k T
    (Schedule), each checked by the twin arm; a stop request, a tick later than late_tick_limit, lost joint
    states (robot mode) or a reflex end it, with a jerk-limited ramp to rest unless the (twin) arm already
    stopped."""
    from fluidlab_ros.pipeline import command_budgets
    from fluidlab_ros.schedule import Schedule
    from fluidlab_ros.stopping import stop_ramp
    from fluidlab_ros.twin import TwinArm

    buf = RunBuffer.attach(job["buffer"])
    cmds, positions = job["velocities"], job["positions"]
    rate = float(job["control_rate"])
    T = 1.0 / rate
    order = np.asarray(job["controller_order"])
    to_robot, robot_mode = bool(job["to_robot"]), job["mode"] == "robot"
    late_limit, js_timeout = float(job["late_tick_limit"]), float(job["joint_state_timeout"])
    n_task0 = int(job["n_task0"])
    twin = TwinArm(limits, job["twin"]["q"])
    twin.restore(job["twin"])
    gain, vmax = float(job["feedback_gain"]), float(job["feedback_max_velocity"])
    a_plan, _ = command_budgets(limits, rate, float(job["margin"]))
    delta = a_plan * T / 9.0
    corr = np.zeros(limits.dof)

    def arm_q():
        if robot_mode and to_robot:
            return measured["q"]
        return twin.q

    def send(command: np.ndarray, now: float, k: int):
        publish(command, order, to_robot)
        return write_row(buf, k, command, twin, now)

    def corrected(k: int) -> np.ndarray:
        # position feedback on the verified profile (sim_node's docs): a late command is held by the arm, which
        # then drifts by (lateness x velocity); the correction follows gain x (q_plan - q_arm) in steps of at most
        # a ninth of the planning acceleration budget, within feedback_max_velocity
        nonlocal corr
        if gain > 0:
            q = arm_q()
            if q is not None:
                target = np.clip(gain * (positions[k] - q), -vmax, vmax)
                corr = corr + np.clip(target - corr, -delta, delta)
        return cmds[k] + corr

    t_shake = time.monotonic()
    problem = shake(job, buf.stop_reason)  # a stop while it waits ends the plan before its first command
    buf.floats[HANDSHAKE] = time.monotonic() - t_shake
    if problem:
        buf.floats[T0] = time.monotonic()
        buf.ints[PHASE], buf.ints[DONE] = 3, 1
        buf.close()
        return {"kind": "done", "outcome": problem, "reflex": None, "twin": twin.snapshot()}
    gc_was_enabled = gc.isenabled()
    gc.disable()  # the cyclic collector stops the thread for tens of ms over a large heap
    # the node's deadline for command 0, or 5 ms from now if the plan came later than that (nothing has been sent:
    # a late start is harmless, where a first tick counted late would stop the stream before it began)
    t0 = max(float(job["t0"]), time.monotonic() + 0.005)
    clock = Schedule(T, t0)
    buf.floats[HEARTBEAT] = t0  # the heartbeat stays at t0 until the first tick
    buf.floats[T0] = t0  # last: the node starts following when it sees T0
    last, prev = np.zeros(limits.dof), np.zeros(limits.dof)
    reason, reflex = "", None
    try:
        for k in range(len(cmds)):
            now, late = clock.wait()
            buf.floats[HEARTBEAT] = now
            buf.ints[LATE_TICKS], buf.floats[MAX_LATE] = clock.late_ticks, clock.max_late
            late_reason = (f"control tick {k} was {late * 1e3:.1f} ms late (late_tick_limit {late_limit * 1e3:g} ms)"
                           if late > late_limit else "")
            if buf.ints[STOP]:  # asked for first: a stall while the request arrived does not hide it
                reason = buf.stop_reason() + (f"; {late_reason}" if late_reason else "")
                break
            if late_reason:
                reason = late_reason
                break
            if robot_mode and to_robot:
                age = now - measured["time"]
                if age > js_timeout:
                    reason = (f"joint states on {job['joint_state_topic']} stopped for {age * 1e3:.0f} ms "
                              f"(joint_state_timeout {js_timeout * 1e3:g} ms)")
                    break
            buf.ints[PHASE] = 0 if k < n_task0 else 1
            command = corrected(k)
            reflex = send(command, now, k)
            prev, last = last, command
            buf.ints[INDEX] = k + 1
            if reflex is not None:
                reason = "the twin arm stopped with a reflex"
                break
        else:
            while np.any(corr):  # ramp the correction out: the stream ends with an exact zero
                corr = corr - np.clip(corr, -delta, delta)
                now, _ = clock.wait()
                reflex = send(corr.copy(), now, -1)
                if reflex is not None:
                    break
            reason = "done" if reflex is None else "the twin arm stopped with a reflex"
        if reason != "done":
            buf.ints[PHASE] = 2
            if reflex is None:  # (after a reflex the arm already stopped; nothing more is accepted)
                # the ramp keeps the never-bunch schedule, starting one period after the last command
                for command in stop_ramp(last, prev, rate, limits, float(job["margin"])):
                    now, _ = clock.wait()
                    reflex = send(command, now, -1)
                    if reflex is not None:
                        break
    except Exception as err:  # noqa: BLE001 - whatever happens, the arm is told to stop and the node learns why
        reason = f"internal error in the command stream: {err!r}"
        try:
            publish(np.zeros(limits.dof), order, to_robot)
        except Exception:  # noqa: BLE001
            pass
    finally:
        if gc_was_enabled:
            gc.enable()
    buf.ints[LATE_TICKS], buf.floats[MAX_LATE] = clock.late_ticks, clock.max_late
    buf.ints[PHASE] = 3
    buf.ints[DONE] = 1
    out = {"kind": "done", "outcome": reason, "reflex": reflex, "twin": twin.snapshot()}
    buf.close()
    return out


# --- the node's side ---------------------------------------------------------------------------------------
class StreamProcess:
    """The node's handle on its stream process: start, hand over a plan, notice its death, replace it."""

    def __init__(self, ctx, config: dict):
        self.ctx, self.config = ctx, config
        self.jobs = ctx.Queue()
        self.results = ctx.Queue()
        self.jobs.cancel_join_thread()
        self.proc = ctx.Process(target=stream_process, name="fluidlab-command-stream", daemon=True,
                                args=(config, self.jobs, self.results))
        self.proc.start()
        self.ready: dict | None = None

    def wait_ready(self, timeout: float) -> bool:
        """Wait for the process's publishers (True), or until it died or the timeout passed (False)."""
        import queue

        deadline = time.monotonic() + timeout
        while self.ready is None:
            if not self.proc.is_alive():
                return False
            try:
                msg = self.results.get(timeout=max(0.0, min(0.2, deadline - time.monotonic())))
            except queue.Empty:
                if time.monotonic() >= deadline:
                    return False
                continue
            if msg.get("kind") == "ready":
                self.ready = msg
        return True

    def alive(self) -> bool:
        return self.proc.is_alive()

    def kill(self):
        if self.proc.is_alive():
            try:
                os.kill(self.proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        self.proc.join(2.0)

    def close(self, timeout: float = 2.0):
        if self.proc.is_alive():
            self.jobs.put(None)
            self.proc.join(timeout)
        if self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(timeout)
