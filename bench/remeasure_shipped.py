"""Re-measure the recorded loss of shipped trajectories after an engine change that moves their physics.

    python bench/remeasure_shipped.py TASK [TASK ...] --why "what changed" [--dest trajectories]

Each task's shipped small trajectory (trajectories/<task>/*_small.json) is replayed on the current engine as
tests/test_tasks.py replays it; its metadata's `final_loss` becomes the replayed loss, and the loss its optimiser
recorded moves to `optimised_loss` (kept from the first re-measurement), with `remeasured` saying why and when (each re-measurement appended).
The trajectory itself and its video are not changed: re-optimising and re-shipping (`bench/ship_best.py`) is the
real fix; this keeps the shipped files honest until then. Writes each file atomically.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import tempfile
from pathlib import Path


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("tasks", nargs="+")
    ap.add_argument("--why", required=True, help="the engine change that moved the physics")
    ap.add_argument("--dest", default=str(Path(__file__).resolve().parents[1] / "trajectories"))
    args = ap.parse_args()
    import numpy as np

    import fluidlab_core
    from fluidlab_core import tasks
    from fluidlab_core.trajectory import Trajectory

    fluidlab_core.init(arch="cpu", precision="f32")
    for name in args.tasks:
        files = sorted((Path(args.dest) / name).glob("*_small.json"))
        if len(files) != 1:
            raise SystemExit(f"{name}: expected one shipped small trajectory, found {files}")
        path = files[0]
        traj = Trajectory.load(path)
        task = tasks.make(name, traj.metadata["size"])
        actions, position = task.actions_from_trajectory(traj)
        loss = float(task.evaluate(actions, tool_position=position, rewards=False)["loss"])
        zero = float(task.evaluate(np.zeros_like(actions), rewards=False)["loss"])
        doc = json.loads(path.read_text())
        meta = doc["metadata"]
        meta.setdefault("optimised_loss", meta["final_loss"])
        meta["final_loss"] = loss
        why = f"{datetime.date.today().isoformat()}: {args.why}"
        meta["remeasured"] = f"{meta['remeasured']}; {why}" if meta.get("remeasured") else why  # every change kept
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".json.tmp")
        with os.fdopen(fd, "w") as f:
            json.dump(doc, f, indent=1)
        os.replace(tmp, path)
        print(f"{name}: loss {meta['optimised_loss']:.6g} when optimised, {loss:.6g} now; tool still: {zero:.6g}",
              flush=True)


if __name__ == "__main__":
    main()
