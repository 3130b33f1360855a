"""The gas pressure solve (engine/poisson.py): does it give the same bits on every run, and what does a solve cost,
in this tree and in an earlier revision, in alternating child processes.

    python bench/poisson_determinism.py [--rev a147a91] [--n 64] [--rounds 3] [--repeats 6] [--threads 2]
        [--load 2]

Each child builds a closed cube of n³ gas cells (one closed region, so the compatibility step's region sums run)
with a box of solid cells inside, draws a random right-hand side (seed 0), solves it to a relative residual of 1e-6
`--repeats` times and reports the median seconds per solve, the iterations, and how many distinct solutions (by
their bytes) the repeats gave. `--load` busy processes run beside the children (the test suite's second worker and
more), which is when a parallel reduction's order changes. The earlier revision is checked out into a temporary
git worktree and imported from there; the child's code is this file's `child` (the solver's API is the same).
Output: bench/results/poisson_determinism.txt.
"""
import argparse
import hashlib
import json
import multiprocessing as mp
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def child(n: int, repeats: int, threads: int) -> dict:
    import numpy as np
    import taichi as ti

    ti.init(arch=ti.cpu, cpu_max_num_threads=threads, offline_cache=True)
    from fluidlab_core.engine.poisson import FLUID, SOLID, PoissonSolver

    solver = PoissonSolver((n, n, n), (False,) * 6)
    flags = np.full((n, n, n), FLUID, np.int8)
    flags[n // 4: n // 2, n // 4: n // 2, n // 3: 2 * n // 3] = SOLID
    solver.flags[0].from_numpy(flags)
    solver.update_flags(flags)
    rhs = np.random.default_rng(0).standard_normal((n, n, n)) * (flags == FLUID)
    seconds, digests, iterations = [], set(), []
    for _ in range(repeats + 1):  # the first compiles
        solver.b.from_numpy(rhs)
        t0 = time.perf_counter()
        rep = solver.solve(1e-6, 500)
        seconds.append(time.perf_counter() - t0)
        iterations.append(rep["iterations"])
        digests.add(hashlib.sha1(solver.x.to_numpy().tobytes()).hexdigest())
    return {"seconds": statistics.median(seconds[1:]), "iterations": sorted(set(iterations)),
            "distinct_solutions": len(digests), "residual": rep["residual"]}


def _busy():
    while True:
        pass


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rev", default="a147a91", help="the earlier revision (before the fixed-order sums)")
    ap.add_argument("--n", type=int, default=64)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=6)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--load", type=int, default=2, help="busy processes beside the children")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        print(json.dumps(child(a.n, a.repeats, a.threads)))
        return
    with tempfile.TemporaryDirectory() as tmp:
        old = Path(tmp) / "old"
        subprocess.run(["git", "worktree", "add", "--detach", str(old), a.rev], cwd=ROOT, check=True,
                       capture_output=True)
        busy = [mp.Process(target=_busy, daemon=True) for _ in range(a.load)]
        for b in busy:
            b.start()
        try:
            runs = {"before": [], "after": []}
            for r in range(a.rounds):
                for label, tree in (("before", old), ("after", ROOT)):
                    env = dict(os.environ, PYTHONPATH=str(tree))
                    out = subprocess.run([sys.executable, __file__, "--child", tree.as_posix(), "--n", str(a.n),
                                          "--repeats", str(a.repeats), "--threads", str(a.threads)],
                                         env=env, capture_output=True, text=True, cwd=str(tree))
                    if out.returncode != 0:
                        raise SystemExit(out.stderr[-3000:])
                    res = json.loads(out.stdout.strip().splitlines()[-1])
                    runs[label].append(res)
                    print(f"round {r + 1} {label}: {res}", flush=True)
        finally:
            for b in busy:
                b.terminate()
            subprocess.run(["git", "worktree", "remove", "--force", str(old)], cwd=ROOT, capture_output=True)
    lines = [f"Pressure solve, closed {a.n}^3 cube with a solid box, tolerance 1e-6, {a.threads} Taichi threads, "
             f"{a.load} busy processes beside; {a.rounds} alternating rounds of {a.repeats} solves each "
             f"(python bench/poisson_determinism.py, {time.strftime('%Y-%m-%d')})",
             f"before = {a.rev} (parallel reductions), after = this tree (fixed-order sums)"]
    for label in ("before", "after"):
        rs = runs[label]
        lines.append(f"{label:6s}: median s/solve {statistics.median(r['seconds'] for r in rs):.4f}; iterations "
                     f"{sorted({i for r in rs for i in r['iterations']})}; distinct solutions per round "
                     f"{[r['distinct_solutions'] for r in rs]} (of {a.repeats + 1})")
    ratio = statistics.median(r['seconds'] for r in runs['after']) / statistics.median(r['seconds'] for r in runs['before'])
    lines.append(f"after/before time per solve: {ratio:.2f}")
    text = "\n".join(lines) + "\n"
    print(text)
    out = ROOT / "bench" / "results" / "poisson_determinism.txt"
    out.write_text(text)


if __name__ == "__main__":
    main()
