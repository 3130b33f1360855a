"""Each task's mounting: where the task's scene sits in the robot base frame, and the tool frame's pose
relative to the flange (link8). Poses are [x, y, z, qx, qy, qz, qw].

The tool offset is a fact about the task (the tool the simulation was built with) and comes from the task
class (`Task.flange_to_tool`, `Task.tool_name`), for the paper's tasks and for tasks of your own registered
with `fluidlab_core.tasks.register`. Where the scene sits is the lab's calibration: robot_models/mounting.json
gives each task's `scene_origin`; a task it does not list has its scene at the base frame's origin (the tasks'
scenes are written in the base frame). `table_height` is the height of the table plane in the scene frame (m;
the file's top-level default, 0: the scenes stand on z = 0, as the arm's base does), used by the collision
check (fluidlab_ros/collision.py); a task's entry may override it.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import robot_models

IDENTITY = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)


@dataclass(frozen=True)
class Mounting:
    task: str
    scene_origin: np.ndarray  # (7,) scene frame in the base frame
    tool: str
    flange_to_tool: np.ndarray  # (7,) tool frame in the flange frame
    table_height: float = 0.0  # m, the table plane's z in the scene frame


def _pose(task: str, key: str, value) -> np.ndarray:
    v = np.asarray(value, dtype=float)
    if v.shape != (7,) or not np.all(np.isfinite(v)) or np.linalg.norm(v[3:]) < 1e-9:
        raise ValueError(f"mounting of {task}: {key} must be 7 finite numbers [x, y, z, qx, qy, qz, qw], got {value!r}")
    v[3:] /= np.linalg.norm(v[3:])
    return v


def tasks() -> list[str]:
    """The tasks that can be mounted: every registered task."""
    from fluidlab_core import tasks as registry

    return registry.names()


def load_mounting(task: str, path: str | Path | None = None) -> Mounting:
    """The mounting of a registered task: its tool offset from the task, its scene origin from mounting.json."""
    from fluidlab_core import tasks as registry

    if task not in registry.names():
        raise KeyError(f"no mounting for task {task!r}: known tasks are {', '.join(registry.names())}")
    cls = registry.task_class(task)
    doc = json.loads(Path(path or robot_models.mounting_path()).read_text())
    unknown = sorted(set(doc["tasks"]) - set(registry.names()))
    if unknown:
        raise ValueError(f"{path or robot_models.mounting_path()} mounts unknown tasks {unknown}; known tasks are "
                         f"{', '.join(registry.names())}")
    entry = doc["tasks"].get(task, {})
    if "flange_to_tool" in entry or "tool" in entry:
        raise ValueError(f"{path or robot_models.mounting_path()}: the tool of {task} is the task's "
                         f"(flange_to_tool, tool_name in its class), not the mounting file's")
    table = float(entry.get("table_height", doc.get("table_height", 0.0)))
    if not np.isfinite(table):
        raise ValueError(f"mounting of {task}: table_height must be a finite number (m), got {table!r}")
    return Mounting(task=task, scene_origin=_pose(task, "scene_origin", entry.get("scene_origin", IDENTITY)),
                    tool=cls.tool_name, flange_to_tool=_pose(task, "flange_to_tool", cls.flange_to_tool),
                    table_height=table)
