"""Model-free RL baselines: SAC and PPO (Stable-Baselines3) on the task's Gymnasium environment, as in the paper.

The agent sees the environment's observation (downsampled particle positions and velocities of each observed
body, the tool pose and twist; envs.py) and gets the paper's reward r_k = c1 − c2·ℓ_k after every step. The
environment runs the task's reference physics (hard contact), so RL trains on the physics it is judged on.

Budget. A run gets `budget` environment steps (one simulated step each), the same currency as the other
methods: `budget / horizon` episodes. The last episode of the budget is kept for the deterministic policy (the
mean action, no exploration noise).

What a run returns. The start state is deterministic, so every episode is an open-loop action sequence. The run's
result is the best of these by the task loss (the loss the other methods minimise; the environment reports each
step's share of it): every training episode, exploration noise included, and the final deterministic one. This
is generous to RL (a lucky exploratory episode counts), and it is what makes its result a trajectory that can be
shipped and executed like the others. The reward curve the paper plots is in the run's history.

Hyper-parameters (HYPERPARAMETERS below; Stable-Baselines3's defaults except where a budget of ~10⁴ steps needs
otherwise): actions are rescaled to [−1, 1] for the policy; SAC: two hidden layers of 256, learning rate 3e-4,
batch 256, τ 0.005, γ 0.99, entropy coefficient tuned, one gradient step per environment step, learning starts
after two episodes of uniform random actions. PPO: two hidden layers of 64, learning rate 3e-4, a rollout of
four episodes per update, minibatch of one episode's length, 10 epochs, γ 0.99, λ 0.95, clip 0.2.

Needs the `rl` extra: `pip install ".[rl]"` (torch, CPU build, and stable-baselines3).
"""
from __future__ import annotations

import os
import time

import numpy as np

from fluidlab_core.optim import params as P
from fluidlab_core.optim.progress import Progress, Result

RL_METHODS = ("sac", "ppo")
HYPERPARAMETERS = {
    "sac": {"learning_rate": 3e-4, "batch_size": 256, "tau": 0.005, "gamma": 0.99, "train_freq": 1,
            "gradient_steps": 1, "ent_coef": "auto", "net_arch": [256, 256], "learning_starts_episodes": 2},
    "ppo": {"learning_rate": 3e-4, "n_epochs": 10, "gamma": 0.99, "gae_lambda": 0.95, "clip_range": 0.2,
            "ent_coef": 0.0, "net_arch": [64, 64], "episodes_per_update": 4},
}


def import_sb3():
    """stable_baselines3 and torch, or an ImportError that says how to install them."""
    try:
        import stable_baselines3
        import torch
    except ImportError:
        raise ImportError("the RL baselines (sac, ppo) need torch and stable-baselines3: pip install \".[rl]\" "
                          "(or pip install torch==2.13.0 stable-baselines3==2.9.2)") from None
    return stable_baselines3, torch


def set_torch_threads(torch):
    """torch uses as many threads as the engine: fluidlab_core.init's cpu_threads (the benchmark's --threads), or
    FLUIDLAB_CPU_THREADS, or all cores."""
    from fluidlab_core import runtime

    cfg = runtime.ensure_init()
    torch.set_num_threads(int(cfg.cpu_threads or os.environ.get("FLUIDLAB_CPU_THREADS") or os.cpu_count() or 1))


def _model(method: str, env, task, budget: int, seed: int):
    sb3, _ = import_sb3()
    hp = dict(HYPERPARAMETERS[method])
    policy_kwargs = {"net_arch": hp.pop("net_arch")}
    if method == "sac":
        starts = hp.pop("learning_starts_episodes") * task.horizon
        return sb3.SAC("MlpPolicy", env, buffer_size=max(budget, 1), learning_starts=starts,
                       policy_kwargs=policy_kwargs, seed=seed, verbose=0, device="cpu", **hp)
    n_steps = hp.pop("episodes_per_update") * task.horizon
    return sb3.PPO("MlpPolicy", env, n_steps=n_steps, batch_size=task.horizon, policy_kwargs=policy_kwargs,
                   seed=seed, verbose=0, device="cpu", **hp)


def run(task, method: str, budget: int, seed: int, callback=None, max_iterations: int | None = None) -> Result:
    """Train `method` ("sac" or "ppo") for `budget` environment steps; report each finished episode to
    `callback(progress)` (one iteration per episode; True stops the run). Returns the best episode's actions as
    an open-loop Result (see the module's docstring)."""
    import gymnasium as gym

    from fluidlab_core.envs import FluidLabEnv

    if method not in RL_METHODS:
        raise ValueError(f"unknown RL method {method!r}; RL methods: {', '.join(RL_METHODS)}")
    sb3, torch = import_sb3()
    from stable_baselines3.common.callbacks import BaseCallback

    set_torch_threads(torch)
    par = P.open_loop(task)
    zero_offset = np.zeros(par.size - par.n_action_params)
    v = task.max_tool_speed
    state = {"best": (np.inf, None), "history": [], "returns": [], "episodes": 0, "steps": 0, "stop": False}
    t0 = time.perf_counter()

    def episode_done(actions: np.ndarray, task_loss: float, episode_return: float):
        state["episodes"] += 1
        state["history"].append(task_loss)
        state["returns"].append(episode_return)
        if task_loss < state["best"][0]:
            state["best"] = (task_loss, np.concatenate([actions.reshape(-1), zero_offset]))
        if callback is not None:
            p = Progress(method, state["episodes"], task_loss, state["best"][0], state["steps"], budget,
                         time.perf_counter() - t0, task.horizon, best_theta=state["best"][1], parametrisation=par)
            if callback(p):
                state["stop"] = True
        if max_iterations is not None and state["episodes"] >= max_iterations:
            state["stop"] = True

    class Recorder(gym.Wrapper):
        """Records each episode's actions (m/s, as applied), task loss and return."""

        def reset(self, **kwargs):
            self._actions, self._loss, self._return = [], 0.0, 0.0
            return self.env.reset(**kwargs)

        def step(self, action):
            a = np.clip(np.asarray(action, dtype=np.float64), -v, v)
            obs, reward, terminated, truncated, info = self.env.step(a)
            state["steps"] += 1
            self._actions.append(a)
            self._loss += info["task_loss"]
            self._return += reward
            if terminated or truncated:
                episode_done(np.array(self._actions), self._loss, self._return)
            return obs, reward, terminated, truncated, info

    base = FluidLabEnv(task.name, size=task.size, task=task)
    unit = np.ones(task.n_actions, dtype=np.float32)
    env = gym.wrappers.RescaleAction(Recorder(base), -unit, unit)

    # every episode but the last is training; PPO would otherwise round up to whole updates past the budget
    train_steps = max(budget // task.horizon - 1, 0) * task.horizon

    class Stop(BaseCallback):
        def _on_step(self) -> bool:
            return not state["stop"] and state["steps"] < train_steps

    model = _model(method, env, task, budget, seed)
    if train_steps:
        model.learn(total_timesteps=train_steps, callback=Stop())
    if not state["stop"] and state["steps"] + task.horizon <= budget:
        obs, _ = env.reset()
        done = False
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, _, terminated, truncated, _ = env.step(action)
            done = terminated or truncated
    if state["best"][1] is None:
        raise ValueError(f"the budget of {budget} steps did not complete one episode of {task.horizon} steps")
    settings = {"hyperparameters": dict(HYPERPARAMETERS[method]), "episodes": state["episodes"], "env_steps": state["steps"],
                "episode_returns": [round(r, 4) for r in state["returns"]],
                "result": "best episode by task loss (training episodes and the final deterministic one)"}
    return Result(par, state["best"][1], state["history"], state["steps"], state["episodes"],
                  time.perf_counter() - t0, settings)
