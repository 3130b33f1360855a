"""Shared test set-up: the engine on the CPU in float32 (what users run by default), initialised once.

FLUIDLAB_TEST_ARCH=cuda runs the whole suite with the engine on CUDA instead (the gradient tests switch to
float64 on the same backend).

The suite compiles the solvers' forward kernels fast (FLUIDLAB_FAST_COMPILE=1, fluidlab_core/runtime.py; set
here unless the caller set it, and inherited by the nodes and command lines the tests start): its time is mostly
compilation, of simulators too small for the kernels' speed to matter (`bench/fast_compile.py`).
FLUIDLAB_FAST_COMPILE=0 before the test command runs it as users run by default.

Markers: `cpu_only` for tests of the CPU's own code paths (per-thread grid copies, thread counts), skipped on
CUDA; `cuda` for tests that need a GPU, skipped on the CPU.
"""
import os

import numpy as np
import pytest

import fluidlab_core

TEST_ARCH = os.environ.get("FLUIDLAB_TEST_ARCH", "cpu")
if TEST_ARCH not in ("cpu", "cuda"):
    raise ValueError(f"FLUIDLAB_TEST_ARCH must be cpu or cuda, got {TEST_ARCH!r}")
os.environ.setdefault("FLUIDLAB_FAST_COMPILE", "1")


def pytest_configure(config):
    config.addinivalue_line("markers", "cpu_only: tests the CPU's own code paths; skipped with FLUIDLAB_TEST_ARCH=cuda")
    config.addinivalue_line("markers", "cuda: needs a CUDA device; run with FLUIDLAB_TEST_ARCH=cuda")


def pytest_collection_modifyitems(config, items):
    for item in items:
        if TEST_ARCH == "cuda" and "cpu_only" in item.keywords:
            item.add_marker(pytest.mark.skip(reason="a CPU code path (FLUIDLAB_TEST_ARCH=cuda)"))
        if TEST_ARCH != "cuda" and "cuda" in item.keywords:
            item.add_marker(pytest.mark.skip(reason="needs CUDA: FLUIDLAB_TEST_ARCH=cuda on a GPU machine"))


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
