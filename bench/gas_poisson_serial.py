"""The gas pressure solve's serial loops on small grids (engine/poisson.py, "Small grids"): AirCirculation's step
with them and without them (FLUIDLAB_POISSON_SERIAL_CELLS=0), at each size, on the CPU.

    python bench/gas_poisson_serial.py [--sizes small medium paper] [--steps 40 20 6] [--rounds 2]

Each (size, setting) runs in a fresh process (the threshold is read when the solver is built): the task's house,
the conditioner turning at 0.8 rad/s, a few warm-up steps (which compile), then `--steps` timed steps; the wall
time per step, the pressure solves' share of it and the CG iterations per step are reported, the median over
`--rounds` alternating rounds. Each process also prints its loss after the timed steps (the task's loss over
them) as hex, which must be the same bits with and without the serial loops. Appends its table to
bench/results/gas_poisson_serial_cpu.txt.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
from datetime import date
from pathlib import Path

from results_file import append_table  # bench/results_file.py (this script's folder is on the path)

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, sys, time
import numpy as np
from fluidlab_core import tasks
from fluidlab_core.engine import poisson
size, steps = sys.argv[1], int(sys.argv[2])
acc = {"t": 0.0, "it": 0}
solve = poisson.PoissonSolver.solve
def timed(self, tol, max_iterations):
    t = time.perf_counter()
    out = solve(self, tol, max_iterations)
    acc["t"] += time.perf_counter() - t
    acc["it"] += out["iterations"]
    return out
poisson.PoissonSolver.solve = timed
task = tasks.make("AirCirculation", size)
sim = task.simulator()
task.reset(sim)
twists = task.twists(np.full((steps + 3, 1), 0.8))
for k in range(3):
    sim.step(twists[k])
acc.update(t=0.0, it=0)
t = time.perf_counter()
for k in range(3, steps + 3):
    sim.step(twists[k])
wall = time.perf_counter() - t
solve_s, iterations = acc["t"], acc["it"]
task.reset(sim)
loss = sim.rollout(twists[:steps], task.loss(steps)).loss
print(json.dumps({"shape": list(task.scene().gas.shape), "ms_per_step": wall / steps * 1e3,
                  "solve_share": solve_s / wall, "cg_per_step": iterations / steps, "loss": float(loss).hex()}))
"""


def run(size: str, steps: int, serial: bool) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    if not serial:
        env["FLUIDLAB_POISSON_SERIAL_CELLS"] = "0"
    else:
        env.pop("FLUIDLAB_POISSON_SERIAL_CELLS", None)
    out = subprocess.run([sys.executable, "-c", CHILD, size, str(steps)], env=env, capture_output=True, text=True,
                         timeout=3600)
    if out.returncode != 0:
        raise RuntimeError(f"{size} (serial={serial}) failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", nargs="+", default=["small", "medium", "paper"])
    ap.add_argument("--steps", nargs="+", type=int, default=[40, 20, 6], help="timed steps per size")
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    if len(args.steps) != len(args.sizes):
        raise SystemExit(f"--steps needs one count per size ({len(args.sizes)}), got {len(args.steps)}")
    from fluidlab_core.engine.poisson import SERIAL_CELLS

    lines = [f"# bench/gas_poisson_serial.py --sizes {' '.join(args.sizes)} --steps {' '.join(map(str, args.steps))} "
             f"--rounds {args.rounds}; {platform.machine()}, CPU, {os.cpu_count()} cores, default threads, "
             f"{date.today()}",
             f"# serial loops on levels of at most {SERIAL_CELLS} cells against none (FLUIDLAB_POISSON_SERIAL_CELLS=0);"
             " medians over the rounds",
             f"{'size':8s} {'gas cells':>14s} {'ms/step off':>12s} {'ms/step on':>11s} {'on/off':>7s} "
             f"{'solve share off/on':>19s} {'CG it/step':>11s} same loss bits"]
    for size, steps in zip(args.sizes, args.steps):
        res = {False: [], True: []}
        for _ in range(args.rounds):
            for serial in (False, True):
                r = run(size, steps, serial)
                res[serial].append(r)
                print(f"{size} serial={serial}: {r}", flush=True)
        off = statistics.median(r["ms_per_step"] for r in res[False])
        on = statistics.median(r["ms_per_step"] for r in res[True])
        share = (statistics.median(r["solve_share"] for r in res[False]),
                 statistics.median(r["solve_share"] for r in res[True]))
        same = len({r["loss"] for r in res[False] + res[True]}) == 1
        shape = "x".join(map(str, res[True][0]["shape"]))
        lines.append(f"{size:8s} {shape:>14s} {off:12.1f} {on:11.1f} {on / off:7.2f} "
                     f"{share[0]:9.0%} / {share[1]:4.0%} {res[True][0]['cg_per_step']:11.1f} {same}")
    print("\n".join(lines))
    append_table(ROOT / "bench" / "results" / "gas_poisson_serial_cpu.txt", lines)


if __name__ == "__main__":
    main()
