"""What a benchmark run costs at each task size: forward and gradient rollouts per simulated step, on this machine.

    python bench/bench_sizes.py [--tasks LatteArtStir GatheringEasy ...] [--sizes small medium] [--threads 1]
        [--steps N] [--out FILE]

Per task and size, after a first whole rollout (which compiles or loads the kernels): one forward rollout of the horizon on the reference
physics (what CMA-ES, SAC, PPO and PODS's policy rollouts pay per step) and one differentiable rollout with its
backward pass (what DP, DP-H and PODS's gradient pay), zero actions, in ms per simulated step, and the wall time
they imply for a 120-rollout run of one thread: CMA-ES ≈ 120 forward rollouts, DP ≈ 120 gradient rollouts.
Writes bench/results/sizes_<arch>.txt (after each row, so that a run cut short keeps its rows); `--arch cuda` on a GPU
machine. 'first s' is the first forward and gradient rollouts together (compiling, or loading the cache, and allocating). The benchmark at a size is worth running where these estimates fit the
machine (docs/benchmark.md). `--steps N` times the first N steps of each horizon instead of all of it (the estimates
still scale to the whole horizon), for sizes whose whole rollouts take too long to time on this machine. For a
particle task whose horizon is longer than its gradient buffer that leaves out checkpointing's second forward pass,
so its DP estimate comes out low; a gas scene checkpoints at any length, so AirCirculation's does not.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tasks", nargs="+", default=None, help="default: every registered task")
    ap.add_argument("--sizes", nargs="+", default=["small", "medium"])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--rollouts", type=int, default=120, help="run length the estimates are for")
    ap.add_argument("--arch", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--steps", type=int, default=None, help="time the first N steps of the horizon (default all)")
    ap.add_argument("--out", default=None, help="default: bench/results/sizes_<arch>.txt")
    args = ap.parse_args(argv)

    import fluidlab_core
    from fluidlab_core import tasks

    fluidlab_core.init(arch=args.arch, precision="f32", cpu_threads=args.threads)
    where = "CUDA" if args.arch == "cuda" else f"CPU, {args.threads} thread(s)"
    if args.steps is not None and args.steps < 1:
        ap.error(f"--steps must be at least 1, got {args.steps}")
    timed = f"; timed over the first {args.steps} steps of the horizon" if args.steps else ""
    lines = [f"Cost per simulated step by task size, {where}, zero actions; estimates for a "
             f"{args.rollouts}-rollout run (CMA-ES: forward rollouts; DP: gradient rollouts){timed}",
             f"{'task':<16} {'size':<7} {'grid':>4} {'horizon':>7} {'forward ms':>10} {'grad ms':>8} "
             f"{'CMA-ES run':>11} {'DP run':>9} {'first s':>8}"]
    print("\n".join(lines), flush=True)
    out = Path(args.out or f"bench/results/sizes_{args.arch}.txt")
    out.parent.mkdir(parents=True, exist_ok=True)
    for name in args.tasks or tasks.names():
        for size in args.sizes:
            task = tasks.make(name, size=size)
            steps = min(args.steps or task.horizon, task.horizon)
            zeros = task.twists(np.zeros((steps, task.n_actions)))
            fwd = task.simulator(grad=False, contact="hard")
            grad = task.simulator(grad=True, contact="hard")
            times = {}
            first = 0.0
            for key, sim, g in (("forward", fwd, False), ("grad", grad, True)):
                t0 = time.perf_counter()
                task.reset(sim)  # the first whole rollout compiles or loads the kernels and allocates the
                sim.rollout(zeros, task.loss(steps), grad=g)  # checkpoint buffers: not timed
                first += time.perf_counter() - t0
                task.reset(sim)
                t0 = time.perf_counter()
                sim.rollout(zeros, task.loss(steps), grad=g)
                times[key] = (time.perf_counter() - t0) / steps
            run = {k: args.rollouts * task.horizon * v / 60.0 for k, v in times.items()}
            lines.append(f"{name:<16} {size:<7} {task.config.grid_res:>4} {task.horizon:>7} "
                         f"{1e3 * times['forward']:>10.1f} {1e3 * times['grad']:>8.1f} "
                         f"{run['forward']:>8.0f} min {run['grad']:>5.0f} min {first:>8.0f}")
            print(lines[-1], flush=True)
            out.write_text("\n".join(lines) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
