"""What fast compilation (`fluidlab_core.init(fast_compile=True)`, FLUIDLAB_FAST_COMPILE=1: the solvers' forward
kernels at Taichi's opt_level 0, fluidlab_core/runtime.py) costs and saves, against the default, each measured in
a fresh process with an empty Taichi cache:

- the MPM forward at 50k particles on a 64³ grid (`fluidlab_core.apps.throughput`): compile seconds and
  particle-substeps per second;
- DP on GatheringEasy at small size (the test suite's DP test): seconds to the first iteration (compilation of
  the differentiable solver) and seconds per iteration after it, then the first evaluation on the reference
  physics (compilation of the forward solver).

    python bench/fast_compile.py [--repeats 2]

Modes alternate (default, fast, default, fast, ...) so that a machine's drift does not favour one. Writes
bench/results/fast_compile_<backend>.txt with each figure's ratio fast / default.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def child(kind: str):
    import fluidlab_core

    cfg = fluidlab_core.init("cpu")
    out = {"fast_compile": cfg.fast_compile}
    if kind == "forward":
        from fluidlab_core.apps import throughput

        r = throughput.time_ours(50_000, 5)
        out.update(compile_s=r["compile"], rate=r["rate"])
    else:
        from fluidlab_core import tasks
        from fluidlab_core.optim import dp

        task = tasks.make("GatheringEasy", "small")
        stamps = []
        t0 = time.perf_counter()
        res = dp.run(task, budget=4 * task.horizon, seed=0, callback=lambda p: stamps.append(time.perf_counter()),
                     options=dp.DPOptions(expanding_region=False, attraction=False))
        par = res.parametrisation
        t1 = time.perf_counter()
        task.evaluate(par.actions(res.theta), tool_position=par.tool_position(res.theta), rewards=False)
        out.update(first_iteration_s=stamps[0] - t0, per_iteration_s=(stamps[-1] - stamps[0]) / (len(stamps) - 1),
                   first_evaluation_s=time.perf_counter() - t1)
    print("RESULT " + json.dumps(out), flush=True)


def measure(kind: str, fast: bool) -> dict:
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, TI_OFFLINE_CACHE_FILE_PATH=cache, FLUIDLAB_FAST_COMPILE="1" if fast else "0",
                   PYTHONPATH=str(ROOT))
        p = subprocess.run([sys.executable, __file__, "--child", kind], env=env, capture_output=True, text=True)
    for line in p.stdout.splitlines():
        if line.startswith("RESULT "):
            r = json.loads(line[7:])
            if r["fast_compile"] != fast:
                raise RuntimeError(f"the child ran with fast_compile={r['fast_compile']}, asked {fast}")
            return r
    raise RuntimeError(f"{kind} run failed (exit {p.returncode}):\n{p.stdout[-2000:]}\n{p.stderr[-2000:]}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--child", choices=["forward", "dp"])
    args = ap.parse_args()
    if args.child:
        return child(args.child)
    rows = {(k, f): [] for k in ("forward", "dp") for f in (False, True)}
    for rep in range(args.repeats):
        for kind in ("forward", "dp"):
            for fast in (False, True):
                r = measure(kind, fast)
                rows[(kind, fast)].append(r)
                print(f"repeat {rep + 1}/{args.repeats}, {kind}, {'fast' if fast else 'default'}: {r}", flush=True)

    def mean(kind, fast, key):
        vals = [r[key] for r in rows[(kind, fast)]]
        return sum(vals) / len(vals)

    lines = [f"fast compilation (the solvers' forward kernels at Taichi's opt_level 0) against the default; {platform.machine()}, {os.cpu_count()} cores, "
             f"{time.strftime('%Y-%m-%d')}, empty Taichi cache per run, mean of {args.repeats} alternating runs",
             f"{'figure':<46} {'default':>10} {'fast':>10} {'fast/default':>13}"]
    for kind, key, label in (("forward", "compile_s", "MPM forward 50k: compile s"),
                             ("forward", "rate", "MPM forward 50k: M particle-substeps/s"),
                             ("dp", "first_iteration_s", "DP GatheringEasy small: first iteration s"),
                             ("dp", "per_iteration_s", "DP GatheringEasy small: s per later iteration"),
                             ("dp", "first_evaluation_s", "DP GatheringEasy small: first evaluation s")):
        a, b = mean(kind, False, key), mean(kind, True, key)
        scale = 1e-6 if key == "rate" else 1.0
        lines.append(f"{label:<46} {a * scale:>10.3g} {b * scale:>10.3g} {b / a:>13.2f}")
    out = ROOT / "bench" / "results" / "fast_compile_cpu.txt"
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
