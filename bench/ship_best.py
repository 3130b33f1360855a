"""Copy the best run of each task from a benchmark folder (its runs.jsonl, from `python -m fluidlab_core.benchmark`) into trajectories/<task>/, with its report and a video of its episode (rendered on
the reference physics).

    python bench/ship_best.py bench/results/benchmark_small [--dest trajectories] [--tasks A B]

A task's previously shipped files (trajectory, report, video) are removed when its best run has another name;
the names in tests and docs that point at them then need the new name (the script prints both).
"""
from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("bench_out")
    ap.add_argument("--dest", default="trajectories")
    ap.add_argument("--tasks", nargs="+", default=None, help="only these tasks (default: every task in the runs)")
    ap.add_argument("--arch", default="cpu", choices=["cpu", "cuda", "auto"], help="Taichi backend of the videos")
    args = ap.parse_args()
    import fluidlab_core
    from fluidlab_core.episode import render_episode
    from fluidlab_core.trajectory import Trajectory
    from fluidlab_core.trajectory_store import report_path

    runs = [json.loads(line) for line in open(Path(args.bench_out) / "runs.jsonl")]

    def kept(r):  # a run whose trajectory file is still there (older sweeps kept only some)
        src = Path(r["trajectory"])
        return (src if src.is_absolute() else Path(args.bench_out) / src).is_file()

    best = {}
    for r in runs:
        if args.tasks and r["task"] not in args.tasks:
            continue
        if "final_loss" in r and "trajectory" in r and kept(r) and (r["task"] not in best
                                                         or r["final_loss"] < best[r["task"]]["final_loss"]):
            best[r["task"]] = r
    fluidlab_core.init(arch=args.arch, precision="f32")
    for task, r in sorted(best.items()):
        src = Path(r["trajectory"])
        if not src.is_absolute():  # the benchmark's records name it relative to their folder
            src = Path(args.bench_out) / src
        dest = Path(args.dest) / task
        dest.mkdir(parents=True, exist_ok=True)
        # shipped names carry the task: sim_node's trajectory names (file stems) are unique across the folder
        stem = src.stem if src.stem.startswith(task + "_") else f"{task}_{src.stem}"
        for old in sorted(dest.iterdir()):
            if old.name.split(".")[0] != stem and old.suffix in (".json", ".mp4"):
                print(f"{task}: removing {old} (replaced by {stem})")
                old.unlink()
        shutil.copy(src, dest / f"{stem}.json")
        report = json.loads(report_path(src).read_text())
        report["trajectory"] = str(dest / f"{stem}.json")  # where it ships, not where the run wrote it
        (dest / f"{stem}.report.json").write_text(json.dumps(report, indent=1))
        traj = Trajectory.load(dest / f"{stem}.json")
        with tempfile.TemporaryDirectory() as tmp:
            out = render_episode(traj, tmp, every=1, size=(480, 360), fps=25)
            shutil.move(out["mp4"], dest / f"{stem}.mp4")
        print(f"{task}: {r['method']} seed {r['seed']} final loss {r['final_loss']:.4e} "
              f"(video loss {out['loss']:.4e}) -> {dest / stem}.json")


if __name__ == "__main__":
    main()
