"""Goal files: reproducible goal patterns of a task, produced by a documented scripted tool motion and shipped
as versioned numpy archives (no pickles).

    fluidlab_core/tasks/data/<task>_<size>.goal.v1.npz
        format   "fluidlab-goal"          version  1
        task     task name                size     "small" | "medium" | "paper"
        steps    (K,) int                 step numbers after which the goal applies
        points   (K, M, 3) float64        goal points in the base frame (m)
        script   JSON text: the scripted motion and how the points were chosen

Regenerate with `python -m fluidlab_core.tasks.goals <task> --size small|medium|paper` (runs the scripted motion on
the task's reference physics and overwrites the file atomically).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from fluidlab_core.files import atomic_path
from fluidlab_core.tasks.base import SIZES

FORMAT = "fluidlab-goal"
VERSION = 1
DATA_DIR = Path(__file__).resolve().parent / "data"


class GoalFileError(ValueError):
    """A goal file that is missing or cannot be used."""


def goal_path(task: str, size: str) -> Path:
    return DATA_DIR / f"{task}_{size}.goal.v{VERSION}.npz"


def save(path, task: str, size: str, steps, points, script: dict) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    steps = np.asarray(steps, dtype=np.int64)
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 3 or points.shape[0] != len(steps) or points.shape[2] != 3:
        raise GoalFileError(f"points must have shape (K, M, 3) with K = {len(steps)} steps, got {points.shape}")
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez_compressed(tmp, format=np.array(FORMAT), version=np.array(VERSION), task=np.array(task),
                            size=np.array(size), steps=steps, points=points, script=np.array(json.dumps(script)))
    return path


def load(task: str, size: str, path=None) -> dict:
    """{"steps": (K,), "points": (K, M, 3), "script": dict} of a task's goal, checked."""
    path = Path(path) if path else goal_path(task, size)
    if not path.exists():
        raise GoalFileError(f"no goal file for {task} ({size}) at {path}; generate it with "
                            f"`python -m fluidlab_core.tasks.goals {task} --size {size}`")
    try:
        with np.load(path, allow_pickle=False) as z:
            doc = {k: z[k] for k in z.files}
    except Exception as exc:  # a truncated or foreign file
        raise GoalFileError(f"{path} is not a readable goal file: {exc}") from None
    if str(doc.get("format")) != FORMAT or int(doc.get("version", -1)) != VERSION:
        raise GoalFileError(f"{path}: expected format {FORMAT!r} version {VERSION}, got {doc.get('format')!s} "
                            f"version {doc.get('version')!s}")
    if str(doc["task"]) != task or str(doc["size"]) != size:
        raise GoalFileError(f"{path} holds the goal of {doc['task']} ({doc['size']}), not {task} ({size})")
    points, steps = doc["points"], doc["steps"]
    if points.ndim != 3 or points.shape[0] != len(steps) or not np.all(np.isfinite(points)):
        raise GoalFileError(f"{path}: malformed points array {points.shape}")
    return {"steps": steps.astype(int), "points": points, "script": json.loads(str(doc["script"]))}


def generate(task_name: str, size: str, out=None) -> Path:
    """Run the task's scripted goal motion and write its goal file."""
    from fluidlab_core import tasks

    task = tasks.make(task_name, size=size)
    if not hasattr(task, "goal_from_script"):
        raise GoalFileError(f"{task_name} has no scripted goal (its goal is a fixed position)")
    steps, points, script = task.goal_from_script()
    return save(out or goal_path(task.name, size), task.name, size, steps, points, script)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description="regenerate a task's goal file from its scripted motion")
    parser.add_argument("task")
    parser.add_argument("--size", default="small", choices=list(SIZES))
    parser.add_argument("--out", default=None, help="output path (default: the shipped file)")
    args = parser.parse_args(argv)
    path = generate(args.task, args.size, args.out)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
