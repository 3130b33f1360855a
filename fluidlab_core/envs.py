"""Gymnasium 1.x environments of the tasks: `FluidLab/<TaskName>-v0`.

    import gymnasium as gym
    import fluidlab_core.envs  # registers the ids (no other work)
    env = gym.make("FluidLab/LatteArtStir-v0", size="small", render_mode="rgb_array")
    obs, info = env.reset(seed=0)

Registering does no work; the simulator is built (and its kernels compiled) when the environment is made.
"""
from __future__ import annotations

import numpy as np



def env_id(task_name: str) -> str:
    """The Gymnasium id of a registered task."""
    return f"FluidLab/{task_name}-v0"


def _import_gymnasium():
    try:
        import gymnasium
    except ImportError:  # pragma: no cover - gymnasium is a dependency of the package
        raise ImportError("the FluidLab environments need gymnasium: pip install 'gymnasium==1.4.0'") from None
    return gymnasium


gym = _import_gymnasium()


class FluidLabEnv(gym.Env):
    """## Description
    A FluidLab task (Xian et al., ICLR 2023) in the robot's base frame: a tool held by a Franka arm moves in the
    horizontal plane and manipulates fluids simulated with differentiable MLS-MPM (fluidlab_core). The task
    (`task_name`) sets the scene: LatteArtStir (stir floating milk foam into a goal pattern), Mixing (spread a
    viscous sugar cube through coffee), GatheringEasy / GatheringHard (carry floating objects to goals with
    currents from a paddle). See fluidlab_core/tasks for the scenes and losses.

    ## Action Space
    `Box(-v_max, v_max, (2,), float32)`, v_max = 0.15 m/s:

    | index | action | unit |
    |---|---|---|
    | 0 | tool velocity along x (base frame, forward) | m/s |
    | 1 | tool velocity along y (base frame, left) | m/s |

    The velocity is held for one step of dt seconds (small: 4 ms for the cup tasks, 5 ms for Gathering; paper:
    2 ms). Actions outside the box are clipped; the tool also stops at its workspace bounds
    (`info["clipped"]`).

    ## Observation Space
    `Box(-inf, inf, (B·P·6 + 13,), float32)` for B observed bodies of P particles each (P = 64 small, 1000 paper
    for the cup tasks, 500 for Gathering):

    | slice | observation | unit |
    |---|---|---|
    | per body: P·3 | positions of a fixed subset of its particles (x, y, z) | m |
    | per body: P·3 | their velocities | m/s |
    | 7 | tool pose (x, y, z, qx, qy, qz, qw), base frame | m |
    | 6 | tool twist (vx, vy, vz, wx, wy, wz) last applied | m/s, rad/s |

    Bodies: LatteArtStir (coffee, milk), Mixing (coffee, sugar), Gathering (water, object_a, object_b).

    ## Rewards
    r_k = c1 − c2·ℓ_k after each step, with ℓ_k the task's per-step loss (m²): LatteArtStir: Chamfer distance to
    the goal pattern of the step (c1 = 1, c2 = 2e5); Mixing: minus the sugar's spread (c1 = 0, c2 = 1e4);
    Gathering: mean squared distance of the objects to their goals (c1 = 1, c2 = 500).

    `info` after each step: "step_loss" (ℓ_k), "task_loss" (this step's share of the task's loss, the loss the
    optimisers minimise: summed over an episode it is that episode's task loss), "clipped" (the tool met its
    workspace bound) and "time" (s).

    ## Starting State
    The task's documented start state (fluids at rest, tool at its start pose); it is deterministic, so `seed`
    only seeds `self.np_random` for the user's benefit. `options={"tool_position": (x, y, z)}` moves the tool's
    start within its workspace.

    ## Episode End
    No termination; truncation after the task's horizon (small: 75 steps for the cup tasks, 100 for
    Gathering; paper: 150 and 250).

    ## Arguments
    `gym.make("FluidLab/<Task>-v0", size="small" | "medium" | "paper", render_mode=None | "rgb_array")`; `task=` an already
    made Task of that name and size, to share it. The Taichi backend
    is that of `fluidlab_core.init` (CPU and float32 by default).

    ## Version History
    - v0: first version.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 25}

    def __init__(self, task_name: str, size: str = "small", render_mode: str | None = None, task=None):
        from fluidlab_core import tasks

        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        if task is not None and (task.name, task.size) != (task_name, size):
            raise ValueError(f"task is {task.name} ({task.size}), but the environment was asked for {task_name} "
                             f"({size})")
        self.task = task if task is not None else tasks.make(task_name, size=size)
        self.render_mode = render_mode
        self.sim = self.task.simulator()
        v = np.float32(self.task.max_tool_speed)
        self.action_space = gym.spaces.Box(-v, v, shape=(self.task.n_actions,), dtype=np.float32)
        n = self.task.observation_size()
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(n,), dtype=np.float32)
        self._term = self.task.step_term()
        self._task_loss = self.task.loss(self.task.horizon)
        self._tool = [spec.name for spec in self.sim.tool_specs].index(self.task.tool_name)
        self._twist = np.zeros(6)
        self._steps = 0
        self.metadata = dict(self.metadata, render_fps=max(1, int(round(1.0 / self.task.dt / 10))))

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        position = (options or {}).get("tool_position")
        self.task.reset(self.sim, position)
        self._twist = np.zeros(6)
        self._steps = 0
        return self.task.observe(self.sim, self._twist), {"time": 0.0}

    def step(self, action):
        a = np.asarray(action, dtype=np.float64).reshape(self.task.n_actions)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action contains NaN or infinity: {action!r}")
        twist = self.task.twists(a[None])
        res = self.sim.rollout(twist, self._term, step_offset=self._steps, horizon=self.task.horizon,
                               terms={"task_loss": self._task_loss})
        self._twist = twist[0]
        self._steps += 1
        step_loss = float(res.step_losses[0])
        reward = self.task.reward(step_loss)
        truncated = self._steps >= self.task.horizon
        obs = self.task.observe(self.sim, self._twist)
        return obs, float(reward), False, truncated, {"clipped": bool(res.clipped[0, self._tool]),
                                                    "step_loss": step_loss, "time": self.sim.time,
                                                    "task_loss": float(res.terms["task_loss"][0])}

    def render(self):
        if self.render_mode == "rgb_array":
            return self.sim.render(view=self.task.camera, size=(320, 240))
        return None


def register():
    """Register an id with Gymnasium for every task of the registry, yours included (idempotent; tasks
    registered later get theirs from `tasks.register`)."""
    from fluidlab_core import tasks

    for name in tasks.names():
        if env_id(name) not in gym.registry:
            gym.register(id=env_id(name), entry_point="fluidlab_core.envs:FluidLabEnv", kwargs={"task_name": name})


register()


def unregister(task_name: str):
    """Remove a task's id from Gymnasium's registry (tasks.unregister calls it)."""
    gym.registry.pop(env_id(task_name), None)
