"""The twin arm: a simulated Franka behind a joint velocity controller, with the arm's reflexes.

Model (what franka_ros2's JointGroupVelocityController and libfranka do with a velocity stream):
- the arm runs a 1 kHz loop (tick tau = 1 ms); each tick it uses the newest command that arrived before it,
  and holds the previous one when none arrived (a late or lost command is held, not skipped);
- positions integrate the held velocity: q_{j+1} = q_j + tau * v_j;
- every tick libfranka checks the commanded signal by finite differences against the official limits
  (no margin):  |v_j| within the (position-based) velocity bounds,  |a_j| = |v_j - v_{j-1}| / tau <= a_max,
  |jerk_j| = |a_j - a_{j-1}| / tau <= j_max, and q within the position limits.
A violation is a reflex: the arm stops at once (the twin sets v = 0, as the brakes do), records the reason
with libfranka's name for it, and ignores commands until `recover()` (franka's error recovery).

Time comes from the caller (seconds on a monotonic clock), so the same object runs in real time inside
sim_node and faster than real time in tests. Units: rad, rad/s. No fluid here (that is fluidlab_core's).
"""
from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from fluidlab_ros.limits import JointLimits

REFLEX_NAMES = {
    "velocity": "joint_velocity_violation",
    "acceleration": "joint_motion_generator_velocity_discontinuity",
    "jerk": "joint_motion_generator_acceleration_discontinuity",
    "position": "joint_position_limits_violation",
}


@dataclass
class Reflex:
    kind: str  # libfranka's name
    joint: str
    value: float  # the offending value (rad, rad/s, rad/s^2 or rad/s^3)
    limit: float
    time: float  # s on the caller's clock

    def message(self) -> str:
        return (f"reflex {self.kind}: {self.joint} reached {self.value:.4g} against a limit of {self.limit:.4g} "
                f"at t = {self.time:.3f} s")


class TwinArm:
    """Joint positions and the held velocity command of a simulated arm, with libfranka's checks."""

    def __init__(self, limits: JointLimits, q0):
        self.limits = limits
        self.tau = limits.check_period
        self._lock = threading.Lock()
        self.q = np.array(q0, dtype=float)
        self.v = np.zeros(limits.dof)  # velocity applied at the last tick
        self.a = np.zeros(limits.dof)  # finite-difference acceleration at the last tick
        self.held = np.zeros(limits.dof)  # newest command, applied from the next tick
        self.tick_time: float | None = None  # caller time of the last simulated tick
        self.reflex: Reflex | None = None
        self.commands_received = 0
        self.ticks = 0

    # --- called by the command stream ---------------------------------------------------------------
    def command(self, velocity, now: float) -> Reflex | None:
        """A velocity command arrives at time `now`: run the ticks up to `now` with the previous command
        held, then hold this one. Returns the reflex if one happened."""
        velocity = np.asarray(velocity, dtype=float)
        with self._lock:
            self._advance(now)
            if self.reflex is None:
                self.held = velocity.copy()
            self.commands_received += 1
            return self.reflex

    def advance(self, now: float) -> Reflex | None:
        """Run the 1 ms ticks up to `now` holding the last command (the controller's loop goes on between
        commands)."""
        with self._lock:
            self._advance(now)
            return self.reflex

    def state(self) -> tuple[np.ndarray, np.ndarray]:
        with self._lock:
            return self.q.copy(), self.v.copy()

    def recover(self):
        """Franka's error recovery: clear a reflex; the arm is at rest where it stopped."""
        with self._lock:
            self.reflex = None
            self.held[:] = 0.0
            self.v[:] = 0.0
            self.a[:] = 0.0

    def snapshot(self) -> dict:
        """The whole state, to hand the arm to another process (the stream process and back)."""
        with self._lock:
            return {"q": self.q.copy(), "v": self.v.copy(), "a": self.a.copy(), "held": self.held.copy(),
                    "tick_time": self.tick_time, "reflex": self.reflex}

    def restore(self, snap: dict):
        with self._lock:
            self.q, self.v = np.array(snap["q"], dtype=float), np.array(snap["v"], dtype=float)
            self.a, self.held = np.array(snap["a"], dtype=float), np.array(snap["held"], dtype=float)
            self.tick_time, self.reflex = snap["tick_time"], snap["reflex"]

    def reset(self, q0, now: float | None = None):
        with self._lock:
            self.q = np.array(q0, dtype=float)
            self.v[:] = 0.0
            self.a[:] = 0.0
            self.held[:] = 0.0
            self.reflex = None
            self.tick_time = now

    # --- the 1 kHz loop ------------------------------------------------------------------------------
    def _advance(self, now: float):
        if self.tick_time is None:
            self.tick_time = now
            return
        n = int(np.floor((now - self.tick_time) / self.tau + 1e-9))
        if n <= 0:
            return
        if self.reflex is not None or (not self.held.any() and not self.v.any() and not self.a.any()):
            self.tick_time += n * self.tau  # at rest: nothing to check
            self.ticks += n
            return
        lim = self.limits
        for _ in range(n):
            self.tick_time += self.tau
            self.ticks += 1
            v = self.held
            a = (v - self.v) / self.tau
            jerk = (a - self.a) / self.tau
            lo, hi = lim.velocity_bounds(self.q)
            checks = (("velocity", np.maximum(v - hi, lo - v), np.abs(v), np.where(v >= 0, hi, -lo)),
                      ("acceleration", np.abs(a) - lim.acceleration, np.abs(a), lim.acceleration),
                      ("jerk", np.abs(jerk) - lim.jerk, np.abs(jerk), lim.jerk))
            for kind, excess, value, limit in checks:
                j = int(np.argmax(excess))
                if excess[j] > 1e-9 * max(1.0, float(limit[j])):
                    self._trip(kind, j, float(value[j]), float(limit[j]))
                    return
            q_next = self.q + self.tau * v
            out = (q_next < lim.lower) | (q_next > lim.upper)
            if out.any():
                j = int(np.argmax(out))
                self._trip("position", j, float(q_next[j]), float(lim.upper[j] if q_next[j] > lim.upper[j]
                                                                   else lim.lower[j]))
                return
            self.q, self.v, self.a = q_next, v.copy(), a
        return

    def _trip(self, kind: str, joint: int, value: float, limit: float):
        self.reflex = Reflex(REFLEX_NAMES[kind], self.limits.joint_names[joint], value, limit, self.tick_time)
        self.v[:] = 0.0
        self.a[:] = 0.0
        self.held[:] = 0.0
