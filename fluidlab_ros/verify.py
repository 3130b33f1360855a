"""Check a joint velocity command stream the way the arm will see it, before anything is sent.

Hold model: a JointGroupVelocityController on franka_ros2 holds the last command for each 1 ms tick of the
arm's control loop, so a stream at `rate` Hz reaches the arm as each command repeated n = 1000 / rate times.
libfranka then checks the commanded signal by finite differences at 1 ms:

    q_j   = q_0 + tau * sum_{i<j} v_i                              (integrated command, position limits)
    v_j                                                            (velocity, position-based for the FR3)
    a_j   = (v_j - v_{j-1}) / tau,   jerk_j = (a_j - a_{j-1}) / tau   (tau = 1 ms)

with the arm at rest before the first command and after the last one. At 500 Hz a smooth acceleration a
arrives as steps 2a tau every other tick, i.e. a finite-difference jerk of 2a / tau: the planner keeps a small
enough for that; this module only measures. Every quantity must stay within `margin` x its official limit
(position: `position_margin` rad inside the range). The report gives, for each quantity and joint, the peak
fraction of the official limit, and the jerk and acceleration that one lost command would cause
(the arm then jumps two commands' change in one tick; a command that is only 1 ms late is harmless). Cartesian flange speeds are checked against the
Cartesian velocity limits; Cartesian accelerations and jerks are reported only (libfranka's joint velocity
interface checks joint-space limits).

Given a `dynamics` model (fluidlab_ros/dynamics.py) the joint torques tau = M(q) qdd + C(q, qd) qd + g(q) and
their rate along the stream must also stay within margin x Franka's tau_max and dtau_max; given a `collision`
model (fluidlab_ros/collision.py) the arm's links must keep the clearance from the table, the task's container
and each other at every command tick (refined to 2 mm of motion). The torques are those of the smooth profile
(`smooth`: q, qd, qdd at the command ticks, from the jerk-limited stage), or, without it, of central
differences of the integrated positions at the command ticks. pipeline.plan always passes both models.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from fluidlab_ros.limits import JointLimits


@dataclass
class Verification:
    ok: bool
    violations: list[str]
    peak: dict = field(default_factory=dict)  # quantity -> (dof,) or scalar fraction of the official limit
    positions: np.ndarray | None = None  # (J + 1, dof) arm positions every 1 ms under the hold model
    flange_positions: np.ndarray | None = None  # (J + 1, 3)
    flange_rotations: np.ndarray | None = None  # (J + 1, 3, 3)
    torque_violations: list[str] = field(default_factory=list)  # also in `violations`
    collision_violations: list[str] = field(default_factory=list)  # also in `violations`
    torque: object = None  # dynamics.TorqueCheck, if a dynamics model was given
    collision: object = None  # collision.CollisionCheck, if a collision model was given
    check_times: dict = field(default_factory=dict)  # s of wall time: torque, collision

    def summary(self) -> dict:
        return {k: float(np.max(v)) for k, v in self.peak.items()}


def ticks_per_command(rate: float, check_period: float = 1e-3) -> int:
    n = (1.0 / rate) / check_period
    if rate <= 0 or abs(n - round(n)) > 1e-9 or round(n) < 1:
        raise ValueError(f"control rate {rate} Hz must divide the arm's {1 / check_period:.0f} Hz loop "
                         f"(1000, 500, 250, 200, 125, 100 Hz, ...)")
    return int(round(n))


def hold(commands: np.ndarray, rate: float, check_period: float = 1e-3) -> np.ndarray:
    """Per-tick velocities (K n, dof) that the arm receives from commands (K, dof) streamed at `rate`."""
    return np.repeat(np.asarray(commands, dtype=float), ticks_per_command(rate, check_period), axis=0)


def _first(mask: np.ndarray):
    idx = np.argwhere(mask)
    return (int(idx[0][0]), int(idx[0][1])) if len(idx) else None


def verify(commands: np.ndarray, q0, rate: float, limits: JointLimits, margin: float = 0.8,
           position_margin: float = 0.03, tolerate_lost_command: bool = False, robot=None, dynamics=None,
           collision=None, smooth=None) -> Verification:
    """Check commands (K, dof) in rad/s, streamed at `rate` Hz from rest at q0. `robot` (fluidlab_ros.robot.Robot)
    enables the Cartesian checks, `dynamics` (dynamics.DynamicModel) the torque and torque-rate checks, `collision`
    (collision.CollisionModel) the clearance checks. `smooth`: (q, qd, qdd), each (N, dof), the smooth
    profile at the command ticks t_k = k / rate, k = 0..N-1, whose torques are checked (default: central
    differences of the integrated positions at the command ticks)."""
    tau = limits.check_period
    commands = np.asarray(commands, dtype=float)
    violations: list[str] = []
    if commands.ndim != 2 or commands.shape[1] != limits.dof:
        return Verification(False, [f"commands must have shape (K, {limits.dof}), got {commands.shape}"])
    bad = _first(~np.isfinite(commands))
    if bad is not None:
        return Verification(False, [f"command {bad[0]} holds NaN or infinity (joint {bad[1] + 1})"])
    v = hold(commands, rate, tau)
    rest = np.zeros((2, limits.dof))
    v_ext = np.vstack([rest, v, rest])  # at rest before and after the stream
    q = np.asarray(q0, dtype=float) + tau * np.vstack([np.zeros((1, limits.dof)), np.cumsum(v, axis=0)])
    acc = np.diff(v_ext, axis=0) / tau
    jerk = np.diff(acc, axis=0) / tau
    t_of = lambda j: j * tau  # noqa: E731
    names = limits.joint_names

    # position
    mid, half = 0.5 * (limits.upper + limits.lower), 0.5 * (limits.upper - limits.lower)
    pos_frac = np.abs(q - mid) / half
    out = (q < limits.lower + position_margin) | (q > limits.upper - position_margin)
    if (b := _first(out)) is not None:
        j, i = b
        violations.append(f"{names[i]} position {q[j, i]:.4f} rad at t = {t_of(j):.3f} s is within "
                          f"{position_margin} rad of its limit [{limits.lower[i]}, {limits.upper[i]}]")
    # velocity (bounds at the position where each tick starts)
    lo, hi = limits.velocity_bounds(q[:-1])
    with np.errstate(divide="ignore", invalid="ignore"):
        vel_frac = np.where(v > 0, v / hi, np.where(v < 0, v / lo, 0.0))
    vel_frac = np.where(np.isfinite(vel_frac), vel_frac, np.inf)
    table_frac = np.abs(v) / limits.velocity
    vel_frac = np.maximum(vel_frac, table_frac)
    if (b := _first(vel_frac > margin)) is not None:
        j, i = b
        violations.append(f"{names[i]} velocity {v[j, i]:.4f} rad/s at t = {t_of(j):.3f} s exceeds {margin:.0%} of "
                          f"its limit [{lo[j, i]:.4f}, {hi[j, i]:.4f}] rad/s at q = {q[j, i]:.4f} rad")
    acc_frac = np.abs(acc) / limits.acceleration
    if (b := _first(acc_frac > margin)) is not None:
        j, i = b
        violations.append(f"{names[i]} acceleration {acc[j, i]:.4g} rad/s^2 at t = {t_of(j - 1):.3f} s exceeds "
                          f"{margin:.0%} of its limit {limits.acceleration[i]} rad/s^2")
    jerk_frac = np.abs(jerk) / limits.jerk
    if (b := _first(jerk_frac > margin)) is not None:
        j, i = b
        violations.append(f"{names[i]} jerk {jerk[j, i]:.4g} rad/s^3 at t = {t_of(j - 1):.3f} s exceeds "
                          f"{margin:.0%} of its limit {limits.jerk[i]} rad/s^3 (finite differences at "
                          f"{tau * 1e3:g} ms with the command held for {ticks_per_command(rate, tau)} ticks)")
    # one lost command (or one overtaken by the next): the arm sees two commands' change within one tick
    c_ext = np.vstack([rest, commands, rest])
    jump2 = np.abs(c_ext[2:] - c_ext[:-2])
    late_jerk = jump2 / tau ** 2 / limits.jerk
    late_acc = jump2 / tau / limits.acceleration
    if tolerate_lost_command:
        if (b := _first(late_jerk > margin)) is not None:
            violations.append(f"{names[b[1]]}: one lost command at t = {(b[0] - 1) / rate:.3f} s would cause a jerk "
                              f"of {late_jerk[b] * limits.jerk[b[1]]:.4g} rad/s^3, over {margin:.0%} of the limit")
        if (b := _first(late_acc > margin)) is not None:
            violations.append(f"{names[b[1]]}: one lost command at t = {(b[0] - 1) / rate:.3f} s would cause an "
                              f"acceleration over {margin:.0%} of the limit")
    peak = {"position": pos_frac.max(axis=0), "velocity": vel_frac.max(axis=0),
            "acceleration": acc_frac.max(axis=0), "jerk": jerk_frac.max(axis=0),
            "jerk_one_lost_command": late_jerk.max(axis=0), "acceleration_one_lost_command": late_acc.max(axis=0)}
    res = Verification(not violations, violations, peak, q)
    if robot is not None:
        _cartesian(res, robot, limits, margin, tau)
    n_hold = ticks_per_command(rate, tau)
    if dynamics is not None:
        from fluidlab_ros.dynamics import check_torques, smooth_derivatives

        start = time.perf_counter()
        if smooth is None:
            smooth = smooth_derivatives(q[::n_hold], 1.0 / rate)
        tc = check_torques(dynamics, *smooth, 1.0 / rate, margin)
        res.torque = tc
        res.peak.update(tc.peak)
        res.torque_violations = list(tc.violations)
        res.check_times["torque"] = time.perf_counter() - start
    if collision is not None:
        start = time.perf_counter()
        q_ticks = q[::n_hold]
        cc = collision.check(q_ticks, np.arange(len(q_ticks)) / rate)
        res.collision = cc
        res.collision_violations = list(cc.violations)
        res.check_times["collision"] = time.perf_counter() - start
    if res.torque_violations or res.collision_violations:
        res.violations.extend(res.torque_violations + res.collision_violations)
        res.ok = False
    return res


def _cartesian(res: Verification, robot, limits: JointLimits, margin: float, tau: float):
    pos, rot = robot.tool_positions_rotations(res.positions, robot.flange_id)
    res.flange_positions, res.flange_rotations = pos, rot
    lin = np.linalg.norm(np.diff(pos, axis=0), axis=1) / tau
    r = Rotation.from_matrix(rot)
    ang = (r[:-1].inv() * r[1:]).magnitude() / tau
    cart = limits.cartesian
    lin_acc = np.linalg.norm(np.diff(np.diff(pos, axis=0), axis=0), axis=1) / tau ** 2 if len(pos) > 2 else np.zeros(1)
    res.peak["cartesian_velocity"] = float(lin.max(initial=0.0)) / cart["translation"]["velocity"]
    res.peak["cartesian_rotational_velocity"] = float(ang.max(initial=0.0)) / cart["rotation"]["velocity"]
    res.peak["cartesian_acceleration"] = float(lin_acc.max(initial=0.0)) / cart["translation"]["acceleration"]
    for key, what in (("cartesian_velocity", "flange speed"), ("cartesian_rotational_velocity",
                                                              "flange angular speed")):
        if res.peak[key] > margin:
            res.violations.append(f"{what} reaches {res.peak[key]:.0%} of the Cartesian limit (margin {margin:.0%})")
            res.ok = False
