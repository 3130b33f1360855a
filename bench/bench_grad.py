"""Gradient cost: forward + backward time over forward time, and peak memory against the horizon.

Scene ("small"): a water block in a box stirred by a soft-contact stick, 12³ grid, float32 on the CPU.
Each horizon runs in a child process, so that its peak resident memory (ru_maxrss) is its own:
  forward     the fast solver (`rollout(grad=False)`)
  diff fwd    the differentiable solver's forward only (time-indexed state, what the backward needs kept)
  fwd + bwd   `rollout(grad=True)`: checkpointed forward, then each segment re-run and reversed
Ratios are against the fast forward run in the same process (warm kernels: each is run once first). Each
time is the fastest of --repeat runs (default: 3 up to 1,000 steps, 1 beyond).

    python bench/bench_grad.py [--horizons 100 1000 10000] [--grid 12] [--arch cpu|cuda]
                               [--out bench/results/grad_cpu.txt]

With --arch cuda, peak RSS is host memory only (GPU memory is not measured yet).

--grid sets the grid resolution (particles grow as its cube, substeps in proportion for stability).
"""
import argparse
import json
import os
import subprocess
import sys
import time

CHILD = r"""
import json, resource, sys, time
import numpy as np
import fluidlab_core as fl
from fluidlab_core import losses, shapes as S, materials as M
from fluidlab_core.engine.checkpoint import rollout_with_grad
N, G, MEMORY, REPEAT, ARCH = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
cfg = fl.init(arch=ARCH, precision="f32", seed=0)
sc = fl.Scene(lower=(0, 0, 0), upper=(0.1, 0.1, 0.1), grid_res=G, dt=4e-4, substeps=2 * G // 12)
water = sc.add_particles(S.Box((0.0, 0.0, 0.0), (0.1, 0.1, 0.03)), M.WATER, name="water")
sc.add_tool(S.Cylinder((0, 0, 0), 0.006, 0.06), pose=(0.05, 0.05, 0.04, 0, 0, 0, 1), softness=500.0,
            workspace=((0.02, 0.02, 0.02), (0.08, 0.08, 0.08)), action_mask=(1, 1, 0, 0, 0, 0))
sim = sc.build(requires_grad=True, grad_max_steps=200, grad_memory=MEMORY)
loss = losses.CenterOfMassDistance((0.07, 0.05, 0.01), particles=sim.handle("water").slice, steps="all")
t = np.arange(N) * sim.dt
actions = np.stack([0.05 * np.cos(20 * np.pi * t), 0.05 * np.sin(20 * np.pi * t)] + [0 * t] * 4, axis=1)
start = sim.get_state()
sim.rollout(actions[:4], loss); sim.set_state(start); sim.rollout(actions[:4], loss, grad=True)  # compile
rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
def timed(fn):  # the fastest of REPEAT runs (this machine's timings vary by +-15 %)
    best = None
    for _ in range(REPEAT):
        sim.set_state(start); t0 = time.perf_counter(); out = fn(); t = time.perf_counter() - t0
        best = t if best is None else min(best, t)
    return best, out
fwd, _ = timed(lambda: sim.rollout(actions, loss))
dfwd, _ = timed(lambda: rollout_with_grad(sim.diff, start, sim._action_sequence(actions), loss, grad=False))
both, res = timed(lambda: sim.rollout(actions, loss, grad=True))
print(json.dumps({"N": N, "particles": sim.n_particles, "forward_s": fwd, "diff_forward_s": dfwd, "fwd_bwd_s": both,
                  "segments": res.stats["segments"], "segment_steps": res.stats["segment_steps"],
                  "checkpoint_MB": res.stats["checkpoint_bytes"] / 1e6, "peak_rss_MB": resource.getrusage(
                      resource.RUSAGE_SELF).ru_maxrss / 1e3, "rss_after_compile_MB": rss_before / 1e3,
                  "grad_finite": bool(np.all(np.isfinite(res.grad_actions))), "backend": cfg.backend}))
"""


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--horizons", type=int, nargs="+", default=[100, 1000, 10000])
    ap.add_argument("--grid", type=int, default=12, help="grid cells across the 10 cm box (a multiple of 12)")
    ap.add_argument("--grad-memory", type=float, default=512e6, help="bytes for the gradient buffer (build)")
    ap.add_argument("--repeat", type=int, default=None, help="runs per timing, the fastest kept")
    ap.add_argument("--arch", default="cpu", choices=["cpu", "cuda", "auto"], help="Taichi backend (default cpu)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=root + os.pathsep + os.environ.get("PYTHONPATH", ""))
    rows = []
    for n in args.horizons:
        print(f"horizon {n} steps ...", file=sys.stderr, flush=True)
        out = subprocess.run([sys.executable, "-c", CHILD, str(n), str(args.grid), str(args.grad_memory),
                              str(args.repeat or (3 if n <= 1000 else 1)), args.arch], capture_output=True, text=True,
                             env=env)
        if out.returncode != 0:
            raise SystemExit(f"horizon {n} failed:\n{out.stderr[-3000:]}")
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    sub = 2 * args.grid // 12
    lines = [f"gradient benchmark: {rows[0]['particles']} particles, {args.grid}^3 grid, {sub} substeps of "
             f"{0.4 / sub:.2g} ms per step, float32, {rows[0]['backend'].upper()} "
             f"({os.cpu_count()} CPU cores), gradient buffer {args.grad_memory / 1e6:.0f} MB, {time.strftime('%Y-%m-%d')}",
             "| steps | segments x steps | fast fwd (s) | diff fwd (s) | fwd+bwd (s) | fwd+bwd / fast fwd | "
             "fwd+bwd / diff fwd | checkpoints (MB) | peak RSS (MB) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['N']} | {r['segments']} x {r['segment_steps']} | {r['forward_s']:.2f} | "
                     f"{r['diff_forward_s']:.2f} | {r['fwd_bwd_s']:.2f} | {r['fwd_bwd_s'] / r['forward_s']:.2f} | "
                     f"{r['fwd_bwd_s'] / r['diff_forward_s']:.2f} | {r['checkpoint_MB']:.1f} | {r['peak_rss_MB']:.0f} |")
    text = "\n".join(lines)
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()
