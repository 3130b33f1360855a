"""Jerk-limited smoothing with Ruckig at the control rate.

Ruckig runs as an online filter in its position interface. At every control tick k (time t_k) it computes a
time-optimal jerk-limited trajectory from the current state to the reference state (position, velocity,
acceleration) at t_k + T, with `minimum_duration` T (one control period), and the state after one period
becomes the next sample. When the reference is reachable within the limits, the output equals the reference.
When it is not (a corner, a too-steep start), the trajectory takes longer, D > T: the target is then moved
to the reference state at t_k + D, the time the arm can get there, and recomputed (a few fixed-point passes),
so the filter intercepts the moving reference instead of trailing it at a constant lag; the remaining
deviation shows in the pipeline's tool-path error.

Velocity bounds are updated every tick from the position (the FR3's position-based limits). Ruckig's
velocity interface is not used: it does not enforce max_velocity or position limits. Targets outside the
limits are clamped to them, and the verifier checks everything afterwards.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from ruckig import InputParameter, Result, Ruckig, RuckigError, Trajectory

from fluidlab_ros.errors import LimitError

INTERCEPT_PASSES = 4


@dataclass
class Smoothed:
    position: np.ndarray  # (K + 1, dof) at ticks 0..K, rad
    velocity: np.ndarray  # (K + 1, dof), rad/s
    acceleration: np.ndarray  # (K + 1, dof), rad/s^2
    lagging_ticks: np.ndarray  # indices of ticks where the reference could not be reached within one period
    settle_ticks: int  # ticks appended after the reference ended, to come to rest


class JerkLimitedFollower:
    def __init__(self, dof: int, period: float, acceleration: np.ndarray, jerk: np.ndarray, velocity_bounds):
        """`velocity_bounds(q)` -> (lo, hi) rad/s at position q; acceleration and jerk are symmetric limits."""
        self.dof, self.period = dof, period
        self.acc, self.jerk, self.velocity_bounds = np.asarray(acceleration), np.asarray(jerk), velocity_bounds

    def run(self, q0, reference, duration: float, at_ticks=None, max_settle_ticks: int = 20000) -> Smoothed:
        """Follow `reference(t) -> (position, velocity, acceleration)` (arrays of shape (dof,), t in s) for
        t in [0, duration], starting at rest at q0, then come to rest at reference(duration). `at_ticks`
        optionally holds the reference at the ticks t = T, 2T, ... (three arrays (K, dof)), precomputed in
        one vectorised call; `reference` is then only called to intercept."""
        T = self.period
        otg, inp, traj = Ruckig(self.dof), InputParameter(self.dof), Trajectory(self.dof)
        inp.current_position, inp.current_velocity, inp.current_acceleration = list(q0), [0.0] * self.dof, \
            [0.0] * self.dof
        inp.max_acceleration, inp.max_jerk = list(self.acc), list(self.jerk)
        inp.minimum_duration = T
        n_ref = int(np.ceil(duration / T - 1e-9))
        final = reference(duration)
        pos, vel, acc = [np.array(q0, dtype=float)], [np.zeros(self.dof)], [np.zeros(self.dof)]
        lagging, settle, k = [], 0, 0
        while True:
            q, v = pos[-1], vel[-1]
            lo, hi = self.velocity_bounds(q)
            # A bound that excludes the current velocity (moving into a shrinking position-based limit) is
            # widened to it; Ruckig then brakes, and the verifier judges the result.
            lo, hi = np.minimum(lo, v), np.maximum(hi, v)
            inp.max_velocity, inp.min_velocity = list(np.maximum(hi, 1e-9)), list(np.minimum(lo, -1e-9))
            t_target = (k + 1) * T
            following = k < n_ref
            for attempt in range(INTERCEPT_PASSES if following else 1):
                if not following:
                    p_ref, v_ref, a_ref = final
                elif attempt == 0 and at_ticks is not None:
                    p_ref, v_ref, a_ref = at_ticks[0][k], at_ticks[1][k], at_ticks[2][k]
                else:
                    p_ref, v_ref, a_ref = reference(min(t_target, duration))
                inp.target_position = list(p_ref)
                inp.target_velocity = list(np.clip(v_ref, lo, hi))
                inp.target_acceleration = list(np.clip(a_ref, -self.acc, self.acc))
                try:
                    res = otg.calculate(inp, traj)
                except RuckigError as err:  # e.g. a velocity bound it can no longer keep at this jerk
                    raise LimitError(f"jerk-limited smoothing failed at tick {k} (t = {k * T:.3f} s): "
                                     f"{str(err).strip()}", tick=k) from None
                if res not in (Result.Working, Result.Finished):
                    raise LimitError(f"jerk-limited smoothing failed at tick {k} (t = {k * T:.3f} s): Ruckig "
                                     f"returned {res.name}", tick=k)
                if traj.duration <= T * (1 + 1e-9) or t_target >= duration:
                    break
                t_target = k * T + traj.duration  # intercept: aim where the reference will be on arrival
            if following and traj.duration > T * (1 + 1e-9):
                lagging.append(k + 1)
            p, v, a = traj.at_time(T)[:3]
            pos.append(np.array(p))
            vel.append(np.array(v))
            acc.append(np.array(a))
            inp.current_position, inp.current_velocity, inp.current_acceleration = p, v, a
            k += 1
            if k >= n_ref:
                if np.all(np.abs(vel[-1]) < 1e-9) and np.all(np.abs(acc[-1]) < 1e-6) \
                        and np.allclose(pos[-1], final[0], atol=1e-9, rtol=0):
                    break
                settle += 1
                if settle > max_settle_ticks:
                    raise LimitError("jerk-limited smoothing did not come to rest at the end of the trajectory")
        return Smoothed(np.array(pos), np.array(vel), np.array(acc), np.array(lagging, dtype=int), settle)
