"""The user-facing simulator returned by `Scene.build()`: stepping, rollouts, reading particles, state round trips.

A Simulator holds the scene's Model (what does not change), the fast solver and its device state (one slot,
stepped in place), and with `requires_grad=True` the differentiable solver. Every way of advancing it goes
through the one rollout loop (engine/rollout.py): `step` is a rollout without a loss, `rollout(grad=False)`
runs the fast solver, `rollout(grad=True)` the checkpointed differentiable one (engine/checkpoint.py) from
the same state, and both end in the rollout's final state.
"""
from __future__ import annotations

import contextlib

import numpy as np

from fluidlab_core import runtime
from fluidlab_core.engine import rollout as loop
from fluidlab_core.engine import tools as T
from fluidlab_core.engine.state import NonFiniteStateError, State

__all__ = ["Simulator", "NonFiniteStateError"]


class Simulator:
    """Steps an MLS-MPM scene. One `step(action)` advances dt seconds in `substeps` substeps, moving the tools
    with the action.

    positions(h)/velocities(h) return (N, 3) float64 arrays in the world frame (m, m/s) for a particle
    handle from `Scene.add_particles` (or its name). `get_state()`/`set_state()` round-trip the whole
    state (a `State`) exactly.
    """

    def __init__(self, scene, model, solver, state, handles, config, diff=None):
        self.scene = scene
        self.model = model  # engine/model.py: grid, materials, statics, tool shapes
        self.solver = solver  # engine/solver.py: FastSolver
        self.state = state  # engine/state.py: StateBuffer of one slot, stepped in place
        self.diff = diff  # engine/diff_solver.py: DiffSolver, when built with requires_grad=True
        self.handles = {h.name: h for h in handles}
        self._config = config
        self.step_count = 0
        self.check_finite_every = 1  # steps between NaN checks (0: never)
        self._static_points = None  # sampled statics for pictures, made on first render
        self._tool_points = None  # tool shapes sampled in their own frames, likewise
        self._compiled = set()  # which solvers have run (their first run compiles their kernels)
        self.gas = None  # engine/gas.GasSolver in a scene with gas and particles (attach_gas)
        self.gas_coupling = None
        self._fast_gas = None  # the gas's step on the fast state (gas_coupling.CoupledGas)

    # --- stepping ---------------------------------------------------------------------------------------
    @property
    def dt(self) -> float:
        """Seconds per step."""
        return self.model.step_dt

    @property
    def substeps(self) -> int:
        return self.model.substeps

    @property
    def time(self) -> float:
        """Simulated time since the start or the last set_state (s)."""
        return self.step_count * self.dt

    @property
    def n_particles(self) -> int:
        return self.model.n_particles

    @property
    def tool_specs(self) -> list:
        """The tools as the scene describes them (engine/tools.ToolSpec)."""
        return self.model.tool_specs

    def _check_alive(self):
        current = runtime.current()
        if current is None or current.generation != self._config.generation:
            raise RuntimeError("this simulator was built before fluidlab_core.init() or fluidlab_core.runtime.reset() "
                               "reset Taichi, and its fields are gone; build the scene again")

    def step(self, action=None, n: int = 1, emit=None) -> dict:
        """Advance `n` steps of dt seconds each, holding the tools' velocity `action` over every step.

        action: for one tool a (6,) array (vx, vy, vz, wx, wy, wz) in m/s and rad/s in the world frame; for
        several an (n_tools, 6) array or a {tool name: (6,)} dict; None keeps tools still. Dimensions outside a
        tool's action mask are ignored. emit: which emitters run (a bool, one per emitter, or a {name: bool}
        dict; default all). Returns info: {"clipped": {tool name: True if the workspace clipped its motion in
        any of these steps}} and, in a scene with emitters, {"emitters": {name: {"emitted": particles so far,
        "pool", "mass" (kg in the scene), "exhausted": the pool ran out and it stopped emitting, "blocked": why
        it did not emit in some of these steps (its exit in a solid), or ""}}}."""
        self._check_alive()
        if action is not None and not self.tool_specs:
            raise ValueError("this scene has no tools, so step() takes no action")
        twist = T.parse_action(self.tool_specs, action)
        on = np.repeat(self._parse_emit(emit)[None], int(n), axis=0)
        first = self.step_count
        clipped, _, blocked = self._run(np.repeat(twist[None], int(n), axis=0), {}, emit_on=on)
        info = {"clipped": {spec.name: bool(clipped[:, i].any()) for i, spec in enumerate(self.tool_specs)}}
        if self.model.has_emitters:
            info["emitters"] = self.emitter_report(blocked, first)
        return info

    # --- emitters ---------------------------------------------------------------------------------------
    @property
    def emitter_specs(self) -> list:
        return self.model.emitter_specs

    def _parse_emit(self, emit) -> np.ndarray:
        """(n_emitters,) bools from None (all on), a bool, a sequence or a {name: bool} dict."""
        specs = self.emitter_specs
        if emit is None or emit is True:
            return np.ones(len(specs), dtype=bool)
        if emit is False:
            return np.zeros(len(specs), dtype=bool)
        if isinstance(emit, dict):
            names = [s.name for s in specs]
            out = np.ones(len(specs), dtype=bool)
            for key, value in emit.items():
                if key not in names:
                    raise KeyError(f"no emitter named {key!r}; emitters: {', '.join(names) or 'none'}")
                out[names.index(key)] = bool(value)
            return out
        arr = np.asarray(emit, dtype=bool).reshape(-1)
        if arr.shape != (len(specs),):
            raise ValueError(f"emit must switch {len(specs)} emitter(s), got {arr.shape[0]} values")
        return arr

    def _emission_plan(self, twists, emit_on):
        """The emitters' on/off per step (N, E), with tool-carried nozzles off where their exit would be in a
        solid, and {emitter: (first blocked step, reason)}."""
        from fluidlab_core.engine import emitters

        n = len(twists)
        on = np.ones((n, self.model.n_emitters), dtype=bool) if emit_on is None else np.asarray(emit_on, dtype=bool)
        if on.shape != (n, self.model.n_emitters):
            raise ValueError(f"emit_on must have shape ({n}, {self.model.n_emitters}), got {on.shape}")
        if not self.model.emitters_on_tools:
            return on, {}
        position, rotation = self.state.read_tools(0)
        applied, _ = T.plan(self.tool_specs, position, twists, self.dt, self.substeps)
        pos, rot = T.plan_poses(self.tool_specs, position, rotation, applied, self.dt)
        return emitters.plan(self.emitter_specs, self.scene.statics, self.scene.lower, self.scene.upper,
                             self.scene.dx, rot, pos, on)

    def emitter_report(self, blocked: dict | None = None, first_step: int = 0) -> dict:
        """Per emitter: particles emitted, pool, mass in the scene (kg), whether its pool ran out, and why it was
        blocked in the steps just run, which began after step `first_step` (see `step`)."""
        from fluidlab_core.engine import emitters

        emitted, on_time = self.state.emission
        ran_out = emitters.exhausted(self.emitter_specs, emitted, on_time)
        out = {}
        for e, spec in enumerate(self.emitter_specs):
            g_why = (blocked or {}).get(e)
            out[spec.name] = {
                "emitted": int(emitted[e]), "pool": spec.pool,
                "mass": float(emitted[e] * spec.particle_volume * spec.material.density),
                "exhausted": bool(ran_out[e]),
                "blocked": f"emitted nothing in step {first_step + g_why[0] + 1} (and maybe later ones): {g_why[1]}"
                if g_why else ""}
            if ran_out[e]:
                out[spec.name]["message"] = (f"emitter {spec.name!r} used up its pool of {spec.pool} particles and "
                                             f"stopped emitting; build with a larger pool or duration")
        return out

    def emitter_pose(self, name: str) -> np.ndarray:
        """(x, y, z, qx, qy, qz, qw) of a nozzle frame in its parent frame (the world, or its tool's frame)."""
        spec = self._emitter(name)
        return np.concatenate([spec.position, spec.quaternion])

    def set_emitter_pose(self, name: str, pose):
        """Move a nozzle (in its parent frame); a fixed nozzle whose exit would lie in a solid is refused. The
        gradients of a rollout with respect to this pose are `grad_emitter_position/rotation`."""
        from fluidlab_core.engine.emitters import blocked_reason

        spec = self._emitter(name)
        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape != (7,) or not np.all(np.isfinite(pose)) or np.linalg.norm(pose[3:]) < 1e-9:
            raise ValueError(f"emitter pose must be (x, y, z, qx, qy, qz, qw) with a non-zero quaternion, got {pose!r}")
        old = spec.position, spec.quaternion
        spec.position, spec.quaternion = pose[:3].copy(), pose[3:] / np.linalg.norm(pose[3:])
        if spec.tool is None:
            why = blocked_reason(spec, self.scene.statics, self.scene.lower, self.scene.upper, self.scene.dx)
            if why:
                spec.position, spec.quaternion = old
                raise ValueError(f"emitter {name!r} cannot emit there: {why}")
        e = self.emitter_specs.index(spec)
        em = self.model.emitters
        em.position[e] = spec.position.tolist()
        em.rotation[e] = spec.rotation().tolist()

    def _emitter(self, name: str):
        names = [s.name for s in self.emitter_specs]
        if name not in names:
            raise KeyError(f"no emitter named {name!r}; emitters: {', '.join(names) or 'none'}")
        return self.emitter_specs[names.index(name)]

    def active_rows(self) -> np.ndarray | None:
        """(N,) bools: the particles that take part now (None: all, in a scene without emitters)."""
        return loop.active_rows(self.model, self.state.emission[0])

    def rollout(self, actions, loss, grad: bool = False, segment_steps: int | None = None, checkpoint_dir=None,
                progress=None, *, terms: dict | None = None, step_offset: int = 0, horizon: int | None = None,
                emit_on=None):
        """Run len(actions) steps from the current state and return the loss (and its gradients).

        actions: (N, 6) for one tool or (N, n_tools, 6): tool twists per step as in `step` (N ≥ 1); for a scene
            without tools pass an integer N (steps with no action).
        loss: a `fluidlab_core.losses.Loss`, evaluated after the steps it names.
        grad: False runs the fast forward solver; True runs the differentiable solver (build with
            requires_grad=True) with gradient checkpointing and returns the gradients with respect to every
            action, the initial tool poses and the initial particle state (see rollout.RolloutResult); in a scene
            with gas (attach_gas) the gas steps with the particles and is differentiated with them, and the
            gradients with respect to its start come back too (engine/gas_coupling.py).
        segment_steps: steps per checkpoint segment (default: as long as the buffer chosen at build allows, see
            checkpoint.plan_segments).
        checkpoint_dir: keep segment checkpoints in a private folder under this directory instead of in memory.
        progress: optional callable(phase, done, total), called once per step of each phase.
        terms: {name: Loss} evaluated beside `loss` without gradients; their per-step values come back in
            `result.terms[name]` (e.g. a task's reward term).
        step_offset, horizon: the step numbers and horizon the losses see (default: the rollout's own steps
            1 … N; an environment stepping one step at a time passes its episode's).
        emit_on: (N, n_emitters) bools, which emitters run in each step (default: all, always).

        The simulator ends in the rollout's final state, as after the same calls to `step`."""
        from fluidlab_core.engine.checkpoint import rollout_with_grad
        from fluidlab_core.losses import Loss

        self._check_alive()
        if not isinstance(loss, Loss):
            raise TypeError(f"loss must be a fluidlab_core.losses.Loss, got {type(loss).__name__}")
        for name, term in (terms or {}).items():
            if not isinstance(term, Loss) or name == "loss":
                raise TypeError(f"terms must map names other than 'loss' to Loss objects, got {name!r}: "
                                f"{type(term).__name__}")
        twists = self._action_sequence(actions)
        if grad:
            if self.diff is None:
                raise RuntimeError("this simulator was built without gradients: build(requires_grad=True) to "
                                   "call rollout(..., grad=True)")
            if terms or step_offset or horizon is not None:
                raise ValueError("rollout(grad=True) takes one loss over the rollout's own steps (no terms, "
                                 "step_offset or horizon)")
            start = self.step_count
            coupled = None
            if self.gas is not None:
                if self.model.has_emitters:
                    raise NotImplementedError("rollout(grad=True) of a scene with gas, particles and emitters: the "
                                              "gas's coupling to emitted particles has no gradient yet")
                from fluidlab_core.engine.gas_coupling import CoupledGas

                coupled = CoupledGas(self.gas_coupling, self.diff.state, self.dt, start)
            on, blocked = self._emission_plan(twists, emit_on) if self.model.has_emitters else (None, {})
            with self._first_run("grad", "the differentiable solver's kernels (forward and backward)"):
                result, final = rollout_with_grad(
                    self.diff, self.get_state(), twists, loss, True, segment_steps, checkpoint_dir, progress,
                    on_nonfinite=lambda fields, p, step: self._raise_nonfinite(fields, p, start + step), emit_on=on,
                    coupled=coupled)
            self.set_state(final)
            if self.model.has_emitters:
                result.stats["emitters"] = self.emitter_report(blocked, start)
            return result
        first = self.step_count
        clipped, values, blocked = self._run(twists, {"loss": loss, **(terms or {})}, progress, step_offset, horizon,
                                             emit_on)
        step_losses = values.pop("loss")
        result = loop.RolloutResult(float(step_losses.sum()), step_losses, clipped.any(axis=2), terms=values)
        if self.model.has_emitters:
            result.stats["emitters"] = self.emitter_report(blocked, first)
        return result

    def _run(self, twists, losses, progress=None, step_offset=0, horizon=None, emit_on=None):
        """The fast solver through the rollout loop: (clipped (N, n_tools, 3), {name: per-step values},
        {emitter: (first blocked step, reason)})."""
        on, blocked = self._emission_plan(twists, emit_on) if self.model.has_emitters else (None, {})
        position, _ = self.state.read_tools(0)
        applied, clipped = T.plan(self.tool_specs, position, twists, self.dt, self.substeps)
        start = self.step_count
        stepper = loop.FastStepper(self.solver, self.state, self.dt, self.check_finite_every, self._raise_nonfinite,
                                   first_step=start, after_step=self._gas_step if self.gas is not None else None)

        def tick(phase, done, total):
            self.step_count = start + done
            if progress:
                progress(phase, done, total)

        with self._first_run("fast", "the simulator's kernels"):
            values, _ = loop.run(stepper, applied, losses, emit_on=on, step_offset=step_offset, horizon=horizon,
                                 progress=tick)
        return clipped, values, blocked

    # --- gas (a scene with particles and gas: engine/gas_coupling.py) --------------------------------------------
    def attach_gas(self, gas, coupling):
        """Step `gas` (a GasSolver) after every step, coupled to the particles by `coupling`."""
        self.gas, self.gas_coupling = gas, coupling
        gas.write_state(gas.initial_state())
        self._gas_start = gas.read_state()

    def _gas_step(self, step: int, twist: np.ndarray):
        """The gas's step after the particles' (operator splitting, engine/gas_coupling.py), on the fast state."""
        from fluidlab_core.engine.gas_coupling import CoupledGas

        if self._fast_gas is None:
            self._fast_gas = CoupledGas(self.gas_coupling, self.state, self.dt, 0)
        self._fast_gas.after_step(step, 0, twist, False)

    def gas_state(self):
        """The gas's state (fluidlab_core.gas.GasState) in a scene with particles and gas."""
        if self.gas is None:
            raise ValueError("this scene has no gas (Scene.add_gas)")
        return self.gas.read_state()

    def set_gas_state(self, state=None):
        """Set the gas's state (None: its start); get_state/set_state cover the particles and tools only."""
        if self.gas is None:
            raise ValueError("this scene has no gas (Scene.add_gas)")
        self.gas.write_state(self._gas_start if state is None else state)

    def gas_view(self):
        """The gas's cell fields as a loss or a picture sees them (fluidlab_core.gas.GasView)."""
        from fluidlab_core.gas import GasView

        return GasView.of(self.gas_state(), self.gas.spec, self.gas.solid.to_numpy() != 0)

    def gas_field(self, name: str) -> np.ndarray:
        return self.gas_view().field(name)

    def _first_run(self, solver: str, what: str):
        """runtime.compiling around a solver's first run (which compiles its kernels), nothing afterwards."""
        if solver in self._compiled:
            return contextlib.nullcontext()
        return runtime.compiling(what, done=lambda: self._compiled.add(solver))

    def _action_sequence(self, actions) -> np.ndarray:
        """(N, n_tools, 6) masked twists from the forms `rollout` accepts (tools.action_sequence)."""
        return T.action_sequence(self.tool_specs, actions)

    def tool_pose(self, name: str) -> np.ndarray:
        """(x, y, z, qx, qy, qz, qw) of a tool's frame in the world (m)."""
        names = [spec.name for spec in self.tool_specs]
        if name not in names:
            raise KeyError(f"no tool named {name!r}; tools: {', '.join(names) or 'none'}")
        self._check_alive()
        position, rotation = self.state.read_tools(0)
        i = names.index(name)
        return T.pose_of(position[i], rotation[i])

    def step_state(self):
        """What a loss sees of the current state (losses.StepState: float64 positions, velocities, tool poses)."""
        from fluidlab_core.losses import StepState

        self._check_alive()
        x, v, tp, tR = self.state.read_steps([0])
        return StepState(self.step_count, self.time, x[0].astype(np.float64), v[0].astype(np.float64), tp[0], tR[0],
                         self.active_rows())

    def check_finite(self):
        """Raise NonFiniteStateError naming the field, step and particle if any state is NaN or infinite."""
        self._check_alive()
        fields, particle = self.state.nonfinite(0)
        if fields:
            self._raise_nonfinite(fields, particle, self.step_count)

    def _raise_nonfinite(self, fields, p: int, step: int):
        body = next((h for h in self.handles.values() if h.start <= p < h.start + h.count), None)
        where = f"particle {p} of body {body.name!r} ({body.material.name})" if body else f"particle {p}"
        raise NonFiniteStateError(
            f"NaN or infinity in particle {', '.join(fields)} at step {step} (t = {step * self.dt:.4g} s), "
            f"first at {where}. The explicit solver went unstable: use more substeps (smaller dt), a softer "
            f"material, or lower speeds.")

    # --- reading ----------------------------------------------------------------------------------------
    def handle(self, h):
        if isinstance(h, str):
            try:
                return self.handles[h]
            except KeyError:
                raise KeyError(f"no particle body named {h!r}; bodies: {', '.join(self.handles)}") from None
        return h

    def _rows(self, read, h):
        """The rows of body h (all bodies if None) that take part, of the per-particle array that read() returns
        (read after the check that the simulator outlived no reset): a body being emitted has the particles that
        have left its nozzle."""
        self._check_alive()
        data = read()
        rows = np.arange(self.n_particles)[slice(None) if h is None else self.handle(h).slice]
        active = self.active_rows()
        if active is not None:
            rows = rows[active[rows]]
        return data[rows].astype(np.float64)

    def positions(self, h=None) -> np.ndarray:
        """(N, 3) particle positions (m) of body `h` (all bodies if None): the particles that take part, so of a
        body an emitter is filling, those that have left its nozzle (`active_rows`)."""
        return self._rows(lambda: self.state.x.to_numpy()[0], h)

    def velocities(self, h=None) -> np.ndarray:
        """(N, 3) particle velocities (m/s)."""
        return self._rows(lambda: self.state.v.to_numpy()[0], h)

    def deformation_gradients(self, h=None) -> np.ndarray:
        return self._rows(lambda: self.state.F.to_numpy()[0], h)

    def volumes(self, h=None) -> np.ndarray:
        """Current particle volumes V⁰·det F (m³)."""
        rest = self._rows(self.model.rest_volume.to_numpy, h)
        return rest * np.linalg.det(self.deformation_gradients(h))

    def stresses(self, h=None) -> np.ndarray:
        """(N, 3, 3) Cauchy stress σ of each particle (Pa), from its constitutive model at its current F and C. With
        Scene(pressure="projection") a liquid's pressure is the projection's, on the grid, and not in these (its F
        stays I: only its viscous part shows)."""
        return self._rows(lambda: self.solver.stresses(self.state), h)

    def pressures(self, h=None) -> np.ndarray:
        """Cauchy pressure −tr(σ)/3 of each particle (Pa), from `stresses` (so not the projection's pressure)."""
        return -np.trace(self.stresses(h), axis1=1, axis2=2) / 3.0

    def particle_colors(self) -> np.ndarray:
        """(N, 3) uint8 colour of every particle row, by its body's material."""
        colors = np.zeros((self.n_particles, 3), dtype=np.uint8)
        for h in self.handles.values():
            colors[h.slice] = np.round(255 * np.asarray(h.material.color)).astype(np.uint8)
        return colors

    def masses(self, h=None) -> np.ndarray:
        return self._rows(self.model.mass.to_numpy, h)

    # --- pictures ---------------------------------------------------------------------------------------
    def render(self, path=None, view="iso", size=(800, 600), title=None, bodies=None, gas: bool = True,
               field: str = "temperature", slice_axis: int = 2, slice_at: float | None = None):
        """A PNG picture of the current state (particles coloured by material, statics in grey and cut away on
        the camera's side, the domain box drawn), written to `path` if given; returns the image as an (H, W, 3)
        uint8 array. `view` is a name from fluidlab_core.render.VIEWS or (azimuth_deg, elevation_deg).

        In a scene with gas (Scene.add_gas beside particles) the picture has a second panel on the right, of the
        same size (so the image is twice `size` wide): a slice of the gas field `field` ("temperature" on the
        scene's fixed colour scale, "smoke", "speed" or a named scalar) across axis `slice_axis` at `slice_at` m
        (default the gas box's middle), as GasSimulator.render and fluidlab_core.render.gas_slice draw it;
        gas=False leaves it out."""
        from fluidlab_core.render import Layer, render, view_axes

        if self.gas is not None and gas:
            picture = self.render(None, view, size, title, bodies, gas=False)
            return _beside_gas_slice(self, picture, path, field, slice_axis, slice_at, size)

        if self._static_points is None:
            self._static_points = [st.shape.sample(self.scene.dx) for st in self.scene.statics]
        # cutaway: statics are drawn only behind the domain's centre, so they never hide what is inside them
        toward = view_axes(view)[2]
        centre = 0.5 * (self.scene.lower + self.scene.upper)
        layers = []
        if self._tool_points is None:
            self._tool_points = [spec.shape.sample(0.5 * self.scene.dx) for spec in self.tool_specs]
        position, rotation = self.state.read_tools(0)
        for i, (spec, local) in enumerate(zip(self.tool_specs, self._tool_points)):
            if len(local):
                layers.append(Layer(local @ rotation[i].T + position[i], spec.color, spec.name))
        for st, points in zip(self.scene.statics, self._static_points):
            behind = points[(points - centre) @ toward < 0.0]
            if len(behind):
                layers.append(Layer(behind, (0.72, 0.72, 0.74), st.name))
        for h in self.handles.values():
            if bodies is None or h.name in bodies:
                x = self.positions(h)  # of a body being emitted: what has left its nozzle
                if len(x):
                    layers.append(Layer(x, h.material.color, h.name))
        return render(layers, path, view=view, bounds=(self.scene.lower, self.scene.upper), size=size, title=title)

    # --- state ------------------------------------------------------------------------------------------
    def start_hydrostatic(self) -> float:
        """Give the liquids the compression of hydrostatic equilibrium in their present positions, so that a scene
        built at rest (every particle at J = 1) does not first fall into its own pressure and ring.

        A weakly compressible liquid (engine/constitutive.py) has the pressure p = λ (1 − J). Each particle of a
        fluid material gets J = 1 − p/λ, F = J^(1/3) 1, with p = |g| × (the mass above it in its column of the
        grid, Δx × Δx across, plus half its own) / Δx²: the weight per unit area of everything over it, liquid
        or not, as in layered hydrostatics p(z) = |g| ∫_z ρ dz'. Nothing else changes (positions, velocities,
        solids' F). Meant for a state at rest with gravity along an axis; returns the largest 1 − J given."""
        from fluidlab_core.engine import constitutive

        if self.model.projection:
            raise ValueError("start_hydrostatic compresses a weakly compressible liquid; with "
                             "Scene(pressure='projection') the liquid is incompressible and starts at rest as it is")
        g = np.asarray(self.model.gravity, dtype=np.float64)
        axis = int(np.argmax(np.abs(g)))
        if not np.any(g) or np.count_nonzero(g) != 1:
            raise ValueError(f"start_hydrostatic needs gravity along one axis, got {tuple(g)} m/s²")
        up = -np.sign(g[axis])
        state = self.get_state()
        x = state.x.astype(np.float64)
        mass = self.model.mass.to_numpy().astype(np.float64)
        active = self.active_rows()
        if active is None:
            active = np.ones(len(x), dtype=bool)
        lam = np.zeros(len(x))
        for h in self.handles.values():
            if constitutive.get(h.material.model).fluid:
                lam[h.slice] = h.material.lam
        dx = self.model.dx
        across = [d for d in range(3) if d != axis]
        rows = np.nonzero(active)[0]
        column = np.floor((x[rows][:, across] - np.asarray(self.model.origin)[across]) / dx).astype(np.int64)
        key = column[:, 0] * (1 << 32) + column[:, 1]
        height = up * x[rows, axis]
        order = np.lexsort((-height, key))  # by column, then from the top down
        key_sorted, m_sorted = key[order], mass[rows][order]
        before = np.cumsum(m_sorted) - m_sorted  # the mass before each particle in the sorted order
        starts = np.r_[0, np.nonzero(np.diff(key_sorted))[0] + 1]  # where each column begins
        first = np.repeat(starts, np.diff(np.r_[starts, len(order)]))
        above = before - before[first]  # the mass above each particle in its own column
        pressure = np.zeros(len(x))
        pressure[rows[order]] = abs(g[axis]) * (above + 0.5 * m_sorted) / dx ** 2
        fluid = lam > 0.0
        J = np.ones(len(x))
        J[fluid] = 1.0 - pressure[fluid] / lam[fluid]
        if np.any(J[fluid] < 0.5):
            worst = int(np.argmin(np.where(fluid, J, np.inf)))
            raise ValueError(f"start_hydrostatic: particle {worst} would be compressed to J = {J[worst]:.3f} "
                             f"(pressure {pressure[worst]:.4g} Pa against a bulk modulus of {lam[worst]:.4g} Pa); "
                             f"the liquid is too soft for its depth")
        F = state.F.copy()
        F[fluid] = (J[fluid] ** (1.0 / 3.0))[:, None, None] * np.eye(3)
        state.F = F.astype(state.F.dtype)
        self.set_state(state)
        return float(np.max(1.0 - J[fluid])) if fluid.any() else 0.0

    def get_state(self) -> State:
        """A copy of the whole state: particles (x, v, C, F in the solver's precision), tool poses (float64) and
        the step count."""
        self._check_alive()
        return self.state.read(0, step=self.step_count)

    def set_state(self, state: State):
        """Restore a state from `get_state()` exactly. With Scene(pressure="projection") the solve's warm starts
        are not part of the state: the run from a restored state agrees with the original to the solve's tolerance,
        not bit for bit."""
        if not isinstance(state, State):
            raise TypeError(f"set_state takes a State (from get_state()), got {type(state).__name__}")
        self._check_alive()
        state.check_shapes(self.n_particles, len(self.tool_specs), self.model.n_emitters)
        self.state.write(0, state)
        if getattr(self.solver, "proj", None) is not None:
            self.solver.proj.reset()
        self.step_count = int(state.step)


def _beside_gas_slice(sim, picture: np.ndarray, path, field: str, axis: int, at, size) -> np.ndarray:
    """The particles' `picture` with a slice of the coupled gas's `field` beside it, both of `size` (render)."""
    from PIL import Image

    from fluidlab_core.render import _write_png_atomic, gas_slice

    position, _ = sim.state.read_tools(0)
    panel = gas_slice(sim.gas_view(), sim.gas.spec, None, field=field, axis=axis, at=at, size=size, tools=position,
                      time=sim.time)
    both = np.concatenate([picture, panel], axis=1)
    if path is not None:
        _write_png_atomic(Image.fromarray(both), path)
    return both
