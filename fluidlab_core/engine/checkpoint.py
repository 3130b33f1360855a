"""Checkpointed rollouts: the loss of N steps and its gradient in memory that does not grow with N.

Works on a differentiable solver (diff_solver.py) and a start State; nothing else. The N steps are split into
segments of K steps, by default as long as the solver's slot buffer allows (plan_segments). The forward pass
(the rollout loop, rollout.run, one segment per block) keeps only each segment's start state, in host memory
or on disk. The backward pass goes through the segments last to first: it restores the start state, re-runs
the segment's forward to fill the buffer, seeds the gradient of the segment's last slot with the one handed
over from the next segment, and runs the substeps' gradients back to the first slot, whose gradient it hands
to the previous segment. Device memory is the buffer (K steps); host memory is N/K states.

Workspace clipping (tools.plan) is differentiated exactly: a linear-velocity component clipped at the
workspace boundary b becomes v = (b − p)/dt, so its gradient goes to the tool position p at the step's
start and none goes to the action.
"""
from __future__ import annotations

import os
import shutil
import tempfile
import time

import numpy as np

from fluidlab_core.engine import rollout, tools
from fluidlab_core.engine.rollout import RolloutResult
from fluidlab_core.engine.state import State

LOSS_GRAD_CACHE_BYTES = 256e6  # host memory for loss gradients kept from the forward pass (see rollout_with_grad)

__all__ = ["rollout_with_grad", "plan_segments", "CheckpointStore", "NonFiniteGradientError", "RolloutResult"]


class NonFiniteGradientError(FloatingPointError):
    """A gradient became NaN or infinite during the backward pass."""


class CheckpointStore:
    """Segment start states, in host memory or (with `directory`) as .npz files in a private folder."""

    def __init__(self, directory=None):
        self.memory: dict[int, State] = {}
        self.directory = None
        self.nbytes = 0
        if directory is not None:
            os.makedirs(directory, exist_ok=True)
            self.directory = tempfile.mkdtemp(prefix="checkpoints-", dir=directory)

    def put(self, k: int, state: State):
        arrays = state.arrays()
        self.nbytes += sum(np.asarray(a).nbytes for a in arrays.values())
        if self.directory is None:
            self.memory[k] = state
        else:
            np.savez(os.path.join(self.directory, f"{k}.npz"), **arrays)

    def get(self, k: int) -> State:
        if self.directory is None:
            return self.memory[k]
        with np.load(os.path.join(self.directory, f"{k}.npz")) as data:
            return State.from_arrays({key: data[key] for key in data.files})

    def close(self):
        self.memory.clear()
        if self.directory is not None:
            shutil.rmtree(self.directory, ignore_errors=True)


def rotation_tangent_grad(G: np.ndarray, R: np.ndarray) -> np.ndarray:
    """dL/dθ at θ = 0 for R ← exp([θ]×) R, from dL/dR = G: with M = G Rᵀ, (M₂₁ − M₁₂, M₀₂ − M₂₀, M₁₀ − M₀₁)."""
    M = G @ np.swapaxes(R, -1, -2)
    return np.stack([M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], axis=-1)


def plan_segments(n_steps: int, capacity_steps: int, segment_steps: int | None = None) -> int:
    """Steps per segment: `segment_steps` if given, else the fewest segments the buffer allows, of equal length.

    The buffer is allocated at build, so longer segments cost no memory: they mean fewer checkpoints (N/K
    host states, at most sqrt(N) whenever the buffer holds sqrt(N) steps) and less recomputation (every
    segment but the last is run twice, about N − K steps). A horizon that fits the buffer is one segment."""
    if capacity_steps < 1:
        raise ValueError("the gradient buffer holds no whole step: build with a larger grad_memory")
    if segment_steps is not None:
        k = int(segment_steps)
        if k < 1:
            raise ValueError(f"segment_steps must be at least 1, got {segment_steps}")
        if k > capacity_steps:
            raise ValueError(f"segment_steps={k} exceeds the gradient buffer of {capacity_steps} steps chosen at "
                             f"build (grad_memory); use segment_steps <= {capacity_steps} or build with more "
                             f"grad_memory")
        return min(k, n_steps)
    n_segments = -(-n_steps // capacity_steps)
    return -(-n_steps // n_segments)


def _default_nonfinite(fields, particle, step):
    from fluidlab_core.engine.state import NonFiniteStateError

    raise NonFiniteStateError(f"the rollout's state became NaN or infinite ({', '.join(fields)}) by step {step}, "
                              f"first at particle {particle}; use more substeps or slower actions")


def rollout_with_grad(solver, start: State, twists: np.ndarray, loss, grad: bool = True, segment_steps=None,
                      checkpoint_dir=None, progress=None, on_nonfinite=None, emit_on=None, coupled=None):
    """Run len(twists) steps from `start` on the differentiable solver (see the module docstring).

    twists: (N, n_tools, 6) masked tool twists, clipped here to the tools' workspaces; emit_on: (N, n_emitters)
    bools, the emitters switched on per step (None: always on). progress(phase, done,
    total) is called once per step with phase "forward", "recompute" or "backward". on_nonfinite(fields,
    particle, step) raises the caller's error for a NaN state. coupled: the gas of a scene with gas and particles
    (gas_coupling.CoupledGas), stepped after every step and differentiated with it; its start state is the gas's
    current state, and the gradients with respect to it come back in result.grad_gas_*. Returns (RolloutResult,
    the final State)."""
    model = solver.model
    n_steps, sub, dt = len(twists), model.substeps, model.step_dt
    K = plan_segments(n_steps, solver.capacity_steps, segment_steps)
    n_seg = -(-n_steps // K)
    store = CheckpointStore(checkpoint_dir)
    t0 = time.perf_counter()
    applied, clipped_dims = tools.plan(model.tool_specs, start.tool_position, twists, dt, sub)
    # what the backward reads is kept only where the backward follows before the buffer is run again
    stepper = rollout.SegmentStepper(solver, K, keep=lambda b: grad and b == n_seg - 1,
                                     on_nonfinite=on_nonfinite or _default_nonfinite,
                                     after_step=None if coupled is None else coupled.after_step)

    def on_block(b, block):
        if b > 0:
            solver.state.copy_slot(K * sub, 0)
        if grad:
            store.put(b, solver.state.read(0))
            if coupled is not None:
                coupled.segment_start(b)

    # the loss gradients of the last segment's steps, taken when its forward reads the state for the loss value,
    # so that its backward need not read the state again (as long as they fit LOSS_GRAD_CACHE_BYTES)
    loss_grads: dict = {}
    last = range((n_seg - 1) * K, n_steps)

    def want_grad(name, g):
        if not grad or g not in last:
            return False
        per_step = sum(a.nbytes for a in next(iter(loss_grads.values())).values()) if loss_grads else 0
        return len(loss_grads) * per_step < LOSS_GRAD_CACHE_BYTES

    try:
        solver.state.write(0, start)
        values, _ = rollout.run(stepper, applied, {"loss": loss}, emit_on=emit_on, want_grad=want_grad,
                                on_block=on_block, progress=progress, grads=loss_grads)
        step_losses = values["loss"]
        final_slot = len(last) * sub
        final = solver.state.read(final_slot, step=start.step + n_steps)
        forward_seconds = time.perf_counter() - t0
        result = RolloutResult(float(step_losses.sum()), step_losses, clipped_dims.any(axis=2))
        result.stats = {"segments": n_seg, "segment_steps": K, "buffer_steps": solver.capacity_steps,
                        "forward_seconds": forward_seconds}
        if grad:
            stepper.keep = lambda b: True  # the recompute pass keeps what each segment's backward reads
            _backward(solver, stepper, loss, result, applied, clipped_dims, n_seg, K, store, progress, loss_grads,
                      emit_on, coupled)
            result.stats["backward_seconds"] = time.perf_counter() - t0 - forward_seconds
            result.stats["checkpoint_bytes"] = store.nbytes
        return result, final
    finally:
        store.close()


def _backward(solver, stepper, loss, result, applied, clipped_dims, n_seg, K, store, progress, loss_grads,
              emit_on=None, coupled=None):
    model = solver.model
    if model.has_emitters:
        model.emitters.clear_grads()
    state = solver.state
    n_steps, sub, dt = len(applied), model.substeps, model.step_dt
    n_tools = model.n_tools
    grad_actions = np.zeros_like(applied)
    mask = tools.action_masks(model.tool_specs)

    def tick(phase, done, _):
        if progress:
            progress(phase, done, n_steps)

    if coupled is not None:
        coupled.begin_backward()
    carry = None
    for seg in reversed(range(n_seg)):
        steps = range(seg * K, min(n_steps, (seg + 1) * K))
        if seg != n_seg - 1:  # the last segment is still in the buffer from the forward pass
            state.write(0, store.get(seg))
            if coupled is not None:
                coupled.restore(seg)
            stepper.run_block(steps, applied[steps.start:steps.stop],
                              None if emit_on is None else emit_on[steps.start:steps.stop], tick, "recompute", seg)
        solver.clear_grads()
        if carry is not None:
            state.add_grad(len(steps) * sub, carry)
        # the loss gradients of the whole segment go in first (each into its own slot), a chunk per launch
        active = [g for g in steps if loss.active(g + 1, n_steps)]
        for i in reversed(range(0, len(active), stepper.per_chunk)):
            chunk = active[i:i + stepper.per_chunk]
            grads = {g: loss_grads.pop(g) for g in chunk if g in loss_grads}
            missing = [g for g in chunk if g not in grads]
            for g, step_state in (stepper.states(steps, missing, 0) if missing else ()):
                grads[g] = step_state.only_active(loss(step_state, n_steps, grad=True)[1])
            for g in reversed(chunk):
                for key, value in grads[g].items():
                    if not np.all(np.isfinite(value)):
                        raise NonFiniteGradientError(f"the loss gradient with respect to {key} is NaN or infinite "
                                                     f"at step {g + 1}")
            state.add_steps_grad([(g - steps.start + 1) * sub for g in chunk], [grads[g] for g in chunk])
        for j in reversed(range(len(steps))):
            g = steps[j]
            s0, s1 = j * sub, (j + 1) * sub
            if coupled is not None:  # the gas's step and drag came after the MPM substeps
                coupled.backward_step(g, s0, s1, applied[g])
            for i in reversed(range(sub)):
                solver.substep_grad(s0 + i)
            if n_tools and clipped_dims[g].any():
                # v = (b − p)/dt on clipped components: the gradient goes to p at the step's start, before the
                # backward goes on past it
                tg, bad = state.step_grad_end(s0, s1)
                if bad:
                    _raise_nonfinite(bad, g, dt)
                cl = clipped_dims[g]
                dp = np.where(cl, -tg[:, :3] / dt, 0.0)
                state.add_grad(s0, {"tool_position": dp})
                tg[:, :3] = np.where(cl, 0.0, tg[:, :3])
                grad_actions[g] = tg * mask
            if progress:
                progress("backward", n_steps - g, n_steps)
        # the other steps' twist gradients, and the NaN watch, once per segment: a NaN or infinity spreads back
        # to the segment's first slot, and the slots still hold every step's gradient to find where it began
        if n_tools:
            twist = state.twist_grads(len(steps), sub)
            for j, g in enumerate(steps):
                if not clipped_dims[g].any():
                    grad_actions[g] = twist[j] * mask
        if state.nonfinite(0, grad=True)[0] or not np.all(np.isfinite(grad_actions[steps.start:steps.stop])):
            for j in reversed(range(len(steps))):
                bad = state.nonfinite(j * sub, grad=True)[0]
                if bad or not np.all(np.isfinite(grad_actions[steps[j]])):
                    _raise_nonfinite(bad or ["tool twists"], steps[j], dt)
        carry = state.read(0, grad=True)
    start = store.get(0)
    result.grad_actions = grad_actions
    result.grad_velocities = carry.v.astype(np.float64)
    result.grad_positions = carry.x.astype(np.float64)
    if n_tools:
        result.grad_tool_position = carry.tool_position
        result.grad_tool_rotation = rotation_tangent_grad(carry.tool_rotation, start.tool_rotation)
    else:
        result.grad_tool_position = np.zeros((0, 3))
        result.grad_tool_rotation = np.zeros((0, 3))
    result.grad_emitter_position, result.grad_emitter_rotation = np.zeros((0, 3)), np.zeros((0, 3))
    if model.has_emitters:
        gp, gR = model.emitters.pose_grads()
        R0 = np.stack([s.rotation() for s in model.emitter_specs])
        result.grad_emitter_position = gp
        result.grad_emitter_rotation = rotation_tangent_grad(gR, R0)
    if coupled is not None:
        coupled.finish(result)


def _raise_nonfinite(fields, g: int, dt: float):
    raise NonFiniteGradientError(
        f"the gradient became NaN or infinite in {', '.join(fields)} at step {g} (t = {g * dt:.4g} s), going backward "
        f"from step {g + 1}. Common causes: an unstable step (more substeps), particles at a kink of the contact or "
        f"plasticity laws, or a NaN in the loss gradient")
