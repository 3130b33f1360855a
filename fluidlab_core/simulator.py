"""The user-facing simulator returned by `Scene.build()`: stepping, reading particles, state round-trips."""
from __future__ import annotations

import numpy as np

from fluidlab_core import runtime


class NonFiniteStateError(FloatingPointError):
    """A particle field became NaN or infinite during a step."""


_FIELD_BITS = ((1, "positions (x)"), (2, "velocities (v)"), (4, "deformation gradients (F)"))


class Simulator:
    """Steps an MLS-MPM scene. One `step(action)` advances dt seconds in `substeps` substeps, moving the tools
    with the action.

    positions(h)/velocities(h) return (N, 3) float64 arrays in the world frame (m, m/s) for a particle
    handle from `Scene.add_particles` (or its name). `get_state()`/`set_state()` round-trip the whole
    particle state exactly.
    """

    def __init__(self, scene, solver, handles, config, diff=None):
        from fluidlab_core.engine.tools import ToolState

        self.scene = scene
        self.solver = solver
        self.diff = diff  # differentiable solver (engine/diff_mpm.py) when built with requires_grad=True
        # fixed at build: the substep length is compiled into the kernels
        self._dt, self._substeps = scene.dt, scene.substeps
        self.tools = ToolState(scene.tools)
        self.handles = {h.name: h for h in handles}
        self._config = config
        self.step_count = 0
        self.check_finite_every = 1  # steps between NaN checks (0: never)
        self._static_points = None  # sampled statics for pictures, made on first render
        self._tool_points = None  # tool shapes sampled in their own frames, likewise

    # --- stepping ---------------------------------------------------------------------------------------
    @property
    def dt(self) -> float:
        """Seconds per step."""
        return self._dt

    @property
    def substeps(self) -> int:
        return self._substeps

    @property
    def time(self) -> float:
        """Simulated time since the start or the last set_state (s)."""
        return self.step_count * self._dt

    @property
    def n_particles(self) -> int:
        return self.solver.n_particles

    def _check_alive(self):
        current = runtime.current()
        if current is None or current.generation != self._config.generation:
            raise RuntimeError("this simulator was built before fluidlab_core.init() reset Taichi; build the scene "
                               "again")

    def step(self, action=None, n: int = 1) -> dict:
        """Advance `n` steps of dt seconds each, holding the tools' velocity `action` over every step.

        action: for one tool a (6,) array (vx, vy, vz, wx, wy, wz) in m/s and rad/s in the world frame; for
        several an (n_tools, 6) array or a {tool name: (6,)} dict; None keeps tools still. Dimensions outside a
        tool's action mask are ignored. Returns info: {"clipped": {tool name: True if the workspace clipped
        its motion in any of these steps}}."""
        self._check_alive()
        if action is not None and not self.tools.specs:
            raise ValueError("this scene has no tools, so step() takes no action")
        velocities = self.tools.parse_action(action)
        clipped = {spec.name: False for spec in self.tools.specs}
        sub_dt = self._dt / self._substeps
        n_tools = len(self.tools.specs)
        # each substep's tool poses and twists go into the substep's own launch (MPMSolver.substep)
        tool_state = np.zeros((max(n_tools, 1), 18), dtype=self.solver.np_real)
        for _ in range(n):
            v_step, hits = self.tools.clip(velocities, self._dt)
            for spec, hit in zip(self.tools.specs, hits):
                clipped[spec.name] |= hit
            turn = self.tools.turns(v_step, sub_dt)
            tool_state[:n_tools, 12:] = v_step
            for _ in range(self._substeps):
                tool_state[:n_tools, :3] = self.tools.position
                tool_state[:n_tools, 3:12] = self.tools.rotation.reshape(n_tools, 9)
                self.solver.substep(tool_state)
                if self.solver.rigid is not None:
                    self.solver.rigid.project()
                    if self.solver.rigid.sdfs:
                        self.solver.rigid.exclude()
                self.tools.advance(v_step, sub_dt, turn)
            self.step_count += 1
            if self.check_finite_every and self.step_count % self.check_finite_every == 0:
                self.check_finite()
        return {"clipped": clipped}

    def rollout(self, actions, loss, grad: bool = False, segment_steps: int | None = None, checkpoint_dir=None,
                progress=None):
        """Run len(actions) steps from the current state and return the loss (and its gradients).

        actions: (N, 6) for one tool or (N, n_tools, 6): tool twists per step as in `step` (N ≥ 1); for a scene
            without tools pass an integer N (steps with no action).
        loss: a `fluidlab_core.losses.Loss`, evaluated after the steps it names.
        grad: False runs the fast forward solver; True runs the differentiable solver (build with
            requires_grad=True) with gradient checkpointing and returns the gradients with respect to every
            action, the initial tool poses and the initial particle state (see checkpoint.RolloutResult).
        segment_steps: steps per checkpoint segment (default: as long as the buffer chosen at build allows, see
            checkpoint.plan_segments).
        checkpoint_dir: keep segment checkpoints in a private folder under this directory instead of in memory.
        progress: optional callable(phase, done, total), called once per step of each phase.

        The simulator ends in the rollout's final state, as after the same calls to `step`."""
        from fluidlab_core.engine.checkpoint import RolloutResult, rollout_with_grad
        from fluidlab_core.losses import Loss, StepState

        self._check_alive()
        if not isinstance(loss, Loss):
            raise TypeError(f"loss must be a fluidlab_core.losses.Loss, got {type(loss).__name__}")
        velocities = self._action_sequence(actions)
        n_steps = len(velocities)
        if grad:
            if self.diff is None:
                raise RuntimeError("this simulator was built without gradients: build(requires_grad=True) to "
                                   "call rollout(..., grad=True)")
            return rollout_with_grad(self, self.diff, velocities, loss, True, segment_steps, checkpoint_dir, progress)
        step_losses = np.zeros(n_steps)
        clipped = np.zeros((n_steps, len(self.tools.specs)), dtype=bool)
        for g in range(n_steps):
            info = self.step(velocities[g] if self.tools.specs else None)
            clipped[g] = [info["clipped"][s.name] for s in self.tools.specs]
            if loss.active(g + 1, n_steps):
                x, v = np.zeros((self.n_particles, 3)), np.zeros((self.n_particles, 3))
                self.solver.read_xv(x, v)
                state = StepState(g + 1, (g + 1) * self._dt, x, v, self.tools.position.copy(),
                                  self.tools.rotation.copy())
                step_losses[g], _ = loss(state, n_steps, grad=False)
            if progress:
                progress("forward", g + 1, n_steps)
        return RolloutResult(float(step_losses.sum()), step_losses, clipped)

    def _action_sequence(self, actions) -> np.ndarray:
        """(N, n_tools, 6) masked twists from the forms `rollout` accepts."""
        n_tools = len(self.tools.specs)
        if isinstance(actions, (int, np.integer)):
            if actions < 1:
                raise ValueError(f"a rollout needs at least one step, got {actions}")
            return np.zeros((int(actions), n_tools, 6))
        arr = np.asarray(actions, dtype=np.float64)
        if n_tools == 0:
            raise ValueError("this scene has no tools: pass the number of steps as actions")
        if arr.ndim == 2 and n_tools == 1:
            arr = arr[:, None, :]
        if arr.ndim != 3 or arr.shape[1:] != (n_tools, 6) or len(arr) < 1:
            raise ValueError(f"actions must have shape (N, 6) for one tool or (N, {n_tools}, 6), got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            bad = np.argwhere(~np.isfinite(arr))[0]
            raise ValueError(f"actions contain NaN or infinity (first at step {bad[0]})")
        return arr * np.array([s.action_mask for s in self.tools.specs], dtype=np.float64)

    def tool_pose(self, name: str) -> np.ndarray:
        """(x, y, z, qx, qy, qz, qw) of a tool's frame in the world (m)."""
        names = [spec.name for spec in self.tools.specs]
        if name not in names:
            raise KeyError(f"no tool named {name!r}; tools: {', '.join(names) or 'none'}")
        return self.tools.pose(names.index(name))

    def check_finite(self):
        """Raise NonFiniteStateError naming the field, step and particle if any state is NaN or infinite."""
        bits = int(self.solver.find_nonfinite())
        if bits:
            p = int(self.solver.bad_particle[None])
            body = next(h for h in self.handles.values() if h.start <= p < h.start + h.count)
            fields = ", ".join(name for bit, name in _FIELD_BITS if bits & bit)
            raise NonFiniteStateError(
                f"NaN or infinity in particle {fields} at step {self.step_count} (t = {self.time:.4g} s), "
                f"first at particle {p} of body {body.name!r} ({body.material.name}). The explicit solver went "
                f"unstable: use more substeps (smaller dt), a softer material, or lower speeds.")

    # --- reading ----------------------------------------------------------------------------------------
    def handle(self, h):
        if isinstance(h, str):
            try:
                return self.handles[h]
            except KeyError:
                raise KeyError(f"no particle body named {h!r}; bodies: {', '.join(self.handles)}") from None
        return h

    def _rows(self, field, h):
        data = field.to_numpy()
        return (data if h is None else data[self.handle(h).slice]).astype(np.float64)

    def positions(self, h=None) -> np.ndarray:
        """(N, 3) particle positions (m) of body `h` (all particles if None)."""
        return self._rows(self.solver.x, h)

    def velocities(self, h=None) -> np.ndarray:
        """(N, 3) particle velocities (m/s)."""
        return self._rows(self.solver.v, h)

    def deformation_gradients(self, h=None) -> np.ndarray:
        return self._rows(self.solver.F, h)

    def volumes(self, h=None) -> np.ndarray:
        """Current particle volumes V⁰·det F (m³)."""
        rest = self._rows(self.solver.rest_volume, h)
        return rest * np.linalg.det(self.deformation_gradients(h))

    def pressures(self, h=None) -> np.ndarray:
        """Cauchy pressure −tr(σ)/3 of each particle (Pa)."""
        self.solver.compute_pressure()
        return self._rows(self.solver.pressure, h)

    def masses(self, h=None) -> np.ndarray:
        return self._rows(self.solver.mass, h)

    # --- pictures ---------------------------------------------------------------------------------------
    def render(self, path=None, view="iso", size=(800, 600), title=None, bodies=None):
        """A PNG picture of the current state (particles coloured by material, statics in grey and cut away on
        the camera's side, the domain box drawn), written to `path` if given; returns the image as an (H, W, 3) uint8 array. `view` is a
        name from fluidlab_core.render.VIEWS or (azimuth_deg, elevation_deg)."""
        from fluidlab_core.render import Layer, render, view_axes

        if self._static_points is None:
            self._static_points = [st.shape.sample(self.scene.dx) for st in self.scene.statics]
        # cutaway: statics are drawn only behind the domain's centre, so they never hide what is inside them
        toward = view_axes(view)[2]
        centre = 0.5 * (self.scene.lower + self.scene.upper)
        layers = []
        if self._tool_points is None:
            self._tool_points = [spec.shape.sample(0.5 * self.scene.dx) for spec in self.tools.specs]
        for i, (spec, local) in enumerate(zip(self.tools.specs, self._tool_points)):
            if len(local):
                layers.append(Layer(local @ self.tools.rotation[i].T + self.tools.position[i], spec.color, spec.name))
        for st, points in zip(self.scene.statics, self._static_points):
            behind = points[(points - centre) @ toward < 0.0]
            if len(behind):
                layers.append(Layer(behind, (0.72, 0.72, 0.74), st.name))
        x = self.positions()
        for h in self.handles.values():
            if bodies is None or h.name in bodies:
                layers.append(Layer(x[h.slice], h.material.color, h.name))
        return render(layers, path, view=view, bounds=(self.scene.lower, self.scene.upper), size=size, title=title)

    # --- state ------------------------------------------------------------------------------------------
    def get_state(self) -> dict:
        """A copy of the particle state (x, v, C, F as numpy arrays in the solver's precision) and the step."""
        s = self.solver
        return {"x": s.x.to_numpy(), "v": s.v.to_numpy(), "C": s.C.to_numpy(), "F": s.F.to_numpy(),
                "tool_position": self.tools.position.copy(), "tool_rotation": self.tools.rotation.copy(),
                "step": self.step_count}

    def set_state(self, state: dict):
        """Restore a state from `get_state()` exactly."""
        s = self.solver
        for key, field in (("x", s.x), ("v", s.v), ("C", s.C), ("F", s.F)):
            arr = np.asarray(state[key])
            if arr.ndim == 0 or arr.shape[0] != s.n_particles:
                raise ValueError(f"state[{key!r}] has {arr.shape[0]} rows, this scene has {s.n_particles} particles")
            field.from_numpy(arr.astype(s.np_real))
        if "tool_position" in state:
            self.tools.position[:] = state["tool_position"]
            self.tools.rotation[:] = state["tool_rotation"]
        self.step_count = int(state.get("step", 0))

