"""Checkpointed rollouts: the loss of N steps and its gradient in memory that does not grow with N.

The N steps are split into segments of K steps, by default as long as the solver's slot buffer allows
(plan_segments).
The forward pass keeps only each segment's start state (in host memory, or on disk), running each segment
through the buffer. The backward pass goes through the segments last to first: it restores the start
state, re-runs the segment's forward to fill the buffer, seeds the gradient of the segment's last slot with
the one handed over from the next segment, and runs the substeps' gradients back to the first slot, whose
gradient it hands to the previous segment. Device memory is the buffer (K steps); host memory is N/K states.

Workspace clipping (tools.ToolState.clip) is differentiated exactly: a linear-velocity component clipped at
the workspace boundary b becomes v = (b − p)/dt, so its gradient goes to the tool position p at the step's
start and none goes to the action.
"""
from __future__ import annotations

import os
import shutil
import tempfile
import time
from dataclasses import dataclass, field

import numpy as np

from fluidlab_core.engine.tools import clip_twists
from fluidlab_core.losses import StepState


LOSS_GRAD_CACHE_BYTES = 256e6  # host memory for loss gradients kept from the forward pass (see rollout_with_grad)
LOSS_READ_BYTES = 16e6  # states read back per launch for the loss (read_steps), and gradients added per launch


class NonFiniteGradientError(FloatingPointError):
    """A gradient became NaN or infinite during the backward pass."""


@dataclass
class RolloutResult:
    """Loss of a rollout and, when requested, its gradients (float64 numpy arrays, SI units).

    grad_actions: (N, n_tools, 6) dL/d(vx, vy, vz, wx, wy, wz) per step (zero where the action mask or the
    workspace clipping leaves an action no effect); grad_tool_position: (n_tools, 3) dL/dp of the initial
    tool origins; grad_tool_rotation: (n_tools, 3) dL/dθ for an initial rotation R₀ ← exp([θ]×) R₀ (world
    frame); grad_velocities / grad_positions: (n_particles, 3) dL/dv⁰, dL/dx⁰ of the initial particle state."""

    loss: float
    step_losses: np.ndarray  # (N,) loss contributed after each step
    clipped: np.ndarray  # (N, n_tools) workspace clipping per step
    grad_actions: np.ndarray | None = None
    grad_tool_position: np.ndarray | None = None
    grad_tool_rotation: np.ndarray | None = None
    grad_velocities: np.ndarray | None = None
    grad_positions: np.ndarray | None = None
    stats: dict = field(default_factory=dict)  # segments, segment_steps, checkpoint bytes, seconds


class CheckpointStore:
    """Segment start states, in host memory or (with `directory`) as .npz files in a private folder."""

    def __init__(self, directory=None):
        self.memory: dict[int, dict] = {}
        self.directory = None
        self.nbytes = 0
        if directory is not None:
            os.makedirs(directory, exist_ok=True)
            self.directory = tempfile.mkdtemp(prefix="checkpoints-", dir=directory)

    def put(self, k: int, state: dict):
        self.nbytes += sum(np.asarray(a).nbytes for a in state.values())
        if self.directory is None:
            self.memory[k] = state
        else:
            np.savez(os.path.join(self.directory, f"{k}.npz"), **state)

    def get(self, k: int) -> dict:
        if self.directory is None:
            return self.memory[k]
        with np.load(os.path.join(self.directory, f"{k}.npz")) as data:
            return {key: data[key] for key in data.files}

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


def rollout_with_grad(sim, diff, velocities: np.ndarray, loss, grad: bool = True, segment_steps=None,
                      checkpoint_dir=None, progress=None) -> RolloutResult:
    """Run len(velocities) steps from the simulator's state on the differentiable solver (see module docstring).

    velocities: (N, n_tools, 6) masked tool twists. progress(phase, done, total) is called once per step
    with phase "forward", "recompute" or "backward"."""
    n_steps = len(velocities)
    sub = sim.substeps
    dt = sim.dt
    capacity = (diff.n_slots - 1) // sub
    K = plan_segments(n_steps, capacity, segment_steps)
    n_seg = -(-n_steps // K)
    store = CheckpointStore(checkpoint_dir)
    step_losses = np.zeros(n_steps)
    t0 = time.perf_counter()
    start = sim.get_state()
    applied, clipped_dims = _clip_all(sim, start, velocities)

    def seg_steps(seg):
        return range(seg * K, min(n_steps, (seg + 1) * K))

    # the loss reads the states of a segment's steps once the segment has run, a chunk of steps per launch
    per_chunk = max(1, int(LOSS_READ_BYTES // max(1, 2 * diff.n_particles * 3 * np.dtype(diff.np_real).itemsize)))

    def loss_chunks(steps):
        """The segment's steps where the loss is active, in chunks of at most per_chunk steps."""
        active = [g for g in steps if loss.active(g + 1, n_steps)]
        return [active[i:i + per_chunk] for i in range(0, len(active), per_chunk)]

    def states_at(steps, chunk):
        """StepState after each step g of chunk (global step numbers within `steps`, the buffered segment), one
        at a time (each in float64 only while the loss looks at it)."""
        x, v, tp, tR = diff.read_steps([(g - steps.start + 1) * sub for g in chunk])
        f64 = np.float64
        for j, g in enumerate(chunk):
            yield StepState(g + 1, (g + 1) * dt, x[j].astype(f64), v[j].astype(f64), tp[j].astype(f64),
                            tR[j].astype(f64))

    # the loss gradients of the last segment's steps, taken when its forward reads the state for the loss value,
    # so that its backward need not read the state again (as long as they fit LOSS_GRAD_CACHE_BYTES)
    loss_grads = {}

    def run_segment(seg, first_pass, phase):
        steps = seg_steps(seg)
        diff.write_twists(applied[steps.start:steps.stop], sub)
        # what the backward reads is kept only where the backward follows before the buffer is run again
        substep = diff.substep if grad and (not first_pass or seg == n_seg - 1) else diff.substep_no_store
        for j, g in enumerate(steps):
            for i in range(sub):
                substep(j * sub + i)
            if progress:
                progress(phase, g + 1, n_steps)
        if not first_pass:
            return
        cache_bytes = 0
        for chunk in loss_chunks(steps):
            for state in states_at(steps, chunk):
                g = state.step - 1
                keep = grad and seg == n_seg - 1 and cache_bytes < LOSS_GRAD_CACHE_BYTES
                step_losses[g], grads = loss(state, n_steps, grad=keep)
                if keep:
                    loss_grads[g] = grads
                    cache_bytes += sum(a.nbytes for a in grads.values())

    try:
        diff.write_state(0, start)
        for seg in range(n_seg):
            if seg > 0:
                diff.copy_slot(K * sub, 0)
            if grad:
                store.put(seg, diff.read_state(0))
            run_segment(seg, True, "forward")
        final_slot = len(seg_steps(n_seg - 1)) * sub
        final = diff.read_state(final_slot)
        bad = _nonfinite_state(final)
        if bad:
            raise NonFiniteGradientError(f"the rollout's state became NaN or infinite ({bad}) before step {n_steps}; "
                                         f"use more substeps or slower actions")
        forward_seconds = time.perf_counter() - t0
        result = RolloutResult(float(step_losses.sum()), step_losses, clipped_dims.any(axis=2))
        result.stats = {"segments": n_seg, "segment_steps": K, "buffer_steps": capacity,
                        "forward_seconds": forward_seconds}
        if grad:
            _backward(sim, diff, loss, result, applied, clipped_dims, seg_steps, n_seg, K, store, loss_chunks,
                      states_at, run_segment, progress, loss_grads)
            result.stats["backward_seconds"] = time.perf_counter() - t0 - forward_seconds
            result.stats["checkpoint_bytes"] = store.nbytes
        final["step"] = sim.step_count + n_steps
        sim.set_state(final)
        return result
    finally:
        store.close()


def _backward(sim, diff, loss, result, applied, clipped_dims, seg_steps, n_seg, K, store, loss_chunks, states_at,
              run_segment, progress, loss_grads):
    n_steps, sub, dt = len(applied), sim.substeps, sim.dt
    n_tools = len(sim.tools.specs)
    grad_actions = np.zeros_like(applied)
    mask = np.array([spec.action_mask for spec in sim.tools.specs], dtype=np.float64).reshape(n_tools, 6)
    carry = None
    for seg in reversed(range(n_seg)):
        if seg != n_seg - 1:  # the last segment is still in the buffer from the forward pass
            diff.write_state(0, store.get(seg))
            run_segment(seg, False, "recompute")
        diff.clear_grads()
        steps = seg_steps(seg)
        if carry is not None:
            diff.add_state_grad(len(steps) * sub, carry)
        # the loss gradients of the whole segment go in first (each into its own slot), a chunk per launch
        for chunk in reversed(loss_chunks(steps)):
            grads = {g: loss_grads.pop(g) for g in chunk if g in loss_grads}
            missing = [g for g in chunk if g not in grads]
            for state in (states_at(steps, missing) if missing else ()):
                grads[state.step - 1] = loss(state, n_steps, grad=True)[1]
            for g in reversed(chunk):
                for key, value in grads[g].items():
                    if not np.all(np.isfinite(value)):
                        raise NonFiniteGradientError(f"the loss gradient with respect to {key} is NaN or infinite "
                                                     f"at step {g + 1}")
            diff.add_steps_grad([(g - steps.start + 1) * sub for g in chunk], [grads[g] for g in chunk])
        for j in reversed(range(len(steps))):
            g = steps[j]
            s0, s1 = j * sub, (j + 1) * sub
            for i in reversed(range(sub)):
                diff.substep_grad(s0 + i)
            if n_tools and clipped_dims[g].any():
                # v = (b − p)/dt on clipped components: the gradient goes to p at the step's start, before the
                # backward goes on past it
                tg, bad = diff.step_grad_end(s0, s1)
                if bad:
                    _raise_nonfinite(bad, g, dt)
                cl = clipped_dims[g]
                dp = np.where(cl, -tg[:, :3] / dt, 0.0)
                diff.add_state_grad(s0, {"tool_position": dp})
                tg[:, :3] = np.where(cl, 0.0, tg[:, :3])
                grad_actions[g] = tg * mask
            if progress:
                progress("backward", n_steps - g, n_steps)
        # the other steps' twist gradients, and the NaN watch, once per segment: a NaN or infinity spreads back
        # to the segment's first slot, and the slots still hold every step's gradient to find where it began
        if n_tools:
            twist = diff.twist_grads(len(steps), sub)
            for j, g in enumerate(steps):
                if not clipped_dims[g].any():
                    grad_actions[g] = twist[j] * mask
        if diff.nonfinite_grad_fields(0) or not np.all(np.isfinite(grad_actions[steps.start:steps.stop])):
            for j in reversed(range(len(steps))):
                bad = diff.nonfinite_grad_fields(j * sub)
                if bad or not np.all(np.isfinite(grad_actions[steps[j]])):
                    _raise_nonfinite(bad or ["tool twists"], steps[j], dt)
        carry = diff.read_state(0, grad=True)
    start = store.get(0)
    result.grad_actions = grad_actions
    result.grad_velocities = carry["v"].astype(np.float64)
    result.grad_positions = carry["x"].astype(np.float64)
    if n_tools:
        result.grad_tool_position = carry["tool_position"]
        result.grad_tool_rotation = rotation_tangent_grad(carry["tool_rotation"], start["tool_rotation"])
    else:
        result.grad_tool_position = np.zeros((0, 3))
        result.grad_tool_rotation = np.zeros((0, 3))


def _raise_nonfinite(fields, g: int, dt: float):
    raise NonFiniteGradientError(
        f"the gradient became NaN or infinite in {', '.join(fields)} at step {g} (t = {g * dt:.4g} s), going backward "
        f"from step {g + 1}. Common causes: an unstable step (more substeps), particles at a kink of the contact or "
        f"plasticity laws, or a NaN in the loss gradient")


def _clip_all(sim, start: dict, velocities: np.ndarray):
    """Workspace clipping of every step, up front: tool origins depend on the twists alone, so they advance on
    the host in float64 as in `Simulator.step` (ToolState), substep by substep."""
    specs, dt, sub = sim.tools.specs, sim.dt, sim.substeps
    applied = np.zeros_like(velocities)
    clipped_dims = np.zeros((len(velocities), len(specs), 3), dtype=bool)
    if not specs:
        return applied, clipped_dims
    position = np.array(start["tool_position"], dtype=np.float64)
    for g in range(len(velocities)):
        applied[g], clipped_dims[g] = clip_twists(specs, position, velocities[g], dt)
        for _ in range(sub):
            position += applied[g, :, :3] * (dt / sub)
    return applied, clipped_dims


def _nonfinite_state(state: dict) -> str:
    names = [key for key in ("x", "v", "C", "F") if not np.all(np.isfinite(state[key]))]
    return ", ".join(names)
