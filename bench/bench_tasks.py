"""Final loss of DP, DP-H and CMA-ES on the four tasks at the same simulation budget and seeds (mean ± std).

    python bench/bench_tasks.py [--size small] [--rollouts 15] [--seeds 0 1 2] [--jobs 2] [--out DIR]

Each run is a separate `fluidlab optimise` process (so runs can go in parallel on a many-core machine,
FLUIDLAB_CPU_THREADS=1 each); its report gives the final loss of the best parameters on the task's reference
physics (hard contact). The budget is the same number of simulated steps for every method: `--rollouts`
times the task's horizon (a DP iteration over r steps counts r steps; its backward pass costs more wall time,
reported beside). Results are written after every run, so an interrupted bench keeps what finished:
DIR/runs.jsonl, and the table to DIR/tasks_<size>.txt and stdout.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path

import numpy as np



def registered_tasks() -> list[str]:
    """Every registered task (the registry's order): a new task joins the bench without a change here."""
    from fluidlab_core import tasks

    return tasks.names()


METHODS = ("dp", "dp-h", "cma-es")
# DP ablations: a variant's name and the techniques it switches off (`fluidlab optimise --without`)
VARIANTS = {"dp-no-sharing": ["gradient_sharing"], "dp-no-attraction": ["attraction"],
            "dp-neither": ["gradient_sharing", "attraction"]}


def run_one(task, method, seed, size, budget_rollouts, out: Path, arch: str = "cpu"):
    from fluidlab_core import tasks

    horizon = tasks.make(task, size).horizon
    name = f"{task}_{method}_seed{seed}_{size}"  # names are unique across the folder (trajectory_store)
    env = dict(os.environ, FLUIDLAB_CPU_THREADS=os.environ.get("FLUIDLAB_CPU_THREADS", "1"))
    base = "dp" if method in VARIANTS else method
    cmd = [sys.executable, "-m", "fluidlab_core.cli", "optimise", task, "--method", base, "--seed", str(seed),
           "--size", size, "--budget", str(budget_rollouts * horizon), "--root", str(out / "trajectories"),
           "--name", name, "--arch", arch, "--force"]  # a bench run again into the same folder replaces its runs
    if method in VARIANTS:
        cmd += ["--without", *VARIANTS[method]]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    report_path = out / "trajectories" / task / f"{name}.report.json"
    if proc.returncode != 0 or not report_path.exists():
        return {"task": task, "method": method, "seed": seed, "error": proc.stderr[-2000:], "wall": wall}
    rep = json.loads(report_path.read_text())
    rep["wall"] = wall
    rep["method"] = method  # the variant's name
    return rep


def table(runs, size, rollouts, names=None) -> str:
    lines = [f"Final loss on the reference physics (hard contact), {size} tasks, float32 CPU, budget {rollouts} "
             f"rollouts of the horizon per run, mean ± std over seeds (n = seeds that finished); lower is better. "
             f"'zero-action' is the loss of leaving the tool still; 'wall' includes the first run's compilation.",
             f"{'task':<15} {'method':<16} {'final loss (mean ± std)':>28} {'n':>2} {'zero-action loss':>17} "
             f"{'wall s/run':>10}"]
    for task in names or sorted({r["task"] for r in runs}, key=lambda t: registered_tasks().index(t)):
        for method in [m for m in (*METHODS, *VARIANTS) if any(r["method"] == m for r in runs)]:
            ok = [r for r in runs if r["task"] == task and r["method"] == method and "final_loss" in r]
            if not ok:
                lines.append(f"{task:<15} {method:<16} {'(no finished run)':>28}")
                continue
            f = np.array([r["final_loss"] for r in ok])
            zero = ok[0].get("zero_loss", float("nan"))
            lines.append(f"{task:<15} {method:<16} {f.mean():>16.4e} ± {f.std():<9.2e} {len(ok):>2} {zero:>17.4e} "
                         f"{np.mean([r['wall'] for r in ok]):>10.0f}")
    return "\n".join(lines)


def zero_losses(size, arch: str = "cpu", names=None) -> dict:
    import fluidlab_core
    from fluidlab_core import tasks

    fluidlab_core.init(arch=arch, precision="f32")
    out = {}
    for name in names or registered_tasks():
        t = tasks.make(name, size)
        out[name] = t.evaluate(np.zeros((t.horizon, t.n_actions)), rewards=False)["loss"]
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", default="small")
    ap.add_argument("--rollouts", type=int, default=15)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--tasks", nargs="+", default=None, help="default: every registered task")
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=[*METHODS, *VARIANTS],
                    help="methods, and DP ablations: " + "; ".join(f"{k}: dp --without {' '.join(v)}"
                                                                   for k, v in VARIANTS.items()))
    ap.add_argument("--out", default="out/bench_tasks")
    ap.add_argument("--arch", default="cpu", choices=["cpu", "cuda", "auto"], help="Taichi backend (default cpu)")
    ap.add_argument("--table-only", action="store_true", help="remake the table from DIR/runs.jsonl")
    args = ap.parse_args()
    args.tasks = args.tasks or registered_tasks()
    out = Path(args.out)
    if args.table_only:
        runs = [json.loads(line) for line in open(out / "runs.jsonl")]
        zero = zero_losses(args.size, args.arch, args.tasks)
        for r in runs:
            r["zero_loss"] = zero.get(r["task"], float("nan"))
        text = table(runs, args.size, args.rollouts)
        (out / f"tasks_{args.size}.txt").write_text(text + "\n")
        print(text)
        return
    out.mkdir(parents=True, exist_ok=True)
    # gradient runs first: they take longest
    jobs = [(t, m, s) for m in args.methods for t in args.tasks for s in args.seeds]
    jobs.sort(key=lambda j: j[1] == "cma-es")
    runs = []
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        futures = {pool.submit(run_one, t, m, s, args.size, args.rollouts, out, args.arch): (t, m, s)
                   for t, m, s in jobs}
        futures[pool.submit(zero_losses, args.size, args.arch, args.tasks)] = "zero"
        zero = {}
        for fut in as_completed(futures):
            if futures[fut] == "zero":
                zero = fut.result()
                continue
            rep = fut.result()
            runs.append(rep)
            with open(out / "runs.jsonl", "a") as f:
                f.write(json.dumps(rep) + "\n")
            status = f"final {rep['final_loss']:.4e}" if "final_loss" in rep else "FAILED " + rep["error"][-300:]
            print(f"[{len(runs)}/{len(jobs)}] {rep['task']} {rep['method']} seed {rep['seed']}: {status} "
                  f"({rep['wall']:.0f} s)", flush=True)
    for r in runs:
        r["zero_loss"] = zero.get(r["task"], float("nan"))
    text = table(runs, args.size, args.rollouts)
    (out / f"tasks_{args.size}.txt").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
