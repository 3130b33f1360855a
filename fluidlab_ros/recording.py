"""Recording executions as rosbag2 (MCAP) files with `rosbags`, and reading them back.

A recording is a rosbag2 folder `<recordings>/<UTC time>_<trajectory>/` holding one MCAP file and
`metadata.yaml`. Topics (CDR, the Jazzy type store; every stamp is the wall-clock time the node acted, ns):

    /sim_node/commands             std_msgs/msg/Float64MultiArray   each command sent (rad/s, controller order)
    /sim_node/measured_joint_states sensor_msgs/msg/JointState      the arm being commanded: the twin in twin
                                                                    mode (every 5th command), the measured arm
                                                                    in robot mode (as it arrives)
    /sim_node/twin/joint_states    sensor_msgs/msg/JointState       the twin arm, every 5th command (100 Hz)
    /sim_node/planned_joint_states sensor_msgs/msg/JointState       the plan's joint positions, every 5th command
    /sim_node/planned_tool_pose    geometry_msgs/msg/PoseStamped    the plan's tool pose, every 5th command
    /sim_node/tool_pose            geometry_msgs/msg/PoseStamped    the measured arm's tool pose, every 5th
    /sim_node/particles            sensor_msgs/msg/PointCloud2      the twin's fluid, at most MAX_POINTS points,
                                                                    stamped with the time the arm was where the
                                                                    fluid's tool is (the worker may run behind);
                                                                    from the start to the end of the motion: the
                                                                    bag closes after the fluid's final state
    /fluidlab/metadata             std_msgs/msg/String              one JSON document, first message

The metadata (a summary without the arrays also in metadata.yaml's custom_data, key "fluidlab") holds: trajectory name, its SHA-256 and
its whole document, robot model, joint names, control rate, mode and target, the task's mounting, software
version, start time, the plan's report, and the plan's timing: for each command its time from the stream
start and the trajectory time it executes (`plan_times`, `plan_traj_times`), so a replay can relate wall
time to the trajectory's own time.

Crash safety: the writer closes an MCAP chunk every FLUSH_PERIOD seconds and flushes the file, so a crash
loses at most that much. A folder without metadata.yaml (a run that never closed its bag) is read by
scanning the MCAP records that made it to disk (`read_recording` does this by itself, and says so);
`recover(path)` writes a closed copy that `ros2 bag play` and any MCAP reader open.
"""
from __future__ import annotations

import json
import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

METADATA_TOPIC = "/fluidlab/metadata"
MAX_POINTS = 2000
FLUSH_PERIOD = 0.5  # s
TOPICS = {
    "/sim_node/commands": "std_msgs/msg/Float64MultiArray",
    "/sim_node/measured_joint_states": "sensor_msgs/msg/JointState",
    "/sim_node/twin/joint_states": "sensor_msgs/msg/JointState",
    "/sim_node/planned_joint_states": "sensor_msgs/msg/JointState",
    "/sim_node/planned_tool_pose": "geometry_msgs/msg/PoseStamped",
    "/sim_node/tool_pose": "geometry_msgs/msg/PoseStamped",
    "/sim_node/particles": "sensor_msgs/msg/PointCloud2",
    METADATA_TOPIC: "std_msgs/msg/String",
}


class RecordingError(ValueError):
    """A recording that cannot be read or used, with the reason."""


def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


class Recorder:
    """Writes messages given as (topic, rclpy message, stamp ns) from any thread; a writer thread serialises
    them (rclpy's CDR, byte-identical to rosbags') into the bag. `close()` ends the bag (metadata.yaml)."""

    def __init__(self, folder: Path, metadata: dict | None = None):
        """Open the bag. The metadata message goes first; pass it here or call write_metadata() before any
        other message (sim_node does, once it knows the stream's start time)."""
        from rosbags.rosbag2 import StoragePlugin, Writer

        self.path = Path(folder)
        if self.path.exists():
            raise RecordingError(f"recording folder {self.path} exists already")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.metadata: dict = {}
        self._writer = Writer(self.path, version=8, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        store = _typestore()
        self._conns = {t: self._writer.add_connection(t, ty, typestore=store) for t, ty in TOPICS.items()}
        self._queue: queue.Queue = queue.Queue()
        self.counts = {t: 0 for t in TOPICS}
        self.error: str = ""
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()
        if metadata is not None:
            self.write_metadata(metadata)

    def write_metadata(self, metadata: dict):
        from std_msgs.msg import String

        self.metadata = metadata
        text = json.dumps(metadata)
        summary = {k: v for k, v in metadata.items() if k not in ("trajectory_document", "plan_times",
                                                                    "plan_traj_times", "plan_report")}
        self._writer.set_custom_data("fluidlab", json.dumps(summary))
        self.put(METADATA_TOPIC, String(data=text), time.time_ns())

    def put(self, topic: str, msg, stamp_ns: int):
        self._queue.put((topic, msg, int(stamp_ns)))

    def _flush(self):
        storage = getattr(self._writer, "storage", None)
        if storage is not None and hasattr(storage, "close_chunk") and getattr(storage, "chunk", None) is not None:
            if storage.chunk.bio.tell():
                storage.close_chunk()
            storage.bio.flush()

    def _run(self):
        from rclpy.serialization import serialize_message

        last_flush = time.monotonic()
        while True:
            try:
                item = self._queue.get(timeout=FLUSH_PERIOD / 2)
            except queue.Empty:
                item = ()
            if item is None:
                break
            try:
                if item:
                    topic, msg, stamp = item
                    self._writer.write(self._conns[topic], stamp, serialize_message(msg))
                    self.counts[topic] += 1
                if time.monotonic() - last_flush > FLUSH_PERIOD:
                    self._flush()
                    last_flush = time.monotonic()
            except Exception as err:  # noqa: BLE001 - a recording problem must not stop the arm; it is reported
                self.error = self.error or f"{type(err).__name__}: {err}"

    def close(self) -> Path:
        self._queue.put(None)
        self._thread.join(30)
        self._writer.close()
        return self.path


def downsample(points: np.ndarray, n: int = MAX_POINTS) -> np.ndarray:
    """An evenly spaced subset of at most n points (the same particles every frame while the count does not change;
    a body an emitter is filling grows, and its subset with it)."""
    if len(points) <= n:
        return points
    return points[np.linspace(0, len(points) - 1, n).astype(int)]


# --- reading ---------------------------------------------------------------------------------------------
@dataclass
class Recording:
    path: Path
    metadata: dict
    closed: bool  # False: the bag was never closed (read by scanning the MCAP file)
    counts: dict = field(default_factory=dict)  # topic -> messages
    commands: tuple = ()  # (times s, (K, dof) rad/s)
    measured: tuple = ()  # (times s, (M, dof) rad)
    twin: tuple = ()
    planned: tuple = ()  # (times s, (K, dof) rad)
    planned_tool: tuple = ()  # (times s, (K, 7) poses)
    tool: tuple = ()
    particles: list = field(default_factory=list)  # [(time s, (n, 3) float32)]
    start_time: float = 0.0  # s since the epoch, of the stream's start


def _mcap_file(path: Path) -> Path:
    files = sorted(path.glob("*.mcap"))
    if not files:
        raise RecordingError(f"{path} holds no .mcap file: not a rosbag2 MCAP recording")
    return files[0]


def _iter_raw(path: Path):
    """(topic, msgtype, stamp ns, CDR bytes) of every message, from the closed bag (rosbags' reader) or, when
    metadata.yaml is missing, from the MCAP records that reached the disk (the `mcap` package's streaming
    reader, which stops at the first truncated record)."""
    path = Path(path)
    if not path.is_dir():
        raise RecordingError(f"no recording folder at {path}")
    if (path / "metadata.yaml").exists():
        from rosbags.rosbag2 import Reader

        try:
            with Reader(path) as reader:
                for conn, stamp, data in reader.messages():
                    yield conn.topic, conn.msgtype, stamp, data
        except Exception as err:  # noqa: BLE001 - rosbags raises several kinds; all mean "cannot read"
            raise RecordingError(f"{path} cannot be read as a rosbag2 recording: {type(err).__name__}: {err}") from None
        return
    from mcap.exceptions import McapError
    from mcap.stream_reader import StreamReader
    from mcap.records import Channel, Message, Schema

    schemas, channels = {}, {}
    with open(_mcap_file(path), "rb") as f:
        try:
            for rec in StreamReader(f, skip_magic=False, emit_chunks=False).records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec.name
                elif isinstance(rec, Channel):
                    channels[rec.id] = (rec.topic, schemas.get(rec.schema_id, ""))
                elif isinstance(rec, Message) and rec.channel_id in channels:
                    topic, msgtype = channels[rec.channel_id]
                    yield topic, msgtype, rec.log_time, rec.data
        except (McapError, EOFError, ValueError, OSError):
            return  # the end of what was written before the crash


def read_recording(path) -> Recording:
    """Read a recording into arrays (times in s since the stream's start). Raises RecordingError with the
    reason for a folder that is not a recording, a corrupt file, or one without FluidLab metadata."""
    from rclpy.serialization import deserialize_message
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import JointState, PointCloud2
    from std_msgs.msg import Float64MultiArray, String

    types = {"std_msgs/msg/Float64MultiArray": Float64MultiArray, "sensor_msgs/msg/JointState": JointState,
             "geometry_msgs/msg/PoseStamped": PoseStamped, "sensor_msgs/msg/PointCloud2": PointCloud2,
             "std_msgs/msg/String": String}
    path = Path(path)
    closed = (path / "metadata.yaml").exists()
    meta = None
    series: dict[str, list] = {t: [] for t in TOPICS}
    try:
        for topic, msgtype, stamp, data in _iter_raw(path):
            if topic not in TOPICS or msgtype not in types:
                continue
            msg = deserialize_message(bytes(data), types[msgtype])
            if topic == METADATA_TOPIC:
                meta = json.loads(msg.data)
            else:
                series[topic].append((stamp * 1e-9, msg))
    except RecordingError:
        raise
    except Exception as err:  # noqa: BLE001 - corrupt CDR or MCAP
        raise RecordingError(f"{path}: corrupt recording ({type(err).__name__}: {err})") from None
    # in stamp order: the twin's fluid is written when the worker computed it, stamped when the arm was there
    for items in series.values():
        items.sort(key=lambda item: item[0])
    if meta is None:
        raise RecordingError(f"{path} has no {METADATA_TOPIC} message: not a FluidLab recording, or truncated "
                             f"before anything was written")
    t0 = float(meta["start_time"])

    dof = len(meta.get("joint_names", [])) or 7

    def rows(values, width):
        return np.array(values, dtype=float) if values else np.zeros((0, width))

    def joints(items):
        return np.array([t - t0 for t, _ in items]), rows([list(m.position) for _, m in items], dof)

    def poses(items):
        return (np.array([t - t0 for t, _ in items]),
                rows([[m.pose.position.x, m.pose.position.y, m.pose.position.z, m.pose.orientation.x,
                       m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w] for _, m in items], 7))

    cmds = series["/sim_node/commands"]
    rec = Recording(path=path, metadata=meta, closed=closed, counts={t: len(v) for t, v in series.items()},
                    start_time=t0)
    rec.counts[METADATA_TOPIC] = 1
    rec.commands = (np.array([t - t0 for t, _ in cmds]), rows([list(m.data) for _, m in cmds], dof))
    rec.measured = joints(series["/sim_node/measured_joint_states"])
    rec.twin = joints(series["/sim_node/twin/joint_states"])
    rec.planned = joints(series["/sim_node/planned_joint_states"])
    rec.planned_tool = poses(series["/sim_node/planned_tool_pose"])
    rec.tool = poses(series["/sim_node/tool_pose"])
    rec.particles = [(t - t0, np.frombuffer(bytes(m.data), dtype=np.float32).reshape(-1, 3))
                     for t, m in series["/sim_node/particles"]]
    return rec


def recover(path, out=None) -> Path:
    """Write a closed copy of a recording that was never closed (`<path>.recovered` by default)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    path = Path(path)
    out = Path(out) if out else path.with_name(path.name + ".recovered")
    store = _typestore()
    writer = Writer(out, version=8, storage_plugin=StoragePlugin.MCAP)
    conns = {}
    writer.open()
    try:
        for topic, msgtype, stamp, data in _iter_raw(path):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(conns[topic], stamp, bytes(data))
    finally:
        writer.close()
    return out
