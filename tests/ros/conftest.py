"""Shared set-up of the ROS tests: an isolated graph, nodes started through their console scripts as separate
processes, and an rclpy client in the test process.

Isolation: every test module gets its own ROS_DOMAIN_ID (from the process id, so parallel pytest workers
differ) and ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST (DDS stays on loopback). Nodes are stopped with SIGINT
(SIGKILL would leave /dev/shm/fastrtps_* files behind) and killed only if they do not end in 15 s.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

rclpy = pytest.importorskip("rclpy", reason="ROS 2 (ros-jazzy-rclpy, requirements-ros.txt) is not installed")
pytest.importorskip("fluidlab_msgs", reason="fluidlab_msgs is not built (pip install ./fluidlab_msgs_py)")

from rclpy.action import ActionClient  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent


def console_script(name: str) -> str:
    path = BIN / name
    if not path.exists():
        pytest.fail(f"console script {name!r} is not installed next to {sys.executable}; run the README's install "
                    f"command (pip install .)")
    return str(path)


@pytest.fixture(scope="module")
def ros_env():
    domain = 100 + (os.getpid() * 7 + hash(time.time())) % 100
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               RMW_IMPLEMENTATION="rmw_fastrtps_cpp", PYTHONUNBUFFERED="1", FLUIDLAB_CPU_THREADS="1")
    saved = {k: os.environ.get(k) for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "RMW_IMPLEMENTATION")}
    os.environ.update({k: env[k] for k in saved})
    yield env
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


class Proc:
    """A child process with its output in a log file (read on failure)."""

    def __init__(self, args, env, log: Path):
        self.log = log
        self.f = open(log, "w")
        self.p = subprocess.Popen(args, env=env, stdout=self.f, stderr=subprocess.STDOUT, cwd=str(ROOT))

    def text(self) -> str:
        if not self.f.closed:
            self.f.flush()
        return self.log.read_text()

    def stop(self, timeout: float = 15.0) -> int:
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGINT)
            try:
                self.p.wait(timeout)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait()
        self.f.close()
        return self.p.returncode

    def last_json(self) -> dict:
        lines = [ln for ln in self.text().splitlines() if ln.startswith("{")]
        return json.loads(lines[-1])


# CI shares two cores with Taichi compiles in the other test worker. When the stream was a thread of the node, a
# stall longer than the node's default late_tick_limit (20 ms, meant for a real-time machine) happened there now
# and then, up to 1.0 s (a stop test once ended on "tick 586 was 1004 ms late" instead of its ~/stop). The stream
# now has its own process, but CI may not grant it real-time priority: the tests allow 5 s, so only what a test
# asks for stops a stream; the twin still judges every command that goes out, and the streaming test asserts
# that no tick came 50 ms late. tests/ros/test_stream_faults.py sets its own limit to test the stall watchdog.
LATE_TICK_LIMIT = "late_tick_limit:=5.0"


def max_late(execute_message: str) -> float:
    """The largest lateness of a control tick (s) that a successful Execute result reports."""
    found = re.search(r"late ticks \(max ([0-9.e+-]+) ms\)", execute_message)
    assert found, execute_message
    return float(found.group(1)) * 1e-3


def start_node(env, tmp_path: Path, *params: str, name: str = "sim_node") -> Proc:
    args = [console_script("sim_node"), "--ros-args", "-p", LATE_TICK_LIMIT, "-p",
            f"recording_folder:={tmp_path / 'recordings'}"]
    for p in params:
        args += ["-p", p]
    return Proc(args, env, tmp_path / f"{name}.log")


def start_monitor(env, tmp_path: Path, topic: str, name: str = "monitor") -> tuple[Proc, Path]:
    out = tmp_path / f"{name}.npz"
    ready = tmp_path / f"{name}.ready"
    proc = Proc([console_script("command_monitor"), "--topic", topic, "--out", str(out), "--ready-file", str(ready)],
                env, tmp_path / f"{name}.log")
    deadline = time.monotonic() + 60
    while not ready.exists():
        assert proc.p.poll() is None, proc.text()
        assert time.monotonic() < deadline, "command_monitor did not start"
        time.sleep(0.1)
    return proc, out


# A service's responses go to every client of that service, and each client's reader discards those that are
# not its own only when it takes them: with rclpy's default QoS (keep last 10) a client that does not take for a
# moment loses its own responses once ten for any client arrive after them. Measured here (tests/ros/
# test_sim_node.py's burst, slowed to one goal per 50 ms from the client's executor thread, which then takes
# nothing): of 20 goals from four Execute clients, the first 10 were never answered, the last 10 were. A CI run
# under load lost one of 40 that way. The tests' clients keep 1000 responses, as a lab's many-client tool should
# (docs/ros.md).
DEEP = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                  durability=DurabilityPolicy.VOLATILE)
ACTION_QOS = {"goal_service_qos_profile": DEEP, "result_service_qos_profile": DEEP,
              "cancel_service_qos_profile": DEEP}

# wait_for_server / wait_for_service return once the client has discovered the server; the server may not yet
# have discovered the client's response reader, and Fast DDS then drops the first response (seen here: a goal
# never acknowledged). A second of settling after discovery avoids it.
SETTLE = 1.0


class Client:
    """An rclpy node in the test process, spun in a background thread."""

    def __init__(self):
        rclpy.init()
        self.node = rclpy.create_node("test_client")
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown()

    @staticmethod
    def wait(future, timeout: float, what: str):
        deadline = time.monotonic() + timeout
        while not future.done():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out after {timeout} s waiting for {what}")
            time.sleep(0.02)
        return future.result()

    def action(self, kind, name: str, timeout: float = 60.0):
        client = ActionClient(self.node, kind, name, **ACTION_QOS)
        assert client.wait_for_server(timeout_sec=timeout), f"action server {name} did not appear in {timeout} s"
        time.sleep(SETTLE)
        return client

    def service(self, kind, name: str, timeout: float = 60.0):
        client = self.node.create_client(kind, name, qos_profile=DEEP)
        assert client.wait_for_service(timeout_sec=timeout), f"service {name} did not appear in {timeout} s"
        time.sleep(SETTLE)
        return client

    def in_executor(self, fn, *args, **kwargs):
        """fn(*args, **kwargs) run by the executor's thread. rclpy's ActionClient files a request's future only
        after sending the request, so a response that the executor thread takes in between is dropped ("Ignoring
        unexpected goal response", seen once in a full local run: a goal never acknowledged). Sent from the
        executor's own thread, nothing can come between. The wait allows 30 s (it was 10): it includes fn's own
        time, and the burst test's fn sends 40 goals and then holds the thread for 1 s (about 1.2 s unloaded)."""
        return self.wait(self.executor.create_task(fn, *args, **kwargs), 30, f"the executor to run {fn.__name__}")

    def call(self, client, request, timeout: float = 30.0):
        return self.wait(self.in_executor(client.call_async, request), timeout, f"a response from {client.srv_name}")

    def send_goal(self, client, goal, feedback=None, timeout: float = 30.0):
        """The goal handle once the server has answered (accepted or not)."""
        return self.wait(self.in_executor(client.send_goal_async, goal, feedback_callback=feedback), timeout,
                         "goal acceptance")

    def result(self, handle, timeout: float, what: str = "the goal's result"):
        return self.wait(self.in_executor(handle.get_result_async), timeout, what)

    def until_progress(self, handle, progress: list, at: float, log, timeout: float = 120.0):
        """Wait until the goal's feedback (appended to `progress`) reaches `at`; if the goal ends first, fail
        with its status and message, and the node's log (`log()`), rather than wait out the timeout."""
        result = self.in_executor(handle.get_result_async)
        deadline = time.monotonic() + timeout
        while not progress or progress[-1] < at:
            if result.done():
                res = result.result()
                raise AssertionError(f"the goal ended (status {res.status}: {res.result.message}) before progress "
                                     f"{at}\n{log()}")
            assert time.monotonic() < deadline, f"no progress {at} within {timeout} s\n{log()}"
            time.sleep(0.01)

    def cancel(self, handle, timeout: float = 10.0):
        return self.wait(self.in_executor(handle.cancel_goal_async), timeout, "the cancel response")

    def run_goal(self, client, goal, timeout: float, feedback=None):
        """Send a goal and wait for its result; returns (accepted, status, result)."""
        handle = self.send_goal(client, goal, feedback)
        if not handle.accepted:
            return False, None, None
        res = self.result(handle, timeout)
        return True, res.status, res.result

    def subscribe(self, kind, topic: str, qos=10):
        got = []
        self.node.create_subscription(kind, topic, lambda m: got.append((time.monotonic(), m)), qos)
        return got


@pytest.fixture(scope="module")
def client(ros_env):
    c = Client()
    yield c
    c.close()


@pytest.fixture
def trajectories(tmp_path):
    """A trajectory folder with the shipped trajectories."""
    folder = tmp_path / "trajectories"
    shutil.copytree(ROOT / "trajectories", folder, ignore=shutil.ignore_patterns("*.mp4"))
    return folder
