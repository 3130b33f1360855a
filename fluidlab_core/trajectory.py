"""The trajectory file: a versioned JSON document of a tool's motion, what optimisers write and what the
ROS node executes.

    {
      "format": "fluidlab-trajectory", "version": 1,
      "task": "LatteArtStir", "tool": "stick", "frame_id": "fr3_link0",
      "units": {"time": "s", "position": "m", "linear_velocity": "m/s", "angular_velocity": "rad/s"},
      "dt": 0.002,                                   # seconds per twist
      "initial_pose": [x, y, z, qx, qy, qz, qw],     # tool frame in frame_id, quaternion (x, y, z, w)
      "twists": [[vx, vy, vz, wx, wy, wz], ...],     # one per step, world (frame_id) frame, held for dt
      "loss_history": [...], "method": "dp", "seed": 0,
      "software_version": "0.1.0", "created": "2026-11-21T07:30:00+00:00", "metadata": {...}
    }

The twist convention is the simulator's (fluidlab_core.engine.tools): over each step the tool origin moves
as p ← p + v dt and the orientation as R ← exp([ω]× dt) R, so `poses()` reproduces the tool poses a
simulation with these actions goes through.

Loading rejects other formats and versions, missing fields, and malformed or non-finite arrays, with a
message that names the field. Saving writes a temporary file in the same folder and renames it, so a
crash never leaves a partial trajectory file.
"""
from __future__ import annotations

import datetime as _dt
import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

FORMAT = "fluidlab-trajectory"
VERSION = 1
UNITS = {"time": "s", "position": "m", "linear_velocity": "m/s", "angular_velocity": "rad/s"}
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$")


class TrajectoryError(ValueError):
    """A trajectory document that cannot be used, with the reason."""


def check_name(name: str, what: str = "trajectory name") -> str:
    """Names become file names: letters, digits, '_', '-', '.', no path separators, not starting with '.'."""
    if not isinstance(name, str) or not _NAME.match(name) or name in (".", ".."):
        raise TrajectoryError(f"{what} {name!r} is not allowed: use letters, digits, '_', '-' and '.', starting "
                              f"with a letter or digit, without path separators (at most 128 characters)")
    if name.endswith(".report"):  # <name>.report.json is the optimiser's report beside <name>.json
        raise TrajectoryError(f"{what} {name!r} is not allowed: a name ending in '.report' would be taken for the "
                              f"report of the trajectory {name[:-7]!r}")
    return name


def _array(value, shape_tail: tuple, what: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TrajectoryError(f"{what} must be numbers, got {type(value).__name__}") from None
    if arr.ndim != 1 + len(shape_tail) or tuple(arr.shape[1:]) != shape_tail:
        want = "(N, " + ", ".join(map(str, shape_tail)) + ")" if shape_tail else "(N,)"
        raise TrajectoryError(f"{what} must have shape {want}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0]
        raise TrajectoryError(f"{what} holds NaN or infinity (first at index {tuple(int(i) for i in bad)})")
    return arr


@dataclass
class Trajectory:
    task: str
    dt: float  # s per twist
    tool: str
    initial_pose: np.ndarray  # (7,) x, y, z (m), qx, qy, qz, qw
    twists: np.ndarray  # (N, 6) vx, vy, vz (m/s), wx, wy, wz (rad/s) in frame_id
    frame_id: str = "fr3_link0"
    method: str = ""
    seed: int | None = None
    loss_history: list = field(default_factory=list)
    metadata: dict = field(default_factory=dict)
    software_version: str = ""
    created: str = ""

    def __post_init__(self):
        self.validate()

    def validate(self):
        if not isinstance(self.task, str) or not self.task:
            raise TrajectoryError("task must be a non-empty string")
        if not isinstance(self.tool, str) or not self.tool:
            raise TrajectoryError("tool must be a non-empty string")
        if not isinstance(self.dt, (int, float)) or not math.isfinite(self.dt) or self.dt <= 0:
            raise TrajectoryError(f"dt must be a positive number of seconds, got {self.dt!r}")
        self.dt = float(self.dt)
        pose = np.asarray(_array([self.initial_pose], (7,), "initial_pose"))[0]
        if np.linalg.norm(pose[3:]) < 1e-9:
            raise TrajectoryError("initial_pose has a zero quaternion")
        pose[3:] /= np.linalg.norm(pose[3:])
        self.initial_pose = pose
        self.twists = _array(self.twists, (6,), "twists")
        if len(self.twists) == 0:
            raise TrajectoryError("twists is empty: a trajectory needs at least one step")
        self.loss_history = [float(v) for v in _array(self.loss_history if len(self.loss_history) else
                                                      np.zeros(0), (), "loss_history")]
        if self.seed is not None and not isinstance(self.seed, int):
            raise TrajectoryError(f"seed must be an integer or null, got {self.seed!r}")
        if not isinstance(self.metadata, dict):
            raise TrajectoryError("metadata must be an object")

    @property
    def n_steps(self) -> int:
        return len(self.twists)

    @property
    def duration(self) -> float:
        """Seconds."""
        return self.n_steps * self.dt

    def poses(self) -> np.ndarray:
        """(N + 1, 7) tool poses at the start and after every step, integrating the twists as the simulator does."""
        out = np.empty((self.n_steps + 1, 7))
        p = self.initial_pose[:3].copy()
        rot = Rotation.from_quat(self.initial_pose[3:])
        out[0] = self.initial_pose
        for i, (v, w) in enumerate(zip(self.twists[:, :3], self.twists[:, 3:])):
            p = p + v * self.dt
            rot = Rotation.from_rotvec(w * self.dt) * rot
            out[i + 1, :3], out[i + 1, 3:] = p, rot.as_quat()
        return out

    # --- JSON ---------------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "format": FORMAT, "version": VERSION, "task": self.task, "tool": self.tool, "frame_id": self.frame_id,
            "units": dict(UNITS), "dt": self.dt, "initial_pose": self.initial_pose.tolist(),
            "twists": self.twists.tolist(), "loss_history": list(self.loss_history), "method": self.method,
            "seed": self.seed, "software_version": self.software_version or _software_version(),
            "created": self.created or _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "metadata": self.metadata,
        }

    @classmethod
    def from_dict(cls, doc) -> "Trajectory":
        if not isinstance(doc, dict):
            raise TrajectoryError(f"a trajectory must be a JSON object, got {type(doc).__name__}")
        if doc.get("format") != FORMAT:
            raise TrajectoryError(f"not a trajectory file: format is {doc.get('format')!r}, expected {FORMAT!r}")
        if doc.get("version") != VERSION:
            raise TrajectoryError(f"unsupported trajectory version {doc.get('version')!r}: this software reads "
                                  f"version {VERSION}")
        missing = [k for k in ("task", "tool", "dt", "initial_pose", "twists") if k not in doc]
        if missing:
            raise TrajectoryError(f"trajectory is missing {', '.join(missing)}")
        units = doc.get("units", UNITS)
        if units != UNITS:
            raise TrajectoryError(f"trajectory units {units} differ from {UNITS}")
        return cls(task=doc["task"], dt=doc["dt"], tool=doc["tool"], initial_pose=doc["initial_pose"],
                   twists=doc["twists"], frame_id=doc.get("frame_id", "fr3_link0"), method=doc.get("method", ""),
                   seed=doc.get("seed"), loss_history=doc.get("loss_history", []), metadata=doc.get("metadata", {}),
                   software_version=doc.get("software_version", ""), created=doc.get("created", ""))

    def save(self, path: str | os.PathLike) -> Path:
        """Write atomically (temporary file in the same folder, then rename); returns the path."""
        from fluidlab_core.files import write_atomic

        return write_atomic(path, json.dumps(self.to_dict(), indent=1, allow_nan=False))

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Trajectory":
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"no trajectory file at {path}")
        return cls.loads(path.read_bytes(), str(path))

    @classmethod
    def loads(cls, data: bytes | str, source: str = "<document>") -> "Trajectory":
        """A trajectory from its JSON text (`source` names it in error messages)."""
        try:
            doc = json.loads(data)
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            raise TrajectoryError(f"{source} is not valid JSON: {err}") from None
        try:
            return cls.from_dict(doc)
        except TrajectoryError as err:
            raise TrajectoryError(f"{source}: {err}") from None


def path_for(root: str | os.PathLike, task: str, name: str) -> Path:
    """trajectories/<task>/<name>.json under `root`, with both names checked."""
    return Path(root) / check_name(task, "task name") / f"{check_name(name)}.json"


def _software_version() -> str:
    from fluidlab_core import __version__

    return __version__
