"""What the RL baselines pay beside the physics: the Gymnasium environment's step against the simulator's own rollout,
and Stable-Baselines3's learning on top (issue 16's optimiser performance).

    python bench/bench_env_overhead.py [--tasks LatteArtStir GatheringEasy] [--repeats 3]

Per task, in one process and alternating (so that load from elsewhere falls on every figure alike), the median
over repeats of:
- rollout: one `sim.rollout` of the whole horizon with zero actions (the physics and the loss, nothing else);
- env: the same steps through `FluidLabEnv.step` (a rollout of one step each, the observation, the reward);
- observe: the observation alone (`task.observe`), per step;
- sac, ppo: `learn` for two episodes (SAC after its random-action warm-up: one gradient step per env step; PPO
  with its rollout of four episodes cut to two), per env step.
Figures in ms per step and as ratios to the rollout. Writes bench/results/env_overhead_cpu.txt.
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tasks", nargs="+", default=["LatteArtStir", "GatheringEasy"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1, help="Taichi and torch threads (the benchmark's default on "
                    "two cores: two runs of one thread)")
    ap.add_argument("--out", default="bench/results/env_overhead_cpu.txt")
    args = ap.parse_args(argv)

    import fluidlab_core
    from fluidlab_core import tasks
    from fluidlab_core.envs import FluidLabEnv
    from fluidlab_core.optim import rl

    fluidlab_core.init(arch="cpu", precision="f32", cpu_threads=args.threads)
    sb3, torch = rl.import_sb3()
    torch.set_num_threads(args.threads)
    lines = [f"Environment and RL overhead beside the physics, CPU, {args.threads} thread(s), median of "
             f"{args.repeats} (ms per simulated step; ratio to the rollout)"]
    for name in args.tasks:
        task = tasks.make(name, size="small")
        env = FluidLabEnv(name, size="small", task=task)
        zeros = np.zeros((task.horizon, task.n_actions))
        times = {k: [] for k in ("rollout", "env", "observe", "sac", "ppo")}

        def rollout():
            task.reset(env.sim)
            env.sim.rollout(task.twists(zeros), task.loss(task.horizon))

        def env_episode():
            env.reset()
            for a in zeros:
                env.step(a)

        def observe():
            for _ in range(task.horizon):
                task.observe(env.sim, np.zeros(6))

        rollout(), env_episode()  # compile / load kernels
        models = {m: rl._model(m, __import__("gymnasium").wrappers.RescaleAction(
            env, -np.ones(task.n_actions, np.float32), np.ones(task.n_actions, np.float32)), task, 10 * task.horizon, 0)
            for m in ("sac", "ppo")}
        models["sac"].learning_starts = 0
        models["ppo"].n_steps = 2 * task.horizon
        models["ppo"].rollout_buffer.buffer_size = 2 * task.horizon
        for m in models.values():
            m.learn(total_timesteps=task.horizon)  # warm-up: first calls build the networks and optimisers
        for _ in range(args.repeats):
            for key, fn in (("rollout", rollout), ("env", env_episode), ("observe", observe)):
                t0 = time.perf_counter()
                fn()
                times[key].append((time.perf_counter() - t0) / task.horizon)
            for key, m in models.items():
                t0 = time.perf_counter()
                m.learn(total_timesteps=2 * task.horizon, reset_num_timesteps=False)
                times[key].append((time.perf_counter() - t0) / (2 * task.horizon))
        med = {k: 1e3 * statistics.median(v) for k, v in times.items()}
        base = med["rollout"]
        lines.append(f"{name} (small, horizon {task.horizon}): " + ", ".join(
            f"{k} {v:.2f} ms ({v / base:.2f}x)" for k, v in med.items()))
        print(lines[-1], flush=True)
    lines.append("env − rollout is the environment's own cost (one rollout call per step, the observation, the "
                 "reward); sac/ppo − env is the learner's.")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
