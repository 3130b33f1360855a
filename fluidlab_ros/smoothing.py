"""Jerk-limited smoothing with Ruckig at the control rate.

Ruckig runs as an online filter in its position interface: at every control tick it receives the reference
state (position, velocity, acceleration) of the next tick as its target, with `minimum_duration` set to one
control period. When the reference is reachable within the limits, the output equals the reference; when it
is not (a corner, a too-steep start), Ruckig follows a time-optimal jerk-limited profile that catches up, and
the deviation shows in the pipeline's tool-path error. Velocity bounds are updated every tick from the
position (the FR3's position-based limits). Ruckig's velocity interface is not used: it does not enforce
max_velocity or position limits. Targets outside the limits are clamped to them, and the verifier checks
everything afterwards.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from ruckig import InputParameter, OutputParameter, Result, Ruckig

from fluidlab_ros.errors import LimitError


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

    def run(self, q0, ref_pos, ref_vel, ref_acc, max_settle_ticks: int = 20000) -> Smoothed:
        """Follow the reference (K, dof) sampled at ticks 1..K starting at rest at q0; then come to rest at
        the final reference position."""
        otg, inp, out = Ruckig(self.dof, self.period), InputParameter(self.dof), OutputParameter(self.dof)
        inp.current_position, inp.current_velocity, inp.current_acceleration = list(q0), [0.0] * self.dof, \
            [0.0] * self.dof
        inp.max_acceleration, inp.max_jerk = list(self.acc), list(self.jerk)
        inp.minimum_duration = self.period
        k_ref = len(ref_pos)
        pos, vel, acc = [np.array(q0, dtype=float)], [np.zeros(self.dof)], [np.zeros(self.dof)]
        lagging, settle = [], 0
        k = 0
        while True:
            q = pos[-1]
            lo, hi = self.velocity_bounds(q)
            # A bound that excludes the current velocity (moving into a shrinking position-based limit) is
            # widened to it; Ruckig then brakes, and the verifier judges the result.
            lo, hi = np.minimum(lo, vel[-1]), np.maximum(hi, vel[-1])
            inp.max_velocity, inp.min_velocity = list(np.maximum(hi, 1e-9)), list(np.minimum(lo, -1e-9))
            if k < k_ref:
                target_v = np.clip(ref_vel[k], lo, hi)
                target_a = np.clip(ref_acc[k], -self.acc, self.acc)
                inp.target_position, inp.target_velocity, inp.target_acceleration = \
                    list(ref_pos[k]), list(target_v), list(target_a)
            else:
                inp.target_position = list(ref_pos[-1])
                inp.target_velocity, inp.target_acceleration = [0.0] * self.dof, [0.0] * self.dof
            res = otg.update(inp, out)
            if res not in (Result.Working, Result.Finished):
                raise LimitError(f"jerk-limited smoothing failed at tick {k} (t = {k * self.period:.3f} s): Ruckig "
                                 f"returned {res.name}", tick=k)
            if k < k_ref and out.trajectory.duration > self.period * (1 + 1e-9):
                lagging.append(k + 1)
            pos.append(np.array(out.new_position))
            vel.append(np.array(out.new_velocity))
            acc.append(np.array(out.new_acceleration))
            out.pass_to_input(inp)
            k += 1
            if k >= k_ref:
                if res == Result.Finished and np.all(np.abs(vel[-1]) < 1e-9) and np.all(np.abs(acc[-1]) < 1e-6):
                    break
                settle += 1
                if settle > max_settle_ticks:
                    raise LimitError("jerk-limited smoothing did not come to rest at the end of the trajectory")
        return Smoothed(np.array(pos), np.array(vel), np.array(acc), np.array(lagging, dtype=int), settle)
