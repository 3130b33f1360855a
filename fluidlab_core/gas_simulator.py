"""The simulator of a scene that holds gas and no particles (`Scene.build()` returns it for such a scene): the
gas solver (engine/gas.py) stepped with the scene's tools, rollouts with losses on the gas, and their gradients
with respect to the tools' actions and start poses, the sources' parameters and the initial gas state.

A step of dt seconds: the tools' twists (clipped to their workspaces, tools.plan) carry them to their pose at the
step's end, p ← p + v dt, R ← exp([ω]× dt) R; then `gas.substeps` gas steps of dt/substeps run with the tools
at that pose, moving at that twist (solid boundaries, and the sources they carry).

Gradients (rollout(grad=True)): checkpointed in segments of K steps (default ⌈√N⌉): the forward keeps each
segment's start; the backward re-runs a segment keeping each substep's start state on the host, then goes back
substep by substep through GasSolver.backward_step. The tools' pose gradients chain on the host through the
pose updates: with θ the rotation tangent (R ← exp([θ]×) R), ∂L/∂θ_k = Qᵀ ∂L/∂θ_{k+1} (Q = exp([ω_k dt]×)),
∂L/∂ω_k = dt J_l(ω_k dt)ᵀ ∂L/∂θ_{k+1} + the direct term, ∂L/∂v_k = dt ∂L/∂p_{k+1} + the direct term.
"""
from __future__ import annotations

import contextlib
import dataclasses
import math

import numpy as np

from fluidlab_core import runtime
from fluidlab_core.engine import tools as T
from fluidlab_core.gas import GasState, GasView, face_grad_from_cells
from fluidlab_core.losses import StepState


@dataclasses.dataclass
class GasSimState:
    """A snapshot of a gas scene: the gas (GasState), the tools' origins (T, 3) m and rotations (T, 3, 3), and the
    number of steps since the start."""

    gas: GasState
    tool_position: np.ndarray
    tool_rotation: np.ndarray
    step: int = 0

    def copy(self) -> "GasSimState":
        return GasSimState(self.gas.copy(), np.array(self.tool_position, copy=True),
                           np.array(self.tool_rotation, copy=True), self.step)

    def replace(self, **changes) -> "GasSimState":
        return dataclasses.replace(self.copy(), **changes)


@dataclasses.dataclass
class GasRolloutResult:
    """Loss of a gas rollout and, with grad=True, its gradients (float64, SI units).

    grad_actions (N, n_tools, 6): dL/d twist per step; grad_tool_position (n_tools, 3), grad_tool_rotation
    (n_tools, 3) (tangent, R₀ ← exp([θ]×) R₀); grad_velocity: dL/d of the initial face velocities (3 arrays);
    grad_scalars (n_q, nx, ny, nz): of the initial temperature, smoke and named scalars; grad_sources: {source
    name: {"position" (3,), "rotation" (3,) tangent, "speed", "temperature", "smoke", <scalar>}} in the source's
    parent frame."""

    loss: float
    step_losses: np.ndarray
    clipped: np.ndarray
    grad_actions: np.ndarray | None = None
    grad_tool_position: np.ndarray | None = None
    grad_tool_rotation: np.ndarray | None = None
    grad_velocity: tuple | None = None
    grad_scalars: np.ndarray | None = None
    grad_sources: dict | None = None
    stats: dict = dataclasses.field(default_factory=dict)
    terms: dict = dataclasses.field(default_factory=dict)


def _hat(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def left_jacobian(phi: np.ndarray) -> np.ndarray:
    """J_l(φ) of SO(3): exp([φ + δ]×) ≈ exp([J_l δ]×) exp([φ]×)."""
    t = float(np.linalg.norm(phi))
    K = _hat(phi)
    if t < 1e-8:
        return np.eye(3) + 0.5 * K
    return np.eye(3) + (1 - math.cos(t)) / t ** 2 * K + (t - math.sin(t)) / t ** 3 * K @ K


class GasSimulator:
    """Steps a gas scene (see the module docstring). Fields are read with `gas_field(name)`, `gas_velocity()`,
    `gas_pressure()` and sampled with `sample(name, points)`."""

    def __init__(self, scene, spec, solver, config):
        self.scene = scene
        self.spec = spec
        self.solver = solver  # engine/gas.GasSolver
        self._config = config
        self.tool_specs = list(scene.tools)
        self.step_count = 0
        self.dt = float(scene.dt)
        self.substeps = int(spec.substeps)
        self.handles = {}
        n = len(self.tool_specs)
        self._tool_p = np.array([t.position for t in self.tool_specs], dtype=np.float64).reshape(n, 3)
        from scipy.spatial.transform import Rotation

        self._tool_R = np.array([Rotation.from_quat(t.quaternion).as_matrix() for t in self.tool_specs],
                                dtype=np.float64).reshape(n, 3, 3)
        self._initial = GasSimState(solver.initial_state(), self._tool_p.copy(), self._tool_R.copy(), 0)
        self.check_finite_every = 1
        self._compiled = set()
        self._solid_cache = None
        self.set_state(self._initial)

    # --- basics ---------------------------------------------------------------------------------------------
    @property
    def time(self) -> float:
        return self.step_count * self.dt

    @property
    def n_particles(self) -> int:
        return 0

    @property
    def model(self):
        return self

    @property
    def has_emitters(self) -> bool:
        return False

    def _check_alive(self):
        current = runtime.current()
        if current is None or current.generation != self._config.generation:
            raise RuntimeError("this simulator was built before fluidlab_core.init() reset Taichi; build the scene "
                               "again")

    def get_state(self) -> GasSimState:
        return GasSimState(self.solver.read_state(), self._tool_p.copy(), self._tool_R.copy(), self.step_count)

    def set_state(self, state: GasSimState):
        g = state.gas
        if tuple(np.shape(v) for v in g.velocity) != tuple(self.solver.face_shapes) or \
                np.shape(g.scalars) != (self.solver.n_q, *self.solver.shape):
            raise ValueError("the state's gas fields do not match this scene's gas grid")
        self.solver.write_state(g)
        self._tool_p = np.array(state.tool_position, dtype=np.float64).reshape(len(self.tool_specs), 3)
        self._tool_R = np.array(state.tool_rotation, dtype=np.float64).reshape(len(self.tool_specs), 3, 3)
        self.step_count = int(state.step)
        self._solid_cache = None

    def initial_state(self) -> GasSimState:
        return self._initial.copy()

    def tool_pose(self, name: str) -> np.ndarray:
        names = [t.name for t in self.tool_specs]
        if name not in names:
            raise KeyError(f"no tool named {name!r}; tools: {', '.join(names) or 'none'}")
        i = names.index(name)
        return T.pose_of(self._tool_p[i], self._tool_R[i])

    def active_rows(self):
        return None

    # --- reading the gas ---------------------------------------------------------------------------------------
    def gas_state(self) -> GasState:
        return self.solver.read_state()

    def solid(self) -> np.ndarray:
        """(nx, ny, nz) bools: cells that are solid now (statics, tools)."""
        if self._solid_cache is None:
            self._solid_cache = self.solver.solid.to_numpy() != 0
        return self._solid_cache

    def view(self) -> GasView:
        return GasView.of(self.gas_state(), self.spec, self.solid())

    def gas_field(self, name: str) -> np.ndarray:
        """(nx, ny, nz) cell values of "temperature" (K), "smoke" (kg/m³) or a named scalar; "velocity" gives
        (nx, ny, nz, 3) m/s at the cell centres."""
        return self.view().field(name)

    def gas_velocity(self) -> np.ndarray:
        return self.view().velocity

    def gas_pressure(self) -> np.ndarray:
        """(nx, ny, nz) pressure of the last step's projection (Pa; a constant is free in closed domains)."""
        return self.solver.pressure(self.dt / self.substeps)

    def sample(self, name: str, points) -> np.ndarray:
        return self.view().sample(name, points)

    def cell_centers(self) -> np.ndarray:
        """(nx, ny, nz, 3) world positions of the cell centres (m)."""
        idx = np.stack(np.meshgrid(*[np.arange(n) for n in self.solver.shape], indexing="ij"), axis=-1)
        return self.spec.lower + self.spec.dx * (idx + 0.5)

    def step_state(self) -> StepState:
        return StepState(self.step_count, self.time, np.zeros((0, 3)), np.zeros((0, 3)), self._tool_p.copy(),
                         self._tool_R.copy(), None, gas=self.view())

    def solver_report(self) -> dict:
        """Iterations and relative residual of the pressure solves since the last call."""
        st = self.solver.stats
        out = {"solves": len(st["iterations"]), "max_iterations": max(st["iterations"], default=0),
               "max_residual": max(st["residual"], default=0.0)}
        st["iterations"].clear()
        st["residual"].clear()
        return out

    # --- stepping ---------------------------------------------------------------------------------------------
    def _first_run(self, key: str, what: str):
        if key in self._compiled:
            return contextlib.nullcontext()
        return runtime.compiling(what, done=lambda: self._compiled.add(key))

    def _poses(self, twists: np.ndarray):
        """Clipped twists, clipped dims, and the tool poses at the end of each step: (N, T, 3), (N, T, 3, 3)."""
        applied, clipped = T.plan(self.tool_specs, self._tool_p, twists, self.dt, 1)
        pos, rot = T.plan_poses(self.tool_specs, self._tool_p, self._tool_R, applied, self.dt)
        return applied, clipped, pos, rot

    def _gas_step(self, g_index: int, p, R, twist):
        s = self.solver
        if self.tool_specs:
            s.set_tools(p, R, twist[:, :3], twist[:, 3:])
        sub_dt = self.dt / self.substeps
        for j in range(self.substeps):
            s.step(sub_dt, g_index * self.substeps + j)
        self._solid_cache = None

    def step(self, action=None, n: int = 1) -> dict:
        """Advance n steps holding the tools' twist `action` (as Simulator.step). Returns {"clipped": {tool: bool},
        "gas": {"solves", "max_iterations", "max_residual"}}."""
        self._check_alive()
        if action is not None and not self.tool_specs:
            raise ValueError("this scene has no tools, so step() takes no action")
        twist = T.parse_action(self.tool_specs, action)
        twists = np.repeat(twist[None], int(n), axis=0)
        res = self.rollout(twists if self.tool_specs else int(n), None)
        return {"clipped": {t.name: bool(res.clipped[:, i].any()) for i, t in enumerate(self.tool_specs)},
                "gas": self.solver_report()}

    def _action_sequence(self, actions) -> np.ndarray:
        """(N, n_tools, 6) masked twists from the forms `rollout` accepts (tools.action_sequence)."""
        return T.action_sequence(self.tool_specs, actions)

    def rollout(self, actions, loss, grad: bool = False, segment_steps: int | None = None, progress=None, *,
                terms: dict | None = None, step_offset: int = 0, horizon: int | None = None, checkpoint_dir=None,
                emit_on=None) -> GasRolloutResult:
        """Run len(actions) steps from the current state; `loss` (a losses.Loss, or None) is evaluated after the
        steps it names; `terms` are evaluated beside it without gradients. With grad=True (one loss over the
        rollout's own steps) the gradients come back as GasRolloutResult describes. The simulator ends in the
        rollout's final state. checkpoint_dir and emit_on are accepted for the Simulator's signature and unused
        (segment starts are kept in host memory; a gas scene has no emitters)."""
        from fluidlab_core.losses import Loss

        self._check_alive()
        if loss is not None and not isinstance(loss, Loss):
            raise TypeError(f"loss must be a fluidlab_core.losses.Loss, got {type(loss).__name__}")
        for name, term in (terms or {}).items():
            if not isinstance(term, Loss) or name == "loss":
                raise TypeError(f"terms must map names other than 'loss' to Loss objects, got {name!r}")
        if grad and not self.solver.needs_grad:
            raise RuntimeError("this simulator was built without gradients: build(requires_grad=True) to call "
                               "rollout(..., grad=True)")
        if grad and (terms or step_offset or horizon is not None):
            raise ValueError("rollout(grad=True) takes one loss over the rollout's own steps (no terms, step_offset "
                             "or horizon)")
        twists = self._action_sequence(actions)
        n = len(twists)
        horizon = horizon if horizon is not None else step_offset + n
        losses = {"loss": loss} if loss is not None else {}
        losses.update(terms or {})
        applied, clipped, pos, rot = self._poses(twists)
        start = self.get_state()
        K = n if not grad else max(1, int(segment_steps or math.ceil(math.sqrt(n))))
        checkpoints = {}
        values = {k: np.zeros(n) for k in losses}
        what = "the gas solver's kernels" + (" (forward and backward)" if grad else "")
        with self._first_run("grad" if grad else "fast", what):
            for g in range(n):
                if grad and g % K == 0:
                    checkpoints[g // K] = self.get_state()
                self._gas_step(start.step + g, pos[g + 1], rot[g + 1], applied[g])
                self._tool_p, self._tool_R = pos[g + 1].copy(), rot[g + 1].copy()
                self.step_count = start.step + g + 1
                k = step_offset + g + 1
                if any(lo.active(k, horizon) for lo in losses.values()):
                    st = self.step_state()
                    st.step, st.time = k, k * self.dt
                    for name, lo in losses.items():
                        values[name][g], _ = lo(st, horizon, grad=False)
                if progress:
                    progress("forward", g + 1, n)
            step_losses = values.pop("loss", np.zeros(n))
            result = GasRolloutResult(float(step_losses.sum()), step_losses, clipped.any(axis=2), terms=values)
            result.stats["gas"] = self.solver_report()
            if grad:
                final = self.get_state()
                self._backward(result, start, checkpoints, K, applied, clipped, pos, rot, loss, progress)
                self.set_state(final)
        return result

    # --- gradients ------------------------------------------------------------------------------------------------
    def _add_loss_grad(self, cv, cq, gr: dict):
        """carry += the loss gradient of one step (cell-centred keys to faces and scalars)."""
        names = self.spec.scalar_names
        add_q = np.zeros(cq.shape)
        add_v = None
        for key, value in gr.items():
            if key == "gas_velocity":
                add_v = face_grad_from_cells(np.asarray(value, dtype=np.float64))
            elif key.startswith("gas_"):
                name = key[4:]
                if name not in names:
                    raise KeyError(f"the loss returned a gradient for gas field {name!r}; fields: {names}")
                add_q[names.index(name)] += value
            elif np.any(np.asarray(value) != 0) and key not in ("tool_position", "tool_rotation"):
                raise KeyError(f"the loss returned a gradient with respect to {key!r}, which a gas scene does not have")
        if add_v is not None:
            for d in range(3):
                cv[d].from_numpy(cv[d].to_numpy() + add_v[d])
        if np.any(add_q):
            cq.from_numpy(cq.to_numpy() + add_q)

    def _backward(self, result, start, checkpoints, K, applied, clipped, pos, rot, loss, progress):
        from fluidlab_core.engine.checkpoint import NonFiniteGradientError, rotation_tangent_grad

        s = self.solver
        n = len(applied)
        nt = len(self.tool_specs)
        cv, cq = s.carry_fields()
        for f in (*cv, cq):
            f.fill(0)
        s.clear_param_grads()
        gp = np.zeros((nt, 3))  # dL/dp of the pose at the end of the step being undone
        gth = np.zeros((nt, 3))  # dL/dθ (tangent) of that pose's rotation
        grad_actions = np.zeros_like(applied)
        mask = T.action_masks(self.tool_specs) if nt else np.zeros((0, 6))
        sub_dt = self.dt / self.substeps
        for seg in reversed(range(-(-n // K))):
            steps = range(seg * K, min(n, (seg + 1) * K))
            self.set_state(checkpoints[seg])
            starts = []
            loss_grads = {}
            for g in steps:  # recompute the segment, keeping every substep's start and the loss gradients
                if nt:
                    s.set_tools(pos[g + 1], rot[g + 1], applied[g, :, :3], applied[g, :, 3:])
                subs = []
                for j in range(self.substeps):
                    subs.append(s.read_state())
                    s.step(sub_dt, (start.step + g) * self.substeps + j)
                starts.append(subs)
                self._solid_cache = None
                self._tool_p, self._tool_R = pos[g + 1].copy(), rot[g + 1].copy()
                if loss is not None and loss.active(g + 1, n):
                    st = self.step_state()
                    st.step, st.time = g + 1, (g + 1) * self.dt
                    _, gr = loss(st, n, grad=True)
                    if gr:
                        loss_grads[g] = gr
                if progress:
                    progress("recompute", g + 1, n)
            for j_step in reversed(range(len(steps))):
                g = steps[j_step]
                if g in loss_grads:
                    gr = loss_grads.pop(g)
                    self._add_loss_grad(cv, cq, gr)
                    if "tool_position" in gr:
                        gp += gr["tool_position"]
                    if "tool_rotation" in gr:
                        gth += rotation_tangent_grad(np.asarray(gr["tool_rotation"]), rot[g + 1])
                if nt:
                    s.set_tools(pos[g + 1], rot[g + 1], applied[g, :, :3], applied[g, :, 3:])
                tool_g, bad = s.backward_substeps(starts[j_step], sub_dt, (start.step + g) * self.substeps, cv, cq)
                if tool_g is not None:  # (dL/dp, dL/dR, dL/dv, dL/dω) of the step's tools; dev_*: used below
                    dp, dR, dev_v, dev_w = tool_g
                    gp += dp
                    gth += rotation_tangent_grad(dR, rot[g + 1])
                if bad or not (np.all(np.isfinite(gp)) and np.all(np.isfinite(gth))):
                    raise NonFiniteGradientError(f"the gas gradient became NaN or infinite in {', '.join(bad) or 'the tool poses'} "
                                                 f"going back through step {g + 1}")
                if nt:
                    # the step's pose update: p_{g+1} = p_g + dt v_g, R_{g+1} = exp([ω_g dt]×) R_g
                    w = applied[g, :, 3:]
                    gv = dev_v + self.dt * gp
                    gw = dev_w.copy()
                    for i in range(nt):
                        gw[i] += self.dt * left_jacobian(w[i] * self.dt).T @ gth[i]
                        Q = rot[g + 1, i] @ rot[g, i].T
                        gth[i] = Q.T @ gth[i]
                    cl = clipped[g]
                    gp = gp + np.where(cl, -gv / self.dt, 0.0)  # a clipped v = (b − p)/dt moves with p, not the action
                    gv = np.where(cl, 0.0, gv)
                    grad_actions[g, :, :3] = gv
                    grad_actions[g, :, 3:] = gw
                    grad_actions[g] *= mask
                if progress:
                    progress("backward", n - g, n)
        result.grad_actions = grad_actions
        result.grad_tool_position = gp
        result.grad_tool_rotation = gth
        result.grad_velocity = tuple(f.to_numpy() for f in cv)
        result.grad_scalars = cq.to_numpy()
        result.grad_sources = s.source_grads()

    def set_viscosity(self, viscosity: float):
        """Change the kinematic viscosity ν (m²/s) without rebuilding; refused above the explicit limit
        ν dt/Δx² ≤ 1/6 per gas substep."""
        from fluidlab_core.gas import _number

        nu = _number("viscosity", viscosity, 0.0)
        sub = self.dt / self.substeps
        if nu * sub / self.spec.dx ** 2 > 1.0 / 6.0:
            raise ValueError(f"viscosity {nu:.3g} m²/s breaks the explicit limit ν Δt/Δx² ≤ 1/6 (Δt {sub:.3g} s, Δx "
                             f"{self.spec.dx:.3g} m): at most {self.spec.dx ** 2 / (6 * sub):.3g} m²/s at this step")
        self.spec.viscosity = nu
        self.solver.nu[None] = nu

    def set_solver(self, tolerance: float | None = None, max_iterations: int | None = None, on_fail: str | None = None):
        """Change the pressure solve's relative tolerance, iteration cap or what missing it does ("raise", "warn")."""
        from fluidlab_core.gas import _number

        if tolerance is not None:
            tol = _number("tolerance", tolerance, 0.0, strict=True)
            if tol >= 1.0:
                raise ValueError(f"tolerance is a relative residual below 1, got {tolerance}")
            self.spec.tolerance = tol
        if max_iterations is not None:
            if not (isinstance(max_iterations, (int, np.integer)) and max_iterations >= 1):
                raise ValueError(f"max_iterations must be an integer >= 1, got {max_iterations!r}")
            self.spec.max_iterations = int(max_iterations)
        if on_fail is not None:
            if on_fail not in ("raise", "warn"):
                raise ValueError(f"on_fail must be 'raise' or 'warn', got {on_fail!r}")
            self.spec.on_fail = on_fail

    # --- sources ------------------------------------------------------------------------------------------------
    def source(self, name: str):
        names = [s.name for s in self.solver.sources]
        if name not in names:
            raise KeyError(f"no gas source named {name!r}; sources: {', '.join(names) or 'none'}")
        return self.solver.sources[names.index(name)]

    def set_source(self, name: str, **values):
        """Change a source's parameters: position, quaternion (its parent frame), speed (m/s), temperature (K),
        smoke (kg/m³) or a named scalar. Those it did not set at build cannot be switched on here."""
        src = self.source(name)
        for key, value in values.items():
            if key in ("position", "quaternion"):
                arr = np.asarray(value, dtype=np.float64)
                want = 3 if key == "position" else 4
                if arr.shape != (want,) or not np.all(np.isfinite(arr)):
                    raise ValueError(f"source {name!r}: {key} must be {want} finite numbers, got {value!r}")
                setattr(src, key, arr / np.linalg.norm(arr) if key == "quaternion" else arr)
            elif key in ("speed", "temperature", "smoke"):
                if getattr(src, key) is None:
                    raise ValueError(f"source {name!r} was built without {key}; add it with {key}=... to switch it")
                setattr(src, key, float(value))
            elif key in src.scalars:
                src.scalars[key] = float(value)
            else:
                raise KeyError(f"source {name!r} has no parameter {key!r}")
        self.solver.upload_sources()

    # --- pictures and viewers ---------------------------------------------------------------------------------------
    def temperature_range(self) -> tuple[float, float]:
        """(low, high) K of the temperatures the scene can hold: the initial and ambient ones and the sources'."""
        return self.spec.temperature_range()

    def render(self, path=None, view="iso", size=(800, 600), title=None, field: str = "temperature", slice_axis=2,
               slice_at=None, points=None, **_):
        """A picture of one slice of a gas field (default: the temperature on the horizontal mid-plane, on the
        scene's fixed colour scale), with the statics and tools drawn as grey cells and `points` (default
        `self.render_points`, e.g. a task's sensors) as dots; see fluidlab_core/render.gas_slice. Writes a PNG if
        `path`; returns the (H, W, 3) uint8 image."""
        from fluidlab_core import render

        pts = points if points is not None else getattr(self, "render_points", None)
        return render.gas_slice(self.view(), self.spec, path, field=field, axis=slice_axis, at=slice_at, size=size,
                                title=title, points=pts, tools=self._tool_p, time=self.time)

    def _slice_cells(self) -> np.ndarray:
        """Flat indices of the gas cells of the horizontal mid-plane (what viewers draw)."""
        nx, ny, nz = self.solver.shape
        k = nz // 2
        idx = np.arange(nx * ny * nz).reshape(nx, ny, nz)[:, :, k].ravel()
        return idx[~self.solid().reshape(-1)[idx]]

    def positions(self, h=None) -> np.ndarray:
        """For viewers (sim_node's ~/particles, recordings): the centres (M, 3) m of the gas cells on the
        horizontal mid-plane; their colours, the temperature's, are `particle_colors()`. A gas scene has no
        particles, so `h` must be None."""
        if h is not None:
            raise KeyError("a gas scene has no particle bodies")
        return self.cell_centers().reshape(-1, 3)[self._slice_cells()]

    def velocities(self, h=None) -> np.ndarray:
        if h is not None:
            raise KeyError("a gas scene has no particle bodies")
        return self.gas_velocity().reshape(-1, 3)[self._slice_cells()]

    def particle_colors(self) -> np.ndarray:
        """(M, 3) uint8 colours of `positions()`: the temperature on the scene's scale (blue cool, red warm)."""
        import matplotlib

        lo, hi = self.temperature_range()
        t = (self.gas_field("temperature").reshape(-1)[self._slice_cells()] - lo) / (hi - lo)
        rgb = matplotlib.colormaps["coolwarm"](np.clip(t, 0.0, 1.0))[:, :3]
        return (255 * rgb).astype(np.uint8)
