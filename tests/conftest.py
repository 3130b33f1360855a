"""Shared test set-up: the engine on the CPU in float32 (what users run by default), initialised once.

FLUIDLAB_TEST_ARCH=cuda runs the whole suite with the engine on CUDA instead (the gradient tests switch to
float64 on the same backend).

The suite compiles the solvers' forward kernels fast (FLUIDLAB_FAST_COMPILE=1, fluidlab_core/runtime.py; set
here unless the caller set it, and inherited by the nodes and command lines the tests start): its time is mostly
compilation, of simulators too small for the kernels' speed to matter (`bench/fast_compile.py`).
FLUIDLAB_FAST_COMPILE=0 before the test command runs it as users run by default.

Scheduling: the README's command hands whole files to two processes (pytest-xdist's loadfile). By default xdist
queues the files with the most tests first, which put the few-but-heavy files (the gas's gradients) last and left
one process idle for the last ~110 s of a 1398 s run (2026-12-05: 2450 CPU-seconds over two processes). Here the
files are queued heaviest first instead (longest-processing-time first), by the per-file seconds in
tests/file_seconds.json, measured from a cold Taichi cache as CI runs it; a file not listed there counts as the
listed files' median. `bash bench/suite_time.sh cold` refreshes the table (pytest's --record-file-seconds: the
files a run ran are written at its end, the others kept).

Markers: `cpu_only` for tests of the CPU's own code paths (per-thread grid copies, thread counts), skipped on
CUDA; `cuda` for tests that need a GPU, skipped on the CPU.
"""
import json
import os
from pathlib import Path

import numpy as np
import pytest

import fluidlab_core

TEST_ARCH = os.environ.get("FLUIDLAB_TEST_ARCH", "cpu")
if TEST_ARCH not in ("cpu", "cuda"):
    raise ValueError(f"FLUIDLAB_TEST_ARCH must be cpu or cuda, got {TEST_ARCH!r}")
os.environ.setdefault("FLUIDLAB_FAST_COMPILE", "1")


TESTS = Path(__file__).parent
FILE_SECONDS = TESTS / "file_seconds.json"  # {file relative to tests/: seconds of its setup, calls and teardown}
_recorded: dict[str, float] = {}
_root = [Path.cwd()]  # pytest's rootdir, which node ids are relative to (set by pytest_configure)


def pytest_addoption(parser):
    parser.addoption("--record-file-seconds", action="store_true",
                     help=f"write each test file's seconds to {FILE_SECONDS} at the end (the order the files are "
                          "queued in)")


def pytest_configure(config):
    config.addinivalue_line("markers", "cpu_only: tests the CPU's own code paths; skipped with FLUIDLAB_TEST_ARCH=cuda")
    config.addinivalue_line("markers", "cuda: needs a CUDA device; run with FLUIDLAB_TEST_ARCH=cuda")
    _root[0] = Path(config.rootpath)
    if hasattr(config.option, "loadscopereorder"):  # xdist: keep the heaviest-first order made below
        config.option.loadscopereorder = False


def _test_file(path_or_nodeid) -> str:
    path = Path(str(path_or_nodeid).split("::")[0])
    if not path.is_absolute():
        path = _root[0] / path
    try:
        return path.resolve().relative_to(TESTS).as_posix()
    except ValueError:
        return path.as_posix()


def pytest_collection_modifyitems(config, items):
    for item in items:
        if TEST_ARCH == "cuda" and "cpu_only" in item.keywords:
            item.add_marker(pytest.mark.skip(reason="a CPU code path (FLUIDLAB_TEST_ARCH=cuda)"))
        if TEST_ARCH != "cuda" and "cuda" in item.keywords:
            item.add_marker(pytest.mark.skip(reason="needs CUDA: FLUIDLAB_TEST_ARCH=cuda on a GPU machine"))
    # the heaviest files first, each file's tests in their own order (module docstring, "Scheduling")
    seconds = json.loads(FILE_SECONDS.read_text()) if FILE_SECONDS.exists() else {}
    default = float(np.median(list(seconds.values()))) if seconds else 0.0
    first: dict[str, int] = {}
    for i, item in enumerate(items):
        first.setdefault(_test_file(item.path), i)
    rank = {id(item): i for i, item in enumerate(items)}
    items.sort(key=lambda it: (-seconds.get(_test_file(it.path), default), first[_test_file(it.path)], rank[id(it)]))


def pytest_runtest_logreport(report):
    name = _test_file(report.nodeid)
    _recorded[name] = _recorded.get(name, 0.0) + report.duration


def pytest_sessionfinish(session, exitstatus):
    config = session.config
    if config.getoption("--record-file-seconds") and not hasattr(config, "workerinput") and _recorded:
        table = json.loads(FILE_SECONDS.read_text()) if FILE_SECONDS.exists() else {}
        table.update({k: round(v, 1) for k, v in _recorded.items()})  # a partial run updates its own files
        table = dict(sorted(table.items(), key=lambda kv: -kv[1]))
        tmp = FILE_SECONDS.with_suffix(".tmp")
        tmp.write_text(json.dumps(table, indent=1) + "\n")
        tmp.replace(FILE_SECONDS)


def init(precision: str = "f32"):
    """The suite's backend (FLUIDLAB_TEST_ARCH) in the given precision, seed 0."""
    return fluidlab_core.init(arch=TEST_ARCH, precision=precision, seed=0)


@pytest.fixture(scope="session", autouse=True)
def taichi_backend():
    init("f32")
    yield


def fresh(fn, *args, **kwargs):
    """fn(*args, **kwargs) right after a reset of Taichi (fluidlab_core.runtime.reset). For a test that builds the same
    scene several times over (a sweep of a parameter that is state, not structure), keeping only numbers from each:
    after a reset the scene's fields get the same identities each time, so from the second build on its kernels
    load from Taichi's offline cache instead of compiling again (the held disc's scene: 3.5 s to 1.1 s a run).
    Simulators built before, in this test or in a fixture, are invalid afterwards, and so are those that test files
    keep in module-level caches (test_tasks.py's _SMALL, test_air_circulation.py's _TASK): safe under the README's
    `--dist loadfile`, where a file's tests run together in one worker, not where a worker interleaves files."""
    fluidlab_core.runtime.reset()
    return fn(*args, **kwargs)


def report(title: str, **numbers):
    """Print the figures a physics test measured, so that they show in the test output (pytest -s / -rA)."""
    parts = ", ".join(f"{k}={v:.4g}" if isinstance(v, (float, np.floating)) else f"{k}={v}" for k, v in numbers.items())
    print(f"\n[{title}] {parts}")
