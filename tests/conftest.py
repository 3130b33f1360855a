"""Shared test set-up: the CPU backend in float32 (what users run by default), initialised once."""
import numpy as np
import pytest

import fluidlab_core


@pytest.fixture(scope="session", autouse=True)
def taichi_cpu():
    fluidlab_core.init(arch="cpu", precision="f32", seed=0)
    yield


def report(title: str, **numbers):
    """Print the figures a physics test measured, so that they show in the test output (pytest -s / -rA)."""
    parts = ", ".join(f"{k}={v:.4g}" if isinstance(v, (float, np.floating)) else f"{k}={v}" for k, v in numbers.items())
    print(f"\n[{title}] {parts}")
