"""The RL baselines (optim/rl.py): SAC and PPO from Stable-Baselines3 on the Gymnasium environment.

What is checked: the environment's per-step share of the task loss adds up to the loss the reference evaluation
gives the same actions (so RL is judged on the same loss as the other methods); a run keeps to its budget to the
step (PPO's whole-update rounding would overrun it); the trajectory returned is the best episode's; the same
seed gives the same run; and a missing install is named.
"""
import sys

import numpy as np
import pytest

import fluidlab_core
from fluidlab_core import optim, tasks

pytest.importorskip("stable_baselines3", reason="the rl extra is part of the test extras")

ROLLOUTS = 5


@pytest.fixture(scope="module")
def task():
    fluidlab_core.init(arch="cpu", precision="f32")
    return tasks.make("LatteArtStir", size="small")


def test_env_task_loss_sums_to_the_reference_evaluation(task):
    import gymnasium as gym

    import fluidlab_core.envs  # noqa: F401 - registers the ids

    env = gym.make("FluidLab/LatteArtStir-v0", size="small", task=task)
    env.reset(seed=0)
    rng = np.random.default_rng(3)
    actions = rng.uniform(-task.max_tool_speed, task.max_tool_speed, (task.horizon, task.n_actions))
    total = 0.0
    for a in actions:
        _, _, _, truncated, info = env.step(a)
        total += info["task_loss"]
    assert truncated
    ref = task.evaluate(actions)["loss"]
    print(f"\nepisode task loss from the env {total:.6e}, reference evaluation {ref:.6e}")
    assert total == pytest.approx(ref, rel=1e-6)


@pytest.mark.parametrize("method", ["sac", "ppo"])
def test_rl_run_keeps_its_budget_and_returns_its_best_episode(task, method):
    budget = ROLLOUTS * task.horizon
    seen = []
    traj = optim.optimise(task, method, budget, seed=0, callback=lambda p: seen.append(p) and False)
    meta = traj.metadata
    print(f"\n{method}: episode losses {[f'{p.loss:.3e}' for p in seen]}, final {meta['final_loss']:.4e}")
    assert meta["steps_used"] == budget  # PPO's rollout of 4 episodes would round 4 training episodes up to 8
    assert [p.steps for p in seen] == [task.horizon * (i + 1) for i in range(ROLLOUTS)]
    assert meta["settings"]["episodes"] == ROLLOUTS
    # the returned trajectory is the best episode (training or deterministic), re-run on the reference physics
    assert meta["final_loss"] == pytest.approx(min(p.loss for p in seen), rel=1e-5)
    assert seen[-1].best_loss == pytest.approx(meta["final_loss"], rel=1e-5)
    actions, _ = task.actions_from_trajectory(traj)
    assert np.all(np.abs(actions) <= task.max_tool_speed + 1e-9)
    assert traj.loss_history == pytest.approx([p.loss for p in seen], rel=1e-9)
    # the same seed explores the same first episode
    again = optim.optimise(task, method, 2 * task.horizon, seed=0)
    assert again.loss_history[0] == pytest.approx(seen[0].loss, rel=1e-5)


def test_missing_sb3_is_named(task, monkeypatch):
    from fluidlab_core.optim import rl

    monkeypatch.setitem(sys.modules, "stable_baselines3", None)
    with pytest.raises(ImportError, match=r"pip install"):
        rl.run(task, "sac", task.horizon, seed=0)


def test_pods_steps_downhill_and_keeps_its_budget(task):
    """PODS (optim/pods.py): its improved actions lower the task loss on the reference physics (the gradient's
    sign and the step are right), a run spends two rollouts per iteration and never more than its budget, and
    it returns its best episode."""
    from fluidlab_core.optim import pods

    seen = []
    budget = 5 * task.horizon  # two iterations of two rollouts; the fifth rollout cannot hold a third
    traj = optim.optimise(task, "pods", budget, seed=0, callback=lambda p: seen.append(p) and False)
    assert [p.steps for p in seen] == [2 * task.horizon, 4 * task.horizon]
    assert traj.metadata["steps_used"] == 4 * task.horizon
    assert traj.metadata["final_loss"] == pytest.approx(min(p.loss for p in seen), rel=1e-5)
    first = seen[0].parametrisation.actions(seen[0].best_theta)  # the first episode's actions
    gsim = task.simulator(grad=True, contact="hard")
    task.reset(gsim)
    res = gsim.rollout(task.twists(first), task.loss(task.horizon), grad=True)
    improved = pods.improve(first, res.grad_actions[:, 0, list(task.action_axes)], task.max_tool_speed)
    before, after = task.evaluate(first)["loss"], task.evaluate(improved)["loss"]
    print(f"\nPODS: first episode loss {before:.4e}, after the gradient step {after:.4e}")
    assert after < before
    assert np.all(np.abs(improved) <= task.max_tool_speed)
    with pytest.raises(ValueError, match="two rollouts"):
        optim.optimise(task, "pods", task.horizon, seed=0)
