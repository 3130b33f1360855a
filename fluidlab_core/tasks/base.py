"""What every task shares: a scene recipe in the robot's base frame, a horizon, a loss, a reward, observations,
and the translation between a task's few action dimensions and the engine's 6-D tool twist.

A task is a description plus cached simulators; it compiles nothing until a simulator is asked for.

    task = tasks.make("LatteArtStir", size="small")
    sim = task.simulator()                       # reference physics: hard tool contact, no gradients
    task.reset(sim)                              # the documented start state
    out = task.evaluate(actions)                 # actions (N, k) in the task's action space (m/s)

Units: metres, seconds, m/s; the world frame is the robot base frame `fr3_link0` (REP-103, z up).
Actions are the tool's velocity along the task's action axes (for the tasks here: vx, vy in the horizontal
plane), held for one step of dt seconds; `twists(actions)` expands them to (N, 6) twists (vx, vy, vz, wx, wy,
wz) as the engine and the trajectory file use them.

Contact: the reference physics of every task uses hard tool contact (the stick and the paddle are solid);
the soft contact model of FluidLab is an optimisation device (`contact="soft"`) that DP uses to get smoother
gradients. Reported losses are always those of the reference physics.

Reward (Gymnasium): r_k = c1 − c2 · ℓ_k after each step k, where ℓ_k is the task's per-step loss term
(`step_term`) and c1, c2 are documented per task so that a typical step earns a reward in about [−1, 1].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fluidlab_core import losses
from fluidlab_core.trajectory import Trajectory

SIZES = ("small", "medium", "paper")  # medium: about 1.5x small's grid, the same episode in seconds
CONTACTS = ("hard", "soft")
FRAME_ID = "fr3_link0"


def _check_contact(contact: str) -> None:
    """Refuse a tool contact other than CONTACTS, naming it."""
    if contact not in CONTACTS:
        raise ValueError(f"contact must be one of {', '.join(CONTACTS)}, got {contact!r}")


@dataclass(frozen=True)
class SizeConfig:
    """The resolution a task runs at. `substeps` is the least that passes the stability check (never fewer than
    the paper's 10 at paper size)."""

    grid_res: int
    dt: float  # s per step
    horizon: int  # steps in an episode
    particles_per_body: int  # observed particles per fluid body (downsampled)
    spacing_cells: float = 0.5  # particle lattice spacing in grid cells


class Task:
    """Base class of the tasks. Subclasses set the class attributes and implement `_populate`, `_domain`,
    `workspace`, `initial_tool_pose`, `loss`, `step_term` and `attraction`."""

    name = ""
    # --- set by subclasses ------------------------------------------------------------------------------
    tool_name = "tool"
    action_axes: tuple[int, ...] = (0, 1)  # indices into (vx, vy, vz, wx, wy, wz)
    max_tool_speed = 0.15  # m/s, bound of each action component
    softness = 400.0  # 1/m, of the tool with contact="soft" (the influence falls by e every 2.5 mm)
    tool_friction = 0.0
    reward_c1 = 1.0
    reward_c2 = 1.0
    observed_bodies: tuple[str, ...] = ()
    target_body = ""  # the body DP's attraction term pulls the tool towards
    camera = "iso"
    periodic: tuple[int, int] | None = None  # (stroke steps, reset steps) of the paper's periodic policy
    flange_to_tool = (0.0, 0.0, 0.15, 0.0, 0.0, 0.0, 1.0)  # tool frame in the flange frame (m, quaternion xyzw)
    sizes: dict[str, SizeConfig] = {}
    action_knots: int | None = None  # gradient methods optimise this many knots per axis instead of every step
    # DP's temporally expanding region suits losses that a partial horizon already approaches; a task whose goal
    # is a final state reached through a detour (tilt a glass and bring it back) sets this False
    expanding_region = True
    # the task loss is the mean over the horizon of `step_term` (so a window of steps has a loss of its own: DP
    # over windows, "dp-window", optim/dp.py); and that method's window in steps (None: a quarter of the horizon)
    loss_is_step_mean = False
    gradient_window: int | None = None
    # std of DP's seeded noise on a task's starting motion (Task.initial_actions), as a fraction of
    # max_tool_speed (DPOptions.initial_noise applies when the task starts from rest)
    start_noise = 0.05
    # DP's Adam step as a fraction of max_tool_speed, where the task needs another than DPOptions.learning_rate
    learning_rate: float | None = None
    # particles at paper size: the paper's "about 100k"; a scene filled by an emitter, or a glass, holds fewer
    paper_particles: tuple[int, int] = (60_000, 140_000)
    # whether the tool touches particles, so that its contact model (soft or hard) changes the physics; a task
    # without (a gas task) builds one simulator for both, not two that compile the same kernels. None: from the
    # scene (touching where it holds any particle body or emitter); a subclass may set True or False
    touches_particles: bool | None = None
    # the liquids' pressure ("state" or "projection"), set by __init__; the class default keeps a plugin task whose
    # own __init__ does not call this one on the default liquid
    pressure = "state"

    def __init__(self, size: str = "small", pressure: str = "state"):
        """size: one of the task's sizes. pressure: the liquids' pressure, "state" (the default, weakly
        compressible; the physics the tasks' optimised trajectories and benchmarks were found on) or "projection"
        (incompressible, floats bodies at Archimedes' depth; forward only, so no gradient methods: Scene's
        `pressure`, engine/projection.py)."""
        self.size = size
        if pressure not in ("state", "projection"):
            raise ValueError(f"pressure must be 'state' or 'projection', got {pressure!r}")
        self.pressure = pressure
        if self.size not in SIZES:
            raise ValueError(f"size must be one of {', '.join(SIZES)}, got {self.size!r}")
        if self.size not in self.sizes:
            raise ValueError(f"task {self.name} has no {self.size!r} size (its sizes: {', '.join(self.sizes)})")
        self.config: SizeConfig = self.sizes[self.size]
        self._sims: dict = {}
        self._initial_state: dict = {}
        self._observe_index: dict | None = None
        self._handles: dict | None = None
        self._touches: bool | None = None
        self._room: dict | None = None

    @property
    def tool_touches_particles(self) -> bool:
        """Whether the tool's contact model (soft or hard) changes the physics: the class's
        `touches_particles` if set, else whether the task's scene holds any particles (bodies or emitters)."""
        if self.touches_particles is not None:
            return bool(self.touches_particles)
        if self._touches is None:  # found by the first simulator(); without one, from a scene built for it
            self._touches = bool(self.scene("hard").bodies)
        return self._touches

    # --- scene ------------------------------------------------------------------------------------------
    def _populate(self, scene, contact: str):
        """Add statics, bodies and the tool to `scene` (subclasses)."""
        raise NotImplementedError

    def _domain(self) -> tuple[tuple, tuple]:
        raise NotImplementedError

    def scene(self, contact: str = "hard"):
        """The task's Scene (not yet built) with the given tool contact."""
        from fluidlab_core.scene import Scene

        _check_contact(contact)
        lower, upper = self._domain()
        cfg = self.config
        # on the projection the tasks' liquid is APIC (flip 0), not the Scene's AFLIP 0.99 there: with AFLIP the
        # Gathering tank's still water stirred itself up (rms speed 0.077 m/s after 1 s and 0.08 on to 10 s, the
        # fastest particles at 0.5-0.6 m/s, against the paddle's 0.15), with APIC it stays still (rms 0.001-0.003)
        # and the foam floats at 0.37-0.39 of its volume under (AFLIP: 0.37-0.41; Archimedes 0.40); docs/engine.md
        scene = Scene(lower=lower, upper=upper, grid_res=cfg.grid_res, dt=cfg.dt, substeps=1, seed=0,
                      pressure=self.pressure, flip=0.0 if self.pressure == "projection" else None)
        scene.particle_spacing = cfg.spacing_cells * scene.dx
        self._populate(scene, contact)
        scene.substeps = max(scene.stable_substeps(), 10 if self.size == "paper" else 1)
        return scene

    def simulator(self, grad: bool = False, contact: str = "hard", grad_max_steps: int = 200):
        """A simulator of the task, built once per (contact, grad) and cached. A gradient simulator also runs
        the fast forward solver, so it serves forward calls of the same contact too. In a task whose tool touches
        no particles (tool_touches_particles False) both contacts are the same physics and share a simulator."""
        _check_contact(contact)
        scene = None
        if self.touches_particles is None and self._touches is None:  # the first build tells (one scene, not two)
            scene = self.scene(contact)
            self._touches = bool(scene.bodies)
        if not self.tool_touches_particles and contact != "hard":
            contact, scene = "hard", None
        key = (contact, grad)
        if not grad and (contact, True) in self._sims:  # (even where a forward one was built before it: the
            return self._sims[(contact, True)]         # forward calls then run on what DP's judgements ran on)
        if key not in self._sims:
            scene = scene or self.scene(contact)
            sim = scene.build(requires_grad=grad, grad_max_steps=grad_max_steps)
            sim.check_finite_every = 10
            self._sims[key] = sim
            self._initial_state[id(sim)] = sim.get_state()
        return self._sims[key]

    def body_slice(self, body: str) -> slice:
        """The rows of a particle body in the simulator's particle arrays (the same in every build)."""
        if self._handles is None:
            sim = next(iter(self._sims.values()), None)
            self._handles = dict(sim.handles) if sim else {b.handle.name: b.handle for b in self.scene().bodies}
        if body not in self._handles:
            raise KeyError(f"{self.name} has no particle body {body!r}; bodies: {', '.join(self._handles)}")
        return self._handles[body].slice

    # --- start state and actions ------------------------------------------------------------------------
    @property
    def horizon(self) -> int:
        return self.config.horizon

    @property
    def dt(self) -> float:
        return self.config.dt

    @property
    def n_actions(self) -> int:
        return len(self.action_axes)

    def workspace(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounds on the tool origin (m), as the scene gives them to the tool."""
        raise NotImplementedError

    def initial_tool_pose(self) -> np.ndarray:
        """(x, y, z, qx, qy, qz, qw) of the tool frame at the start (m)."""
        raise NotImplementedError

    def reset(self, sim, tool_position=None):
        """Put `sim` in the task's start state, optionally with the tool origin moved to `tool_position` (m,
        clipped to the workspace)."""
        state = self._initial_state[id(sim)]
        if tool_position is not None:
            lo, hi = self.workspace()
            pos = np.array(state.tool_position, dtype=np.float64)
            pos[0] = np.clip(np.asarray(tool_position, dtype=np.float64), lo, hi)
            moved = self._liquid_round_tool(state, pos[0])  # None: no liquid sampled round the tool (a gas task)
            state = state.replace(tool_position=pos, **({} if moved is None else {"x": moved}))
        sim.set_state(state)

    def _tool_room(self) -> dict:
        """{body name: the sites (m) its liquid leaves for the tool at the tool's nominal start}, for the bodies
        sampled round the tool (`common.Without` with a `common.Posed` tool among its solids), with the tool's
        shape and rotation: the lattice sites of the body's shape without the tool that lie inside it."""
        if self._room is None:
            from fluidlab_core.tasks import common

            scene = self.scene("hard")
            self._room = {}
            for body in scene.bodies:
                shape = body.shape
                if not isinstance(shape, common.Without):
                    continue
                tools = [s for s in shape.solids if isinstance(s, common.Posed)]
                if not tools:
                    continue
                rest = common.Without(shape.shape, [s for s in shape.solids if not isinstance(s, common.Posed)])
                sites = rest.sample(scene.particle_spacing)
                tool = tools[0]
                self._room[body.handle.name] = (sites[tool.sdf(sites) < 0.0], tool)
        return self._room

    def _liquid_round_tool(self, state, position) -> np.ndarray | None:
        """The start positions with the tool's origin at `position` (m): the particles of a body sampled round
        the tool's nominal start that the tool covers there move into the sites it left at the nominal start and
        no longer covers, so that the liquid starts round the tool wherever the start puts it (with the tool's
        volume, the same number of sites up to a lattice row; any left over stay, and the tool pushes them out).
        None where no body was sampled round the tool (AirCirculation's state has no particles)."""
        from fluidlab_core.tasks import common

        room = self._tool_room()
        if not room:
            return None
        x = np.array(state.x, copy=True)
        for name, (sites, tool) in room.items():
            if np.allclose(position, tool.position):
                continue
            there = common.Posed(tool.shape, np.concatenate([position, tool.rotation.as_quat()]))
            rows = np.arange(self.body_slice(name).start, self.body_slice(name).stop)
            movers = rows[there.sdf(x[rows].astype(np.float64)) < 0.0]
            free = sites[there.sdf(sites) >= 0.0]
            n = min(len(movers), len(free))
            x[movers[:n]] = free[:n].astype(x.dtype)
        return x

    def twists(self, actions) -> np.ndarray:
        """(N, 6) tool twists from (N, k) actions in the task's action space, clipped to ±max_tool_speed."""
        a = np.asarray(actions, dtype=np.float64)
        if a.ndim == 1 and self.n_actions == 1:
            a = a[:, None]
        if a.ndim != 2 or a.shape[1] != self.n_actions:
            raise ValueError(f"{self.name} actions must have shape (N, {self.n_actions}) for axes "
                             f"{self.action_axis_names()}, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{self.name} actions contain NaN or infinity")
        out = np.zeros((len(a), 6))
        out[:, list(self.action_axes)] = np.clip(a, -self.max_tool_speed, self.max_tool_speed)
        return out

    def actions_from_twists(self, twists) -> np.ndarray:
        tw = np.asarray(twists, dtype=np.float64)
        return tw[:, list(self.action_axes)]

    def initial_actions(self) -> np.ndarray | None:
        """(N, k) actions gradient-based optimisers start from (plus their seeded noise), or None for rest. A
        task whose loss barely changes until the tool has done something large (tilting a glass until it pours)
        gives a starting motion here and says so in docs/tasks.md."""
        return None

    def action_axis_names(self) -> tuple[str, ...]:
        names = ("vx", "vy", "vz", "wx", "wy", "wz")
        return tuple(names[i] for i in self.action_axes)

    # --- losses -----------------------------------------------------------------------------------------
    def loss(self, horizon: int | None = None) -> losses.Loss:
        """The task loss of a rollout of `horizon` steps (default: the task's horizon)."""
        raise NotImplementedError

    def step_term(self) -> losses.Loss:
        """The per-step loss term ℓ_k behind the reward (evaluated after every step)."""
        raise NotImplementedError

    def attraction(self, weight: float) -> losses.Loss:
        """DP's attraction term: pulls the tool towards the body it must move (see optim/dp.py)."""
        from fluidlab_core.tasks.losses import ToolAttraction

        return ToolAttraction(self.attraction_particles(), weight=weight)

    def gradient_sharing(self, weight: float) -> losses.Loss | None:
        """DP's gradient sharing term (tasks/losses.py: ShareWithLead, BodyAttraction), or None where the task
        has none. The paper's released code has it in Pouring and Transporting only."""
        return None

    def attraction_particles(self):
        return self.body_slice(self.target_body)

    def reward(self, step_loss: float) -> float:
        return self.reward_c1 - self.reward_c2 * float(step_loss)

    # --- evaluation -------------------------------------------------------------------------------------
    def evaluate(self, actions, tool_position=None, sim=None, progress=None, rewards: bool = True) -> dict:
        """Run the task from its start state with (N, k) actions on the reference physics (unless `sim` is
        given). Returns {"loss", "step_losses", "clipped_steps"} and, with rewards=True, the per-step
        "rewards" and their sum "return"."""
        sim = sim or self.simulator()
        twists = self.twists(actions)
        self.reset(sim, tool_position)
        terms = {"reward_term": self.step_term()} if rewards else {}
        res = sim.rollout(twists, self.loss(len(twists)), progress=progress, terms=terms)
        out = {"loss": res.loss, "step_losses": res.step_losses, "clipped_steps": int(res.clipped.any(axis=1).sum())}
        if rewards:
            r = self.reward_c1 - self.reward_c2 * res.terms["reward_term"]
            out.update(rewards=r, **{"return": float(r.sum())})
        return out

    def step_state(self, sim) -> losses.StepState:
        return sim.step_state()

    # --- observations -----------------------------------------------------------------------------------
    def observation_size(self) -> int:
        return len(self.observed_bodies) * self.config.particles_per_body * 6 + 13

    def observe(self, sim, tool_twist=None) -> np.ndarray:
        """Downsampled positions (m) and velocities (m/s) of each observed body, then the tool pose (x, y, z,
        qx, qy, qz, qw) and twist (m/s, rad/s); float32. The same particles are observed every step (a fixed
        subset per body, chosen with a fixed seed); of a body that an emitter is still adding, the rows of
        particles not yet emitted are zero."""
        if self._observe_index is None:
            rng = np.random.default_rng(12345)
            self._observe_index = {}
            for body in self.observed_bodies:
                h = sim.handle(body)
                m = min(self.config.particles_per_body, h.count)
                idx = np.sort(rng.choice(h.count, m, replace=False)) + h.start
                if m < self.config.particles_per_body:  # repeat to keep the documented shape
                    idx = np.resize(idx, self.config.particles_per_body)
                self._observe_index[body] = idx
        x, v = sim.state.x.to_numpy()[0].astype(np.float64), sim.state.v.to_numpy()[0].astype(np.float64)
        active = sim.active_rows()
        if active is not None:  # particles not yet emitted are observed as zero rows
            x[~active], v[~active] = 0.0, 0.0
        parts = []
        for body in self.observed_bodies:
            idx = self._observe_index[body]
            parts += [x[idx].ravel(), v[idx].ravel()]
        parts.append(sim.tool_pose(self.tool_name))
        parts.append(np.zeros(6) if tool_twist is None else np.asarray(tool_twist, dtype=np.float64))
        return np.concatenate(parts).astype(np.float32)

    # --- trajectories -----------------------------------------------------------------------------------
    def trajectory(self, actions, tool_position=None, method="", seed=None, loss_history=(), metadata=None
                   ) -> Trajectory:
        """A Trajectory document (fluidlab_core/trajectory.py) of these actions from the start state."""
        pose = self.initial_tool_pose().copy()
        if tool_position is not None:
            lo, hi = self.workspace()
            pose[:3] = np.clip(tool_position, lo, hi)
        meta = {"size": self.size, "flange_to_tool": list(self.flange_to_tool),
                "action_axes": list(self.action_axis_names())}
        if self.pressure != "state":  # the physics it was found on, where not the default
            meta["pressure"] = self.pressure
        meta.update(metadata or {})
        return Trajectory(task=self.name, dt=self.dt, tool=self.tool_name, initial_pose=pose,
                          twists=self.twists(actions), frame_id=FRAME_ID, method=method, seed=seed,
                          loss_history=list(loss_history), metadata=meta)

    def actions_from_trajectory(self, traj: Trajectory) -> tuple[np.ndarray, np.ndarray]:
        """(actions (N, k), initial tool position (3,)) of a trajectory written for this task; refuses
        trajectories of another task, time step or horizon, and twists outside the action axes."""
        if traj.task != self.name:
            raise ValueError(f"the trajectory is for task {traj.task!r}, not {self.name!r}")
        if abs(traj.dt - self.dt) > 1e-12:
            raise ValueError(f"the trajectory's dt {traj.dt} s differs from {self.name} ({self.size}) dt {self.dt} s")
        other = [i for i in range(6) if i not in self.action_axes]
        if np.any(np.abs(traj.twists[:, other]) > 1e-12):
            raise ValueError(f"the trajectory moves the tool along axes {self.name} does not use (only "
                             f"{self.action_axis_names()})")
        return self.actions_from_twists(traj.twists), traj.initial_pose[:3].copy()


class PatternTask(Task):
    """A task whose loss is the Chamfer distance between one body (`pattern_body`) and goal snapshots that a
    scripted motion drew on the reference physics (its goal file, tasks/goals.py): LatteArtStir, LatteArtPour and
    the ice-cream tasks."""

    pattern_body = ""
    goal_every = 5  # steps between goal snapshots
    goal_points = 500  # points per snapshot

    def goal(self) -> dict:
        """{step: (M, 3) goal points}, from the goal file (loaded once)."""
        from fluidlab_core.tasks import goals

        if not hasattr(self, "_goal"):
            doc = goals.load(self.name, self.size)
            self._goal = {int(k): p for k, p in zip(doc["steps"], doc["points"])}
        return self._goal

    def loss(self, horizon=None):
        from fluidlab_core.tasks.losses import ChamferToGoal

        horizon = horizon or self.horizon
        goal = {k: p for k, p in self.goal().items() if k <= horizon}
        if not goal:  # before the first goal snapshot the loss is that of the first one, seen early
            k0 = min(self.goal())
            goal = {horizon: self.goal()[k0]}
        return ChamferToGoal(goal, self.body_slice(self.pattern_body))

    def step_term(self):
        from fluidlab_core.tasks.losses import ChamferToGoal

        goal = self.goal()
        steps = sorted(goal)
        # the goal of every step: the snapshot at or after it
        per_step = {k: goal[next(s for s in steps if s >= k)] for k in range(1, min(self.horizon, steps[-1]) + 1)}
        return ChamferToGoal(per_step, self.body_slice(self.pattern_body))
