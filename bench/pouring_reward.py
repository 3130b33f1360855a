"""Pouring: what the per-step reward r = c1 − c2·ℓ_k pays along a pour, against the still glass.

    python bench/pouring_reward.py [TRAJECTORY.json ...]

Replays each trajectory (default: the shipped Pouring trajectory and the benchmark's DP run, where present) on
the reference physics, small size, float32, and prints its final loss (the task's goal), its return
Σ_k (c1 − c2 ℓ_k), and the mean per-step loss ℓ_k and the glass's tilt (rad) over each eighth of the 8 s episode;
then the same for the task's starting pour (Task.initial_actions) and the still glass. ℓ_k is the task's loss
evaluated at step k: the light liquid's mean height above the table plus the heavy liquid's mean L1 distance
from its starting places (m). Writes bench/results/pouring_reward_small.txt.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
DEFAULTS = ["trajectories/Pouring/*_small.json",
            "bench/results/benchmark_small/trajectories/Pouring/Pouring_dp_seed0_small.json"]


def describe(name, task, actions, position=None):
    out = task.evaluate(actions, position)
    step_loss = (task.reward_c1 - np.asarray(out["rewards"])) / task.reward_c2
    tilt = np.cumsum(np.asarray(actions)[:, 0]) * task.dt  # rad about y; the glass's only axis
    eighths = np.array_split(np.arange(len(step_loss)), 8)
    return [f"{name}",
            f"  final loss {out['loss']:.4e} m   return {out['return']:.1f}",
            "  mean step loss by eighth (m): " + " ".join(f"{step_loss[i].mean():.4f}" for i in eighths),
            "  tilt at the end of each eighth (rad): " + " ".join(f"{tilt[i[-1]]:.2f}" for i in eighths)]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trajectories", nargs="*", help="Pouring trajectory files (default: shipped and benchmark DP)")
    args = ap.parse_args()
    paths = [Path(p) for p in args.trajectories] or [
        p for pattern in DEFAULTS for p in sorted(ROOT.glob(pattern))]
    import fluidlab_core
    from fluidlab_core import tasks
    from fluidlab_core.trajectory import Trajectory

    fluidlab_core.init(arch="cpu", precision="f32")
    task = tasks.make("Pouring", "small")
    lines = [f"Pouring, small, float32, CPU; reward r = {task.reward_c1:g} − {task.reward_c2:g} ℓ per step, "
             f"{task.horizon} steps of {task.dt * 1e3:g} ms"]
    for path in paths:
        traj = Trajectory.load(path)
        actions, position = task.actions_from_trajectory(traj)
        lines += describe(str(path.relative_to(ROOT) if path.is_absolute() and ROOT in path.parents else path),
                          task, np.asarray(actions), position)
        print("\n".join(lines[-4:]), file=sys.stderr)
    lines += describe("the task's starting pour (Task.initial_actions)", task, task.initial_actions())
    lines += describe("the still glass", task, np.zeros((task.horizon, len(task.action_axes))))
    text = "\n".join(lines) + "\n"
    out = ROOT / "bench" / "results" / "pouring_reward_small.txt"
    out.write_text(text)
    print(text + f"wrote {out}")


if __name__ == "__main__":
    main()
