"""Each task's mounting (robot_models/mounting.json): where the task's scene sits in the robot base frame
and the tool frame's pose relative to the flange (link8). Poses are [x, y, z, qx, qy, qz, qw]."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import robot_models


@dataclass(frozen=True)
class Mounting:
    task: str
    scene_origin: np.ndarray  # (7,) scene frame in the base frame
    tool: str
    flange_to_tool: np.ndarray  # (7,) tool frame in the flange frame

    @classmethod
    def from_dict(cls, task: str, entry: dict) -> "Mounting":
        def pose(key):
            v = np.asarray(entry[key], dtype=float)
            if v.shape != (7,) or not np.all(np.isfinite(v)) or np.linalg.norm(v[3:]) < 1e-9:
                raise ValueError(f"mounting of {task}: {key} must be 7 finite numbers [x, y, z, qx, qy, qz, qw]")
            v[3:] /= np.linalg.norm(v[3:])
            return v

        return cls(task=task, scene_origin=pose("scene_origin"), tool=str(entry.get("tool", "tool")),
                   flange_to_tool=pose("flange_to_tool"))


def tasks(path: str | Path | None = None) -> list[str]:
    return sorted(_read(path)["tasks"])


def load_mounting(task: str, path: str | Path | None = None) -> Mounting:
    doc = _read(path)["tasks"]
    if task not in doc:
        raise KeyError(f"no mounting for task {task!r} in {path or robot_models.mounting_path()}: "
                       f"known tasks are {', '.join(sorted(doc))}")
    return Mounting.from_dict(task, doc[task])


def _read(path) -> dict:
    return json.loads(Path(path or robot_models.mounting_path()).read_text())
