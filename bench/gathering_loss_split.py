"""What the Gathering tasks' optimised trajectories gain, split into the objects' horizontal and vertical distance to
their goals, on the default liquid and on the projection (issue 19: the tasks' physics).

    python bench/gathering_loss_split.py [--tasks GatheringEasy GatheringHard] [--size small]
        [--out bench/results/gathering_loss_split_small.txt]

The Gathering loss is the mean over the horizon of Σ_objects mean_p |x_p − g|² (m²), with the goals g at the objects'
floating height (fluidlab_core/tasks/gathering.py). It splits exactly into a horizontal part, (x, y), which is what
gathering means, and a vertical part, z, which is zero for an object floating at its Archimedes depth and grows as
it sinks. On the default liquid the foam sinks (0.91 of its volume under the surface in its first second; README,
floating bodies), on the projection it floats. For each task, liquid and trajectory, one rollout, and the two parts:
- still: the paddle held still;
- dp (state): DP seed 0 on the default (bench/results/benchmark_<size>/, the 2026-11-27 sweep; shipped until
  2026-12-06);
- cma-es-free (state): CMA-ES over free knots on the default, on the fixed statics, its best seed by its final loss
  in bench/results/benchmark_<size>_statics/runs.jsonl (seed 1 on GatheringEasy, shipped; seed 0 on GatheringHard,
  shipped until 2026-12-07);
- dp-free (state): DP over the same free knots on the default, on the fixed statics, seed 0
  (bench/results/benchmark_<size>_statics/; GatheringHard's ships since 2026-12-07);
- cma-es (state): the optimiser benchmark's CMA-ES seed 0 on the default, on the fixed statics
  (bench/results/benchmark_<size>_statics/);
- cma-es, cma-es-free, ppo, sac (projection): their seed 0 on the projection (bench/results/benchmark_<size>_projection/,
  from `python -m fluidlab_core.benchmark --pressure projection --methods cma-es cma-es-free ppo sac`).
A trajectory whose file is missing is skipped. Beside each: the paddle's net displacement over the horizon and the
farthest it goes from its start (m), from its twists: the periodic stroke returns it to its start every period.
Appends its table to the output file.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from results_file import append_table  # bench/results_file.py (this script's folder is on the path)

ROOT = Path(__file__).resolve().parents[1]


def trajectories(task: str, size: str) -> dict:
    """{label: path} of the trajectories compared (those whose file exists)."""
    paths = {
        "dp (state)": ROOT / "bench" / "results" / f"benchmark_{size}" / "trajectories" / task
        / f"{task}_dp_seed0_{size}.json",
        "cma-es (state)": ROOT / "bench" / "results" / f"benchmark_{size}_statics" / "trajectories" / task
        / f"{task}_cma-es_seed0_{size}.json",
    }
    statics = ROOT / "bench" / "results" / f"benchmark_{size}_statics"
    runs = statics / "runs.jsonl"
    free = [json.loads(line) for line in open(runs)] if runs.is_file() else []
    free = [r for r in free if r["task"] == task and r["method"] == "cma-es-free" and "final_loss" in r]
    if free:  # its best seed
        paths["cma-es-free (state)"] = statics / min(free, key=lambda r: r["final_loss"])["trajectory"]
    paths["dp-free (state)"] = statics / "trajectories" / task / f"{task}_dp-free_seed0_{size}.json"
    for method in ("cma-es", "cma-es-free", "ppo", "sac"):
        paths[f"{method} (projection)"] = (ROOT / "bench" / "results" / f"benchmark_{size}_projection" / "trajectories"
                                           / task / f"{task}_{method}_seed0_{size}_projection.json")
    return {k: p for k, p in paths.items() if p.is_file()}


def split(task, sim, actions, position) -> dict:
    """One rollout: the loss's horizontal and vertical parts (m², each a mean over the horizon), their sum, and the
    task's own loss of the same actions (a check of the split)."""
    goals = task.goals()
    twists = task.twists(actions)
    task.reset(sim, position)
    horizontal, vertical = [], []
    for twist in twists:
        sim.step(action=twist)
        h = v = 0.0
        for body, g in goals.items():
            d = sim.positions(body) - g
            h += float(np.mean(d[:, 0] ** 2 + d[:, 1] ** 2))
            v += float(np.mean(d[:, 2] ** 2))
        horizontal.append(h)
        vertical.append(v)
    out = {"horizontal": float(np.mean(horizontal)), "vertical": float(np.mean(vertical))}
    out["sum"] = out["horizontal"] + out["vertical"]
    out["loss"] = float(task.evaluate(actions, position, sim=sim, rewards=False)["loss"])
    path = np.cumsum(np.asarray(twists)[:, :3], axis=0) * task.dt  # the paddle's displacement from its start (m)
    out["net"], out["reach"] = float(np.linalg.norm(path[-1])), float(np.linalg.norm(path, axis=1).max())
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tasks", nargs="+", default=["GatheringEasy", "GatheringHard"])
    ap.add_argument("--size", default="small")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    import fluidlab_core as fl
    from fluidlab_core import tasks
    from fluidlab_core.trajectory import Trajectory

    fl.init("cpu")
    out = Path(args.out or ROOT / "bench" / "results" / f"gathering_loss_split_{args.size}.txt")
    lines = [f"# bench/gathering_loss_split.py, {time.strftime('%Y-%m-%d %H:%M')}, size {args.size}, CPU, float32",
             "# task | liquid | trajectory | loss (m²) = horizontal + vertical | its gain on the still tool's loss: "
             "total, horizontal, vertical (share of the still loss) | task.evaluate's loss (check) | the paddle's net "
             "displacement and farthest reach from its start (m)"]
    print("\n".join(lines), flush=True)
    for name in args.tasks:
        for pressure in ("state", "projection"):
            task = tasks.make(name, args.size, pressure=pressure)
            sim = task.simulator()
            still = split(task, sim, np.zeros((task.horizon, task.n_actions)), None)
            rows = [("still", still)]
            for label, path in trajectories(name, args.size).items():
                actions, position = task.actions_from_trajectory(Trajectory.load(path))
                rows.append((label, split(task, sim, actions, position)))
            for label, r in rows:
                gain = [(still[k] - r[k]) / still["sum"] for k in ("sum", "horizontal", "vertical")]
                line = (f"{name} | {pressure} | {label} | {r['sum']:.4e} = {r['horizontal']:.4e} + {r['vertical']:.4e} | "
                        f"{gain[0]:+.3f}, {gain[1]:+.3f}, {gain[2]:+.3f} | {r['loss']:.4e} | {r['net']:.4f}, {r['reach']:.4f}")
                lines.append(line)
                print(line, flush=True)
            fl.runtime.reset()  # the next build starts its fields' ids from zero (its kernels from the cache)
    append_table(out, lines)


if __name__ == "__main__":
    main()
