"""An arm's limits as data (robot_models/<robot>/limits.json): joint position, velocity, acceleration, jerk,
the FR3's position-based velocity limits, the Cartesian limits, and the joint torque and torque-rate limits
(`effort`, N m, and `effort_rate`, N m/s: checked by fluidlab_ros/dynamics.py). Values are Franka's official ones,
without margin; margins are applied by the planner and the verifier (see docs/execution.md)."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import robot_models


@dataclass(frozen=True)
class JointLimits:
    robot: str
    joint_names: tuple[str, ...]
    lower: np.ndarray  # rad
    upper: np.ndarray  # rad
    velocity: np.ndarray  # rad/s, the table maximum
    acceleration: np.ndarray  # rad/s^2
    jerk: np.ndarray  # rad/s^3
    position_based_velocity: dict | None  # FR3: gain, offset, q_upper, q_lower arrays
    cartesian: dict  # translation/rotation/elbow: velocity, acceleration, jerk
    check_period: float  # s, libfranka checks every command at this period
    effort: np.ndarray | None = None  # N m, tau_max per joint
    effort_rate: np.ndarray | None = None  # N m/s, dtau_max per joint

    @classmethod
    def load(cls, robot: str = "fr3", path: str | Path | None = None) -> "JointLimits":
        path = Path(path) if path is not None else robot_models.limits_path(robot)
        doc = json.loads(path.read_text())
        arr = lambda v: np.asarray(v, dtype=float)  # noqa: E731
        pbv = doc.get("position_based_velocity")
        if pbv is not None:
            pbv = {k: arr(pbv[k]) for k in ("gain", "offset", "q_upper", "q_lower")}
        lim = cls(robot=doc["robot"], joint_names=tuple(doc["joint_names"]), lower=arr(doc["position"]["lower"]),
                  upper=arr(doc["position"]["upper"]), velocity=arr(doc["velocity"]),
                  acceleration=arr(doc["acceleration"]), jerk=arr(doc["jerk"]), position_based_velocity=pbv,
                  cartesian=doc["cartesian"], check_period=float(doc.get("check_period", 1e-3)),
                  effort=arr(doc["effort"]) if "effort" in doc else None,
                  effort_rate=arr(doc["effort_rate"]) if "effort_rate" in doc else None)
        for name in ("lower", "upper", "velocity", "acceleration", "jerk"):
            if getattr(lim, name).shape != (len(lim.joint_names),):
                raise ValueError(f"{path}: {name} must have one value per joint ({len(lim.joint_names)})")
        for name in ("effort", "effort_rate"):
            v = getattr(lim, name)
            if v is not None and (v.shape != (len(lim.joint_names),) or np.any(v <= 0)):
                raise ValueError(f"{path}: {name} must have one positive value per joint ({len(lim.joint_names)})")
        if np.any(lim.lower >= lim.upper) or np.any(lim.velocity <= 0) or np.any(lim.acceleration <= 0) \
                or np.any(lim.jerk <= 0):
            raise ValueError(f"{path}: limits must have lower < upper and positive velocity, acceleration, jerk")
        return lim

    @property
    def dof(self) -> int:
        return len(self.joint_names)

    def velocity_bounds(self, q) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) allowed joint velocity (rad/s) at positions q (..., dof). For the FR3 the bounds
        shrink near the position limits (Franka's position-based velocity limits); elsewhere they are
        -velocity, +velocity."""
        q = np.asarray(q, dtype=float)
        hi = np.broadcast_to(self.velocity, q.shape).copy()
        lo = -hi
        p = self.position_based_velocity
        if p is not None:
            up = -p["offset"] + np.sqrt(np.maximum(0.0, p["gain"] * (p["q_upper"] - q)))
            dn = p["offset"] - np.sqrt(np.maximum(0.0, p["gain"] * (q - p["q_lower"])))
            hi = np.minimum(hi, np.maximum(0.0, up))
            lo = np.maximum(lo, np.minimum(0.0, dn))
        return lo, hi
