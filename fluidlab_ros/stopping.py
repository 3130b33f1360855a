"""Bringing the arm to rest from wherever the command stream is: the stop ramp.

Used on cancel, on ~/stop, on lost joint states and on a late control tick. From the last commanded velocity
v0 and the acceleration of the stream a0 = (v0 - v_prev) / T (T = 1 / control rate), Ruckig's velocity
interface computes the time-optimal jerk-limited profile to v = 0, a = 0 with the same acceleration and jerk
budgets the planner uses (pipeline.command_budgets: what the arm sees under the 1 ms hold model stays within
margin x its limits). The ramp is sampled at T; its last command is exactly zero. Joints decelerate
together (Ruckig synchronises them), so the tool stops close to its path.
"""
from __future__ import annotations

import numpy as np
from ruckig import ControlInterface, InputParameter, Result, Ruckig, Trajectory

from fluidlab_ros.pipeline import command_budgets


def stop_ramp(v0, v_prev, control_rate: float, limits, margin: float = 0.8) -> np.ndarray:
    """Velocity commands (K, dof), rad/s, one per control period, from the stream's state to rest."""
    v0 = np.asarray(v0, dtype=float)
    T = 1.0 / control_rate
    if not np.any(v0):
        return np.zeros((1, len(v0)))
    acc, jerk = command_budgets(limits, control_rate, margin, tolerate_lost_command=True)
    a0 = np.clip((v0 - np.asarray(v_prev, dtype=float)) / T, -acc, acc)
    dof = len(v0)
    otg, inp, traj = Ruckig(dof), InputParameter(dof), Trajectory(dof)
    inp.control_interface = ControlInterface.Velocity
    inp.current_position = [0.0] * dof
    inp.current_velocity = list(v0)
    inp.current_acceleration = list(a0)
    inp.target_velocity = [0.0] * dof
    inp.target_acceleration = [0.0] * dof
    inp.max_acceleration = list(acc)
    inp.max_jerk = list(jerk)
    inp.max_velocity = list(np.maximum(np.abs(v0), limits.velocity))
    res = otg.calculate(inp, traj)
    if res not in (Result.Working, Result.Finished):
        # cannot happen for a reachable rest state; fall back to a linear ramp at the acceleration budget
        n = int(np.ceil(np.max(np.abs(v0) / (acc * T)))) + 1
        return v0[None, :] * np.linspace(1, 0, n + 1)[1:, None]
    n = int(np.ceil(traj.duration / T - 1e-9))
    out = np.array([traj.at_time(min((k + 1) * T, traj.duration))[1] for k in range(n)])
    out = out.reshape(n, dof) if n else np.zeros((0, dof))
    return np.vstack([out, np.zeros((1, dof))])
