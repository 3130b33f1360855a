"""Where a test run's time goes into compiling: each Taichi kernel instance's first launch timed (its compile, and one
run of a kernel that is small at the suite's sizes), summed per test file and per kernel.

As a pytest plugin (both pytest-xdist processes load it; each writes its own JSON when it ends):

    TI_OFFLINE_CACHE_FILE_PATH=$(mktemp -d) PYTHONPATH=bench COMPILE_PROFILE_DIR=/tmp/cp \\
        .venv/bin/python -m pytest -q -n 2 --dist loadfile -p compile_profile tests
    python bench/compile_profile.py /tmp/cp ["a note on the run"]   # the table: bench/results/compile_profile_cpu.txt

A kernel instance is Taichi's (kernel, template arguments) pair: a scene built again, or with other fields, compiles
its kernels again. Processes that the tests start (the command line, the ROS nodes) are not counted.
"""
import collections
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
_per_file = collections.Counter()
per_kernel = collections.Counter()  # first-launch seconds by 'qualname[autodiff mode]'
_count = collections.Counter()
_seen = set()
_current = ["(outside a test)"]


def install():
    """Wrap Taichi's kernel launch so that each kernel instance's first launch adds its seconds to per_kernel
    (and to the current test file's)."""
    from taichi.lang import kernel_impl

    launch = kernel_impl.Kernel.__call__

    def first_launch_timed(self, *args, **kwargs):
        try:
            key = (id(self), self.mapper.lookup(kernel_impl._process_args(self, args, kwargs))[0])
        except Exception:  # let Taichi raise its own error
            return launch(self, *args, **kwargs)
        if key in _seen:
            return launch(self, *args, **kwargs)
        _seen.add(key)
        t = time.perf_counter()
        try:
            return launch(self, *args, **kwargs)
        finally:
            dt = time.perf_counter() - t
            name = f"{getattr(self.func, '__qualname__', self.func)}[{self.autodiff_mode.name}]"
            per_kernel[name] += dt
            _count[name] += 1
            _per_file[_current[0]] += dt

    kernel_impl.Kernel.__call__ = first_launch_timed


def pytest_configure(config):
    install()


def pytest_runtest_logstart(nodeid, location):
    _current[0] = nodeid.split("::")[0]


def pytest_sessionfinish(session):
    out = Path(os.environ.get("COMPILE_PROFILE_DIR", ROOT / "bench" / "results" / "compile_profile"))
    out.mkdir(parents=True, exist_ok=True)
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    (out / f"first_launches_{worker}.json").write_text(json.dumps(
        {"per_file": _per_file, "per_kernel": per_kernel, "count": _count}, indent=1))


def summarise(folder: Path, out: Path, note: str = "", top: int = 40):
    per_file, per_kernel, count = collections.Counter(), collections.Counter(), collections.Counter()
    files = sorted(folder.glob("first_launches_*.json"))
    if not files:
        raise SystemExit(f"no first_launches_*.json in {folder}: run the tests with -p compile_profile first")
    for f in files:
        d = json.loads(f.read_text())
        per_file.update(d["per_file"])
        per_kernel.update(d["per_kernel"])
        count.update(d["count"])
    total = sum(per_file.values())
    lines = [f"# bench/compile_profile.py {folder} ({len(files)} processes); summarised {date.today()}"]
    lines += [f"# {note}"] if note else []
    lines += [
             f"first launches (compiles) in all: {total:.0f} s over {sum(count.values())} kernel instances",
             "", "seconds  test file"]
    lines += [f"{v:7.1f}  {k}" for k, v in per_file.most_common()]
    lines += ["", f"seconds  instances  kernel [autodiff mode] (the {top} largest)"]
    lines += [f"{v:7.1f}  {count[k]:9d}  {k}" for k, v in per_kernel.most_common(top)]
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"wrote {out}")


def run_child(script: Path, tree: Path, arg: str) -> dict:
    """`script --child arg` in a fresh process on `tree`'s package (PYTHONPATH, working directory) with an empty
    Taichi cache and fast compilation, as the test suite compiles; its last line of output, as JSON."""
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, PYTHONPATH=str(tree), TI_OFFLINE_CACHE_FILE_PATH=cache, FLUIDLAB_FAST_COMPILE="1")
        out = subprocess.run([sys.executable, str(script), "--child", arg], cwd=str(tree), env=env,
                             capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f"child on {tree} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def before_after(script: Path, cases: list, rev: str | None, rounds: int, figures: list, out: Path,
                 same=None) -> None:
    """The compile benchmarks' driver (bench/gas_compile.py, bench/dp_compile.py): run_child(script, tree, case)
    for each case, for this tree ("after") and, with `rev`, that revision ("before", checked out into a temporary
    git worktree), alternating, `rounds` times; then a table of each figure's median per tree (and after/before)
    into `out`. same(after_runs, before_runs) -> str, if given, adds a line per case (what must not change)."""
    trees = {"after": ROOT}
    tmp = None
    if rev:
        tmp = Path(tempfile.mkdtemp()) / "before"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tmp), rev], check=True,
                       capture_output=True)
        trees = {"before": tmp, "after": ROOT}
    results = {(name, case): [] for name in trees for case in cases}
    try:
        for r in range(rounds):
            for case in cases:
                for name, tree in trees.items():
                    res = run_child(script, tree, case)
                    results[(name, case)].append(res)
                    print(f"round {r + 1}/{rounds} {case:<15} {name:<6} " + ", ".join(
                        f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in res.items()), flush=True)
    finally:
        if tmp is not None:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tmp)], capture_output=True)
            shutil.rmtree(tmp.parent, ignore_errors=True)
    head = subprocess.run(["git", "-C", str(ROOT), "describe", "--always", "--dirty"], capture_output=True,
                          text=True).stdout.strip()
    lines = [f"# bench/{Path(script).name}{' --rev ' + rev if rev else ''} --rounds {rounds}; after = {head}; "
             f"{platform.machine()}, {os.cpu_count()} cores, {date.today()}; medians, empty Taichi cache per run, "
             "FLUIDLAB_FAST_COMPILE=1", f"{'case':<16}{'figure':<26}" + "".join(f"{n:>10}" for n in trees)
             + ("     after/before" if rev else "")]
    for case in cases:
        for fig in figures:
            med = {n: statistics.median(x[fig] for x in results[(n, case)]) for n in trees}
            line = f"{case:<16}{fig:<26}" + "".join(f"{med[n]:10.3g}" for n in trees)
            if rev:
                line += f"{med['after'] / med['before']:17.2f}"
            lines.append(line)
        if rev and same is not None:
            lines.append(f"{case:<16}{same(results[('after', case)], results[('before', case)])}")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def before_after_cli(doc: str, script: Path, child, case_flag: str, cases: list, figures: list, out: Path,
                     same=None) -> None:
    """The command line of a compile benchmark built on before_after: --rev, --rounds, `case_flag` (the cases, default
    `cases`), --out (default `out`); with the hidden --child CASE, child(CASE)'s dict printed as JSON (run_child)."""
    import argparse

    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--rev", help="an earlier revision to compare with (checked out into a temporary worktree)")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument(case_flag, dest="cases", nargs="+", default=cases, metavar=case_flag.lstrip("-").upper())
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--out", default=str(out))
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.child)))
        return
    before_after(script, args.cases, args.rev, args.rounds, figures, Path(args.out), same)


if __name__ == "__main__":
    if len(sys.argv) < 2 or sys.argv[1] in ("-h", "--help"):
        print(__doc__)
        raise SystemExit(0 if len(sys.argv) >= 2 else 2)
    summarise(Path(sys.argv[1]), ROOT / "bench" / "results" / "compile_profile_cpu.txt",
              sys.argv[2] if len(sys.argv) > 2 else "")
