"""The rollout loop: N steps of a solver with tool twists, losses evaluated after the steps they name.

Every way of running the simulation goes through `run`: `Simulator.step` and `Simulator.rollout` on the fast
solver, the forward pass of a checkpointed gradient rollout on the differentiable solver (checkpoint.py), and
through those `Task.evaluate`, the Gymnasium environments' `step` and sim_node's fluid twin.

    twists ──plan (workspace clipping, host, float64)──▶ applied twists
    for each block of steps:  stepper.run_block(block)            (fast solver: one step; differentiable
                              losses on stepper.states(block)      solver: one checkpoint segment)
                              stepper.check(block)                 (NaN watch)

A stepper adapts a solver to the loop: `FastStepper` steps a one-slot StateBuffer in place and reads it after
each step; `SegmentStepper` runs a whole checkpoint segment through the differentiable solver's buffer and
then reads the states of the steps a loss needs, many per launch.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fluidlab_core.engine.control import Control
from fluidlab_core.engine.emitters import schedule
from fluidlab_core.losses import StepState

LOSS_READ_BYTES = 16e6  # states read back per launch for the loss (SegmentStepper.states)


@dataclass
class RolloutResult:
    """Loss of a rollout and, when requested, its gradients (float64 numpy arrays, SI units).

    grad_actions: (N, n_tools, 6) dL/d(vx, vy, vz, wx, wy, wz) per step (zero where the action mask or the
    workspace clipping leaves an action no effect); grad_tool_position: (n_tools, 3) dL/dp of the initial
    tool origins; grad_tool_rotation: (n_tools, 3) dL/dθ for an initial rotation R₀ ← exp([θ]×) R₀ (world
    frame); grad_velocities / grad_positions: (n_particles, 3) dL/dv⁰, dL/dx⁰ of the initial particle state
    (zero on pool particles not yet emitted); grad_emitter_position / grad_emitter_rotation: the same for each
    emitter's nozzle pose in its parent frame (the world, or its tool's frame).
    terms: per-step values (N,) of the extra loss terms asked for by name (`terms=` of the rollout)."""

    loss: float
    step_losses: np.ndarray  # (N,) loss contributed after each step
    clipped: np.ndarray  # (N, n_tools) workspace clipping per step
    grad_actions: np.ndarray | None = None
    grad_tool_position: np.ndarray | None = None
    grad_tool_rotation: np.ndarray | None = None
    grad_velocities: np.ndarray | None = None
    grad_positions: np.ndarray | None = None
    grad_emitter_position: np.ndarray | None = None  # (n_emitters, 3) dL/d nozzle origin in its parent frame
    grad_emitter_rotation: np.ndarray | None = None  # (n_emitters, 3) dL/dθ for R ← exp([θ]×) R, parent frame
    # a scene with gas and particles: dL/d of the gas's start (face velocities (3 arrays), scalars
    # (n_q, nx, ny, nz)) and of its sources' parameters ({name: {...}} as GasRolloutResult.grad_sources)
    grad_gas_velocity: tuple | None = None
    grad_gas_scalars: np.ndarray | None = None
    grad_gas_sources: dict | None = None
    stats: dict = field(default_factory=dict)  # segments, segment_steps, checkpoint bytes, seconds
    terms: dict = field(default_factory=dict)


class FastStepper:
    """The fast solver on a one-slot StateBuffer, one step per block. `check_every`: steps between NaN checks
    (0: never); `on_nonfinite(fields, particle, step)` raises the caller's error."""

    def __init__(self, solver, state, dt: float, check_every: int = 0, on_nonfinite=None, first_step: int = 0,
                 after_step=None):
        self.solver, self.state, self.dt = solver, state, dt
        self.check_every, self.on_nonfinite = int(check_every), on_nonfinite
        self.first_step = first_step  # steps taken before the rollout (the NaN check counts from the start)
        self.block_steps = 1
        self.after_step = after_step  # after_step(g, twists): what else a step does (the gas of a coupled scene)

    def run_block(self, block: range, applied: np.ndarray, emit_on=None, progress=None, phase: str = "forward",
                  b: int = 0):
        for j, g in enumerate(block):
            self.solver.step(self.state, Control(applied[j], None if emit_on is None else emit_on[j]))
            if self.after_step is not None:
                self.after_step(self.first_step + g, applied[j])
            if progress:
                progress(phase, g + 1, None)

    def states(self, block: range, steps, step_offset: int):
        """The StepState after the block's last step (the only one the one-slot buffer holds)."""
        if not steps:
            return
        assert list(steps) == [block[-1]], "a one-slot buffer holds only the block's last step"
        x, v, tp, tR = self.state.read_steps([0])
        g = block[-1]
        k = step_offset + g + 1
        active = active_rows(self.solver.model, self.state.emission[0])
        yield g, StepState(k, k * self.dt, x[0].astype(np.float64), v[0].astype(np.float64), tp[0], tR[0], active)

    def check(self, block: range):
        step = self.first_step + block[-1] + 1
        if self.check_every and step % self.check_every == 0:
            fields, particle = self.state.nonfinite(0)
            if fields:
                self.on_nonfinite(fields, particle, step)


class SegmentStepper:
    """The differentiable solver, one checkpoint segment of `block_steps` steps per block, starting each from
    slot 0 of its buffer. `keep(block_index)`: whether the segment keeps the stores its backward reads.
    `after_step(g, slot, twist, keep)`: what else step g does once its end state is in `slot` (the gas of a
    coupled scene, gas_coupling.CoupledGas)."""

    def __init__(self, solver, block_steps: int, keep=lambda b: True, on_nonfinite=None, after_step=None):
        self.solver, self.block_steps, self.keep, self.on_nonfinite = solver, int(block_steps), keep, on_nonfinite
        self.after_step = after_step
        self.dt = solver.model.step_dt
        n = solver.n_particles
        itemsize = np.dtype(solver.np_real).itemsize
        self.per_chunk = max(1, int(LOSS_READ_BYTES // max(1, 2 * n * 3 * itemsize)))

    def run_block(self, block: range, applied: np.ndarray, emit_on=None, progress=None, phase: str = "forward",
                  b: int = 0):
        sub = self.solver.substeps
        state = self.solver.state
        state.write_twists(applied, sub)
        model = self.solver.model
        if model.has_emitters:  # the block's emission, from slot 0's, into every slot (emitters.schedule)
            on = np.ones((len(block), model.n_emitters), dtype=bool) if emit_on is None else emit_on
            counts, times, _ = schedule(model.emitter_specs, *state.read_emission(0), on, sub, model.dt)
            state.write_emission(0, counts, times)
            self.counts = counts
        keep = self.keep(b)
        substep = self.solver.substep if keep else self.solver.substep_no_store
        for j, g in enumerate(block):
            for i in range(sub):
                substep(j * sub + i)
            if self.after_step is not None:
                self.after_step(g, (j + 1) * sub, applied[j], keep)
            if progress:
                progress(phase, g + 1, None)

    def states(self, block: range, steps, step_offset: int):
        """StepStates after each of `steps` (within the buffered block), read a chunk of steps per launch and
        handed out one at a time (each in float64 only while the loss looks at it)."""
        sub = self.solver.substeps
        steps = list(steps)
        for i in range(0, len(steps), self.per_chunk):
            chunk = steps[i:i + self.per_chunk]
            slots = [(g - block.start + 1) * sub for g in chunk]
            x, v, tp, tR = self.solver.state.read_steps(slots)
            for j, g in enumerate(chunk):
                k = step_offset + g + 1
                active = active_rows(self.solver.model, self.counts[slots[j]]) if self.solver.model.has_emitters \
                    else None
                yield g, StepState(k, k * self.dt, x[j].astype(np.float64), v[j].astype(np.float64), tp[j], tR[j],
                                   active)

    def check(self, block: range):
        fields, particle = self.solver.state.nonfinite(len(block) * self.solver.substeps)
        if fields and self.on_nonfinite:
            self.on_nonfinite(fields, particle, block[-1] + 1)


def active_rows(model, emitted) -> np.ndarray | None:
    """(N,) bools: the particles that take part (every body's, and the pool particles emitted so far), or None
    in a scene without emitters."""
    if not model.has_emitters:
        return None
    spec = model.spec
    return (spec.emitter_of < 0) | (spec.pool_index < np.asarray(emitted)[np.maximum(spec.emitter_of, 0)])


def run(stepper, applied: np.ndarray, losses: dict, *, emit_on=None, step_offset: int = 0,
        horizon: int | None = None, want_grad=None, on_block=None, progress=None, phase: str = "forward",
        grads: dict | None = None):
    """Run len(applied) steps of `stepper` with the (clipped) twists `applied` (N, n_tools, 6) and the emitters
    switched on per step by `emit_on` (N, n_emitters) bools (None: always on).

    losses: {name: Loss}, each evaluated after the steps it names (StepState.step = step_offset + k after the
        rollout's k-th step, horizon `horizon`, default step_offset + N).
    want_grad(name, g): whether to keep the gradient of loss `name` after step g (0-based).
    on_block(b, block): called before block b (a range of 0-based steps) runs.
    progress(phase, done, total): called once per step.
    grads: the dict that collects {g: gradients} of the losses that asked for them (a new one by default).
    Returns ({name: (N,) values}, grads).
    """
    n = len(applied)
    horizon = horizon if horizon is not None else step_offset + n
    values = {name: np.zeros(n) for name in losses}
    grads = {} if grads is None else grads
    K = stepper.block_steps

    def tick(ph, done, _):
        if progress:
            progress(ph, done, n)

    for b in range(-(-n // K)):
        block = range(b * K, min(n, (b + 1) * K))
        if on_block:
            on_block(b, block)
        stepper.run_block(block, applied[block.start:block.stop],
                          None if emit_on is None else emit_on[block.start:block.stop], tick, phase, b)
        active = [g for g in block if any(loss.active(step_offset + g + 1, horizon) for loss in losses.values())]
        for g, state in stepper.states(block, active, step_offset):
            for name, loss in losses.items():
                keep = bool(want_grad and want_grad(name, g))
                values[name][g], gradient = loss(state, horizon, grad=keep)
                if keep:
                    grads[g] = state.only_active(gradient)
        stepper.check(block)
    return values, grads
