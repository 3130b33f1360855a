"""Trajectory parametrisations: linear maps from a parameter vector θ to the (N, k) action sequence of a task,
so that a gradient with respect to the actions maps back by the transpose.

    actions = reshape(A θ_a, (N, k)),   dL/dθ_a = Aᵀ vec(dL/d actions)

- open loop: θ_a is the action sequence itself (A = I).
- periodic (the paper's Gathering policies; Mixing's too in the paper, open loop here: tasks/cup_tasks.py):
  θ_a is a stroke of S steps; each period is the stroke followed by R steps at the constant velocity
  −(Σ stroke)/R that returns the tool to where the stroke started, repeated until the horizon (the last period
  is cut short).
- knots (CMA-ES): θ_a holds K values per axis; actions are their piecewise-linear interpolation over the
  horizon (or over the stroke of a periodic policy), which keeps the search low-dimensional.

Every parametrisation also carries the initial tool position's offset in the action plane (k values, metres),
bounded by the task's workspace. Action parameters are bounded by ±max_tool_speed; all the maps above keep
actions within that bound when θ is (the return velocity is a mean of stroke velocities when R ≥ S).
"""
from __future__ import annotations

import numpy as np

KNOTS = 8  # knots per axis of the knots parametrisation (CMA-ES's search, and DP's over free knots)


class Parametrisation:
    """θ = [action parameters (n_a), initial tool position offset (k)]."""

    def __init__(self, task, matrix: np.ndarray, name: str):
        self.task = task
        self.matrix = np.asarray(matrix, dtype=np.float64)  # (N·k, n_a)
        self.name = name
        self.k = task.n_actions
        self.n_action_params = self.matrix.shape[1]
        lo, hi = task.workspace()
        start = task.initial_tool_pose()[:3]
        axes = [i for i in task.action_axes if i < 3]
        self._axes = axes
        self.pose_lower = (lo - start)[axes]
        self.pose_upper = (hi - start)[axes]

    @property
    def size(self) -> int:
        return self.n_action_params + len(self._axes)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        v = self.task.max_tool_speed
        lo = np.concatenate([np.full(self.n_action_params, -v), self.pose_lower])
        hi = np.concatenate([np.full(self.n_action_params, v), self.pose_upper])
        return lo, hi

    def clip(self, theta):
        lo, hi = self.bounds()
        return np.clip(theta, lo, hi)

    def actions(self, theta) -> np.ndarray:
        """(N, k) actions of θ."""
        return (self.matrix @ theta[: self.n_action_params]).reshape(self.task.horizon, self.k)

    def tool_position(self, theta) -> np.ndarray:
        """Initial tool origin (3,) of θ (m)."""
        pos = self.task.initial_tool_pose()[:3].copy()
        pos[self._axes] += theta[self.n_action_params:]
        return pos

    def fit(self, actions) -> np.ndarray:
        """The action parameters whose actions are nearest (least squares) to (N, k) `actions`."""
        return np.linalg.lstsq(self.matrix, np.asarray(actions, dtype=np.float64).reshape(-1), rcond=None)[0]

    def gradient(self, grad_actions, grad_tool_position) -> np.ndarray:
        """dL/dθ from dL/d actions (N, k) and dL/d initial tool position (3,)."""
        ga = self.matrix.T @ np.asarray(grad_actions, dtype=np.float64).reshape(-1)
        return np.concatenate([ga, np.asarray(grad_tool_position, dtype=np.float64)[self._axes]])


def open_loop(task) -> Parametrisation:
    return Parametrisation(task, np.eye(task.horizon * task.n_actions), "open-loop")


def _periodic_matrix(horizon: int, stroke: int, reset: int) -> np.ndarray:
    """(N, S): row t gives action t as a combination of stroke velocities (one axis)."""
    period = stroke + reset
    m = np.zeros((horizon, stroke))
    for t in range(horizon):
        phase = t % period
        if phase < stroke:
            m[t, phase] = 1.0
        else:
            m[t, :] = -1.0 / reset
    return m


def _knot_matrix(length: int, knots: int) -> np.ndarray:
    """(length, K) piecewise-linear interpolation of K knots spread evenly over `length` steps."""
    if knots < 2:
        return np.ones((length, 1))
    t = np.linspace(0.0, knots - 1, length)
    m = np.zeros((length, knots))
    i = np.minimum(np.floor(t).astype(int), knots - 2)
    f = t - i
    m[np.arange(length), i] = 1.0 - f
    m[np.arange(length), i + 1] = f
    return m


def _per_axis(m_axis: np.ndarray, k: int) -> np.ndarray:
    """Apply a per-axis (N, P) map to k interleaved axes: θ laid out (P, k), actions (N, k)."""
    return np.kron(m_axis, np.eye(k))


def periodic(task) -> Parametrisation:
    stroke, reset = task.periodic
    if reset < stroke:
        raise ValueError(f"{task.name}: the return motion ({reset} steps) must not be shorter than the stroke "
                         f"({stroke} steps), or it would need speeds beyond the stroke's")
    return Parametrisation(task, _per_axis(_periodic_matrix(task.horizon, stroke, reset), task.n_actions),
                           f"periodic (stroke {stroke} + return {reset} steps)")


def knots(task, n_knots: int = KNOTS, free: bool = False) -> Parametrisation:
    """Low-dimensional: n_knots per axis over the horizon, or over the stroke of a periodic task (`free`: over the
    whole horizon all the same, so that the tool may end anywhere)."""
    if task.periodic and not free:
        stroke, reset = task.periodic
        m = _periodic_matrix(task.horizon, stroke, reset) @ _knot_matrix(stroke, min(n_knots, stroke))
        name = f"periodic, {min(n_knots, stroke)} knots per axis over the stroke"
    else:
        m = _knot_matrix(task.horizon, n_knots)
        name = f"{n_knots} knots per axis, piecewise linear"
    return Parametrisation(task, _per_axis(m, task.n_actions), name)


def default(task) -> Parametrisation:
    """The parametrisation gradient methods use: periodic where the paper uses it, knots where the task asks
    for a smooth motion (`Task.action_knots`: a tool that an arm turns fast, whose joint accelerations an
    open-loop sequence with per-step noise would break), open loop otherwise."""
    if task.periodic:
        return periodic(task)
    if task.action_knots:
        return knots(task, task.action_knots)
    return open_loop(task)
