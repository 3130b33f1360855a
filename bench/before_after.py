"""The engine before and after a change, on this machine: forward throughput (bench_mpm.py) and forward +
backward time (bench_grad.py) of an earlier revision and of the working tree, in alternating runs.

    python bench/before_after.py --rev 135a8dc [--rounds 3] [--particles 20000 50000 100000]
                                 [--horizons 100 1000] [--out bench/results/before_after_cpu.txt]

The earlier revision is checked out into a temporary git worktree; each benchmark runs that tree's own copy of
the script (its API may differ) in a child process, alternating before/after `--rounds` times so that the
machine's drift (other load, thermal state) falls on both. Reported: the median of the rounds for each figure,
and the after/before ratio (forward throughput: higher is better; times: lower is better).
"""
import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(tree: Path, args: list[str]) -> str:
    env = dict(os.environ, PYTHONPATH=str(tree))
    out = subprocess.run([sys.executable, *args], cwd=str(tree), env=env, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"{' '.join(args)} failed in {tree}:\n{out.stderr[-3000:]}")
    return out.stdout


def forward(tree: Path, particles) -> dict:
    """{particles: M particle-substeps/s} from bench_mpm.py's table (Genesis skipped)."""
    text = _run(tree, ["bench/bench_mpm.py", "--steps", "5", "--particles", *map(str, particles)])
    rows = {}
    for line in text.splitlines():
        m = re.match(r"\s*(\d+)\s+([0-9.]+)\s+", line)
        if m:
            rows[int(m.group(1))] = float(m.group(2))
    return rows


def gradient(tree: Path, horizons, scratch: Path) -> dict:
    """{horizon: (fast forward s, fwd+bwd s)} from bench_grad.py's table."""
    out = scratch / "grad.txt"
    _run(tree, ["bench/bench_grad.py", "--horizons", *map(str, horizons), "--out", str(out)])
    rows = {}
    for line in out.read_text().splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if len(cells) > 5 and cells[0].isdigit():
            rows[int(cells[0])] = (float(cells[2]), float(cells[4]))
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rev", required=True, help="the earlier revision (a commit, tag or branch)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--particles", type=int, nargs="+", default=[20_000, 50_000, 100_000])
    ap.add_argument("--horizons", type=int, nargs="+", default=[100, 1000])
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "before_after_cpu.txt"))
    args = ap.parse_args()
    rev = subprocess.run(["git", "rev-parse", "--short", args.rev], cwd=ROOT, capture_output=True, text=True,
                         check=True).stdout.strip()
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                          check=True).stdout.strip()
    scratch = Path(tempfile.mkdtemp(prefix="before-after-"))
    before = scratch / "before"
    subprocess.run(["git", "worktree", "add", "--detach", str(before), rev], cwd=ROOT, check=True,
                   capture_output=True)
    trees = {"before": before, "after": ROOT}
    fwd = {k: [] for k in trees}
    grad = {k: [] for k in trees}
    # bench_mpm.py writes its table into its tree's bench/results: keep this tree's as it was
    kept = {p: p.read_bytes() for p in (ROOT / "bench" / "results").glob("mpm_forward_*.txt")}
    try:
        for r in range(args.rounds):
            for name, tree in (trees.items() if r % 2 == 0 else reversed(list(trees.items()))):
                print(f"round {r + 1}/{args.rounds}: {name} ...", file=sys.stderr, flush=True)
                fwd[name].append(forward(tree, args.particles))
                grad[name].append(gradient(tree, args.horizons, scratch))
    finally:
        for p, data in kept.items():
            p.write_bytes(data)
        subprocess.run(["git", "worktree", "remove", "--force", str(before)], cwd=ROOT, capture_output=True)
        shutil.rmtree(scratch, ignore_errors=True)

    def med(runs, key, i=None):
        return statistics.median(r[key] if i is None else r[key][i] for r in runs)

    lines = [f"before = {rev}, after = {head} + working tree; {args.rounds} alternating rounds, medians; "
             f"CPU ({os.cpu_count()} cores), float32; {time.strftime('%Y-%m-%d')}",
             "| benchmark | before | after | after / before |", "|---|---|---|---|"]
    for n in sorted(fwd["before"][0]):
        b, a = med(fwd["before"], n), med(fwd["after"], n)
        lines.append(f"| forward, {n} particles (M particle-substeps/s, higher is better) | {b:.2f} | {a:.2f} | "
                     f"{a / b:.2f} |")
    for h in sorted(grad["before"][0]):
        for i, what in ((0, "fast forward"), (1, "forward + backward")):
            b, a = med(grad["before"], h, i), med(grad["after"], h, i)
            lines.append(f"| {what}, {h} steps (s, lower is better) | {b:.2f} | {a:.2f} | {a / b:.2f} |")
    text = "\n".join(lines)
    print(text)
    Path(args.out).write_text(text + "\n" + json.dumps({"forward": fwd, "gradient": grad}) + "\n")
    print(f"wrote {args.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
