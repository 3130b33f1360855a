"""Extending the engine from outside the package (docs/extending.md): a constitutive model with six named
parameters and a task, both in tests/extension/, run through the engine, gradients, the task registry,
Gymnasium and the `fluidlab` command without editing fluidlab_core. (sim_node's side: tests/ros/test_extension_node.py.)
"""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import fluidlab_core as fl
from tests import conftest
from fluidlab_core import losses
from tests.conftest import report
from tests.extension import toy_material
from tests.extension.toy_material import GEL

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def f64():
    conftest.init("f64")
    yield
    conftest.init("f32")


@pytest.fixture
def toy_task():
    """ToyPush registered for the test, and taken out again (other test files in this process list the
    paper's tasks alone)."""
    from fluidlab_core import tasks
    from tests.extension import toy_task as module

    tasks.register(module.ToyPush)
    yield module.ToyPush
    tasks.unregister("ToyPush")


def test_a_model_with_six_named_parameters_gets_each_of_them(f64):
    """The stress the engine computes for the toy model equals the law evaluated in numpy, for deformations
    and velocity gradients that make every parameter count (j_min among them: some particles are compressed
    below it)."""
    scene = fl.Scene(lower=(0, 0, 0), upper=(0.04, 0.04, 0.04), grid_res=8, dt=1e-4, substeps=2,
                     gravity=(0, 0, 0))
    body = scene.add_particles(fl.Box((0.01, 0.01, 0.01), (0.03, 0.03, 0.03)), GEL, name="gel")
    sim = scene.build()
    rng = np.random.default_rng(0)
    state = sim.get_state()
    n = body.count
    F = np.eye(3) + 0.2 * rng.normal(size=(n, 3, 3))
    F[:5] *= 0.5  # det F = 1/8 · det: under j_min = 0.2
    C = 10.0 * rng.normal(size=(n, 3, 3))
    sim.set_state(state.replace(F=F, C=C))
    J = np.linalg.det(F)
    assert (J[:5] < GEL.min_volume_ratio).any() and (J > GEL.min_volume_ratio).any()
    expected = toy_material.kirchhoff_stress(F, C, GEL.kernel_params()) / J[:, None, None]
    sigma = sim.stresses("gel")
    err = np.abs(sigma - expected).max() / np.abs(expected).max()
    report("toy model stress vs numpy", particles=n, max_rel_error=err)
    assert err < 1e-12
    np.testing.assert_allclose(sim.pressures("gel"), -np.trace(expected, axis1=1, axis2=2) / 3.0, rtol=1e-10,
                               atol=1e-9 * np.abs(expected).max())


def test_a_task_of_our_own_is_listed_optimisable_and_a_gym_environment(f64, toy_task):
    """ToyPush (tests/extension/toy_task.py) appears in the task list and as a Gymnasium id once imported; its
    differentiable rollout's action gradient matches central differences; its environment steps."""
    import gymnasium as gym

    import fluidlab_core.envs  # noqa: F401 - the ids of the tasks known so far
    from fluidlab_core import tasks

    assert "ToyPush" in tasks.names() and "FluidLab/ToyPush-v0" in gym.registry
    task = tasks.make("ToyPush", "small")
    sim = task.simulator(grad=True, contact="soft")
    rng = np.random.default_rng(3)
    actions = rng.uniform(0.02, 0.08, size=(task.horizon, 2)) * np.array([1.0, 0.3])
    task.reset(sim)
    start = sim.get_state()
    loss = task.loss() + losses.Linear(b=rng.normal(size=(sim.n_particles, 3)), steps="all")
    res = sim.rollout(task.twists(actions), loss, grad=True)
    direction = rng.normal(size=actions.shape)

    def at(eps):
        sim.set_state(start)
        return sim.rollout(task.twists(actions + eps * direction), loss).loss

    fd = (at(1e-6) - at(-1e-6)) / 2e-6
    analytic = float(np.sum(res.grad_actions[:, 0, :2] * direction))
    err = abs(fd - analytic) / abs(fd)
    report("toy task action gradient vs finite difference", fd=fd, analytic=analytic, rel_error=err)
    assert err < 5e-3

    env = gym.make("FluidLab/ToyPush-v0", size="small")
    obs, info = env.reset(seed=0)
    assert obs.shape == env.observation_space.shape == (16 * 6 + 13,)
    total = 0.0
    for _ in range(task.horizon):
        obs, reward, terminated, truncated, info = env.step(np.array([0.05, 0.0], dtype=np.float32))
        total += reward
        assert np.all(np.isfinite(obs)) and not terminated
    assert truncated and np.isfinite(total)
    env.close()


def test_the_command_line_finds_a_task_through_the_environment():
    """`fluidlab list` in another process lists ToyPush when FLUIDLAB_TASKS names its module, and names a
    module that cannot be imported."""
    env = dict(os.environ, FLUIDLAB_TASKS="tests.extension.toy_task",
               PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-m", "fluidlab_core.cli", "list"], capture_output=True, text=True,
                         env=env, cwd=str(ROOT), timeout=120)
    assert out.returncode == 0, out.stderr
    assert "ToyPush" in out.stdout and "GatheringHard" in out.stdout
    env["FLUIDLAB_TASKS"] = "no_such_module_here"
    out = subprocess.run([sys.executable, "-m", "fluidlab_core.cli", "list"], capture_output=True, text=True,
                         env=env, cwd=str(ROOT), timeout=120)
    assert out.returncode != 0 and "FLUIDLAB_TASKS" in out.stderr and "no_such_module_here" in out.stderr
