"""Feasibility pass and time scaling of a joint-space path.

A segment is a joint path q(r) over trajectory time r in [0, R] (a cubic spline through the IK samples).
It is executed along a time map t -> r(t) that keeps the geometric path and changes only the timing:

    rate r'(t) = S(t / T_in) / s     ramp-in  (S(x) = 10x^3 - 15x^4 + 6x^5, the quintic smoothstep)
               = 1 / s               middle
               = S((T - t) / T_out) / s   ramp-out

so the joint velocity q'(r) r' starts and ends at zero even when the trajectory's first or last twist does
not (an abrupt start), and a uniform factor s >= 1 slows the whole segment down when joint speeds or
accelerations would exceed the planning limits. The scale is the smallest s with

    |q'(r)| / s          <= v_plan(q)           (per joint, directional, position-based for the FR3)
    |q''_W(r)| / s^2     <= PATH_SHARE a_plan   (q''_W: acceleration averaged over a window W)

The acceleration is averaged over `accel_window` because trajectories are piecewise-constant twists: the
instantaneous acceleration at a twist change is unbounded. Where the path's corners are sharper than the arm
can follow at that scale, the arm is given it filtered over up to the same window (followable_path), whose
acceleration is then that windowed acceleration, so the jerk-limited smoothing after this pass follows it
closely instead of cutting corners; the filter's and the smoothing's path deviation is measured and bounded
by the pipeline, and the rest of the budget is the smoothing's headroom. Inside a ramp the joint acceleration
is q'' r'^2 + q' r'' = S(x)^2 A + S'(x) V / (s T) with A and V the path's peak |q''_W| / s^2 and |q'| over the
ramp: T is the shortest ramp with that sum within a_plan for every x, and with the ramp's jerk term
q' r''' = S''(x) V / (s T^2) within half the jerk budget.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline

_S_PRIME_MAX = 1.875  # max of S'(x) = 30x^2 - 60x^3 + 30x^4
_S_SECOND_MAX = 5.7735026918962585  # max |S''(x)| = 10/sqrt(3)
PATH_SHARE = 0.8  # share of the acceleration budget the path may use at the scaled speed
_X = np.linspace(0.0, 1.0, 201)[1:-1]  # ramp phase grid


def _smooth(x):
    return x ** 3 * (10 - 15 * x + 6 * x ** 2)


def _smooth_d(x):
    return 30 * x ** 2 * (1 - x) ** 2


def _smooth_int(x):  # integral of S from 0 to x
    return x ** 4 * (2.5 - 3 * x + x ** 2)


@dataclass(frozen=True)
class TimeMap:
    """t (s, wall time from the segment start) -> trajectory time r (s)."""

    length: float  # R, trajectory-time length of the segment (s)
    scale: float  # s >= 1
    ramp_in: float  # T_in (s of wall time)
    ramp_out: float  # T_out

    @property
    def duration(self) -> float:
        middle = self.length - (self.ramp_in + self.ramp_out) / (2 * self.scale)
        return self.ramp_in + self.ramp_out + self.scale * middle

    def __call__(self, t):
        """(r, dr/dt, d2r/dt2) at wall times t (clamped to [0, duration])."""
        s, tin, tout, T = self.scale, self.ramp_in, self.ramp_out, self.duration
        t = np.clip(np.asarray(t, dtype=float), 0.0, T)
        r = np.empty_like(t)
        rd = np.full_like(t, 1.0 / s)
        rdd = np.zeros_like(t)
        if tin > 0:
            m = t < tin
            x = t[m] / tin
            r[m], rd[m], rdd[m] = tin * _smooth_int(x) / s, _smooth(x) / s, _smooth_d(x) / (s * tin)
        else:
            m = np.zeros_like(t, dtype=bool)
        r_in = tin / (2 * s)
        mid = ~m & (t <= T - tout)
        r[mid] = r_in + (t[mid] - tin) / s
        if tout > 0:
            e = t > T - tout
            x = (T - t[e]) / tout
            r[e], rd[e], rdd[e] = self.length - tout * _smooth_int(x) / s, _smooth(x) / s, -_smooth_d(x) / (s * tout)
        return r, rd, rdd


@dataclass(frozen=True)
class ScaleReport:
    scale: float
    velocity_ratio: float  # peak |q'| / v_plan at s = 1
    acceleration_ratio: float  # peak |q''_W| / a_plan at s = 1
    binding: str  # what set the scale, e.g. "velocity of joint 4", or "none"


def windowed_acceleration(qd: np.ndarray, dt: float, window: float) -> np.ndarray:
    """Acceleration (N, dof) from per-step velocities qd (N, dof): the difference of the mean velocity over
    the `window` seconds after and before each step boundary, divided by the window."""
    n = max(1, int(round(window / dt)))
    if len(qd) < 2:
        return np.zeros_like(qd)
    c = np.vstack([np.zeros((1, qd.shape[1])), np.cumsum(qd, axis=0)])
    idx = np.arange(1, len(qd))
    after = (c[np.minimum(idx + n, len(qd))] - c[idx]) / np.minimum(n, len(qd) - idx)[:, None]
    before = (c[idx] - c[np.maximum(idx - n, 0)]) / np.minimum(n, idx)[:, None]
    span = (np.minimum(n, len(qd) - idx) + np.minimum(n, idx))[:, None] * dt / 2
    return (after - before) / span


def box_filter(q: np.ndarray, m: int) -> np.ndarray:
    """The path q (N + 1, dof) averaged twice over a centred box of 2m + 1 samples (a copy; unchanged for
    m = 0). Each end is padded with its point reflection (2 q_0 - q_i), so the ends keep their positions
    and, on straight stretches, their velocities. Twice: the acceleration of the filtered path is the path's
    acceleration weighted by a triangle of half-width (2m + 1) samples (box * box), the weighting of
    windowed_acceleration's difference of mean velocities; velocities become box averages, so no peak
    speed grows."""
    out = np.array(q, dtype=float, copy=True)
    m = min(int(m), len(out) - 1)
    if m < 1:
        return out
    for _ in range(2):
        pad = np.vstack([2 * out[0] - out[m:0:-1], out, 2 * out[-1] - out[-2:-m - 2:-1]])
        c = np.vstack([np.zeros((1, out.shape[1])), np.cumsum(pad, axis=0)])
        out = (c[2 * m + 1:] - c[:-2 * m - 1]) / (2 * m + 1)
    out[0], out[-1] = q[0], q[-1]  # equal but for the running sum's rounding
    return out


def followable_path(q: np.ndarray, dt: float, scale: float, a_max: np.ndarray, j_max: np.ndarray,
                    window: float) -> tuple[np.ndarray, int, CubicSpline]:
    """The least filtered path (box_filter with m = 0, 1, ... up to round(window / (2 dt))) whose cubic
    spline, run `scale` times slower, keeps every joint within a_max (rad/s^2) and j_max (rad/s^3), so a
    jerk-limited follower can track it without lagging. Returns (path, m, spline), the spline q(r) of the path
    over trajectory time r = k dt (the pipeline follows it); m is the largest one when none fits: its
    acceleration is then the windowed acceleration over `window`, which choose_time_map bounds.

    Why: the IK samples of piecewise-constant twists have a corner at every step. A follower that cannot
    reach its reference within a period cuts across, and where it comes back to the path depends chaotically
    on the path (2.3-15.7 mm tool-path error for one trajectory planned from nearby stopping points; with this
    path 0.71-0.72 mm from 116 of them). Smooth paths (a circle) are left as they are: the filter
    would cut them (a 5 cm circle at 0.5 s per turn, filtered over the full window, left its path by 1.8 mm)."""
    r = np.arange(len(q)) * dt
    if len(q) < 3:  # no corner to filter
        path = box_filter(q, 0)
        return path, 0, CubicSpline(r, path, axis=0, bc_type="not-a-knot")
    m_max = int(round(window / (2 * dt)))
    for m in range(m_max + 1):
        path = box_filter(q, m)
        spline = CubicSpline(r, path, axis=0, bc_type="not-a-knot")
        acc = np.abs(spline(r, 2)).max(axis=0) / scale ** 2
        jerk = np.abs(spline(r[:-1] + dt / 2, 3)).max(axis=0) / scale ** 3
        if np.all(acc <= a_max) and np.all(jerk <= j_max):
            return path, m, spline
    return path, m_max, spline


def choose_time_map(q: np.ndarray, dt: float, velocity_bounds, a_plan: np.ndarray, j_plan: np.ndarray,
                    accel_window: float, max_scale: float, ramp_in: bool = True, ramp_out: bool = True):
    """Time map for the IK samples q (N + 1, dof) spaced dt in trajectory time. `velocity_bounds(q)` gives
    the planning velocity bounds (lo, hi) at positions q; a_plan and j_plan are the acceleration and jerk
    budgets of the smoothing stage. Returns (TimeMap, ScaleReport); the report's scale
    may exceed max_scale (the caller refuses then)."""
    qd = np.diff(q, axis=0) / dt  # per-step joint velocity in trajectory time (rad/s at s = 1)
    mid = 0.5 * (q[1:] + q[:-1])
    lo, hi = velocity_bounds(mid)
    with np.errstate(divide="ignore", invalid="ignore"):
        vr = np.where(qd > 0, qd / hi, np.where(qd < 0, qd / lo, 0.0))
    vr = np.where(np.isfinite(vr), vr, np.inf)  # moving against a zero bound: not executable at any speed
    acc = windowed_acceleration(qd, dt, accel_window)
    ar = np.abs(acc) / (PATH_SHARE * a_plan) if len(acc) else np.zeros((1, q.shape[1]))
    v_ratio, a_ratio = float(vr.max(initial=0.0)), float(ar.max(initial=0.0))
    s = max(1.0, v_ratio, np.sqrt(a_ratio))
    binding = "none"
    if s > 1.0:
        if v_ratio >= np.sqrt(a_ratio):
            binding = f"velocity of joint {int(np.unravel_index(np.argmax(vr), vr.shape)[1]) + 1}"
        else:
            binding = f"acceleration of joint {int(np.unravel_index(np.argmax(ar), ar.shape)[1]) + 1}"
    length = (len(q) - 1) * dt
    if not np.isfinite(s):
        return TimeMap(length, s, 0.0, 0.0), ScaleReport(s, v_ratio, a_ratio, binding)
    while True:
        tin = _ramp(qd, acc, dt, s, a_plan, j_plan, start=True) if ramp_in else 0.0
        tout = _ramp(qd, acc, dt, s, a_plan, j_plan, start=False) if ramp_out else 0.0
        if (tin + tout) / (2 * s) <= length or s > max_scale:
            break
        s *= 1.25  # ramps longer than the segment: slow down, which shortens them in trajectory time
    return TimeMap(length, s, tin, tout), ScaleReport(s, v_ratio, a_ratio, binding)


def _ramp(qd, acc, dt, s, a_plan, j_plan, start: bool) -> float:
    """Ramp duration T (s) such that S(x)^2 A + S'(x) V / (s T) <= a_plan and S''(x) V / (s T^2) <= j_plan / 2
    for every phase x, with V = max |q'| and A = max |q''_W| / s^2 over the part of the path the ramp covers
    (found by a few fixed-point passes, since that part depends on T)."""
    sx, sdx = _smooth(_X), _smooth_d(_X)
    t_ramp = 0.0
    for _ in range(4):
        n = max(1, int(np.ceil(t_ramp / (2 * s) / dt)) + 1)
        v = np.abs(qd[:n] if start else qd[-n:]).max(axis=0)
        a = np.abs(acc[:n] if start else acc[-n:]).max(axis=0) / s ** 2 if len(acc) else np.zeros_like(v)
        # largest B = V / (s T) with S^2 A + S' B <= a_plan at every phase, per joint
        room = np.min((a_plan[None, :] - sx[:, None] ** 2 * a[None, :]) / sdx[:, None], axis=0)
        room = np.maximum(room, 1e-3 * a_plan)  # the path alone uses the budget: make the ramp long
        t_acc = np.max(v / (s * room))
        t_jerk = np.max(np.sqrt(2 * _S_SECOND_MAX * v / (s * j_plan)))
        t_new = float(max(t_acc, t_jerk))
        if t_new <= t_ramp * 1.0001:
            break
        t_ramp = t_new
    return t_ramp
