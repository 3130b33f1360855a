"""Joint torques along a plan: the arm's rigid-body dynamics, checked against Franka's torque and torque-rate
limits before anything is sent.

Physics
-------
The arm is a fixed-base chain of 7 rigid links joined by revolute joints. Its equation of motion is

    tau = M(q) qdd + C(q, qd) qd + g(q)                                                     (1)

    q, qd, qdd   joint positions (rad), velocities (rad/s), accelerations (rad/s^2), (7,)
    tau          joint torques (N m), the torque each joint's drive must exert on the link it moves
    M(q)         joint-space mass matrix (kg m^2; N m s^2/rad), symmetric positive definite
    C(q, qd) qd  Coriolis and centrifugal torques (N m)
    g(q)         gravity torques (N m) = dV/dq with V(q) = - sum_i m_i g0 . c_i(q) the potential energy
                 (m_i the link masses, c_i(q) their centres of mass in the base frame)

with gravity g0 = (0, 0, -9.81) m/s^2 in the base frame `<robot>_link0` (z up: the arm stands upright on a
horizontal table). (1) is evaluated with the recursive Newton-Euler algorithm, RNEA (Luh, Walker and Paul,
"On-line computational scheme for mechanical manipulators", J. Dyn. Sys. Meas. Control 102, 1980;
Featherstone, "Rigid Body Dynamics Algorithms", Springer 2008, ch. 5), as implemented by Pinocchio's
`pinocchio.rnea` (Carpentier et al., "The Pinocchio C++ library", SII 2019), on the kinematic model of
robot_models/<robot>/<robot>.urdf with the link inertias of robot_models/<robot>/inertials.json (mass,
centre of mass and inertia tensor about it, in each link's frame; sources and licences in that file).

Payload: what is mounted on the flange (the task's tool, a Franka Hand if any) is not known; it is a point
mass `Payload.mass` (default 0.5 kg, inertials.json) at `Payload.com` in the tool frame (default its origin,
the tool tip: a longer lever than a real tool's centre of mass), rigidly attached to link 7.

Torque rate: dtau_k = (tau_{k+1} - tau_k) / T (N m/s) at the control period T. Differentiating (1),

    dtau/dt = M(q) qddd + dM/dt qdd + d/dt (C(q, qd) qd + g(q))                              (2)

and at the plan's speeds (about 1 rad/s) and accelerations (about 1 rad/s^2 at 500 Hz) the first term
dominates: for the FR3, M_22 reaches about 1.8 kg m^2, so Franka's joint jerk limit of 5000 rad/s^3 would
allow 9000 N m/s, far beyond the 1000 N m/s torque-rate limit. The planner therefore also bounds each
joint's jerk so that  sum_j |M_ij|max J_j <= share x margin x dtau_max_i  for every joint i (`torque_rate_jerk`,
|M_ij|max over the plan's own IK samples, share 0.9 as for the other planning limits), and the check below
measures (2) by finite differences.

What is sampled: the smooth plan of the jerk-limited stage (Ruckig's position, velocity and acceleration at
every control tick, t_k = k T). The velocity commands v_k = (q_{k+1} - q_k) / T integrate to those
positions. The arm holds each command for its 1 ms ticks (verify.py), so the commanded velocity is a
staircase whose finite-difference acceleration alternates between 2a and 0 at 500 Hz; that staircase is
bounded by the acceleration and jerk checks of verify.py and is smoothed by the arm's joint controller, so
the torques the rigid body needs are those of the smooth profile, evaluated here.

Neglected (the margin, default 80 % of each limit, is what covers them):
- joint friction (Coulomb and viscous): the drives exert it on top of (1);
- motor (rotor) inertia reflected through the gears, which adds to the diagonal of M and is not part of the
  published link inertias; it matters only with the inertial torques, small at the plan's accelerations;
- elasticity of the joints, and the tracking error of the arm's own controller: the torques are those of the
  commanded motion, not of the motion the arm actually makes;
- the payload's own rotational inertia (a point mass), and uncertainty of the published inertial parameters.
Franka's own torque, torque-rate and collision reflexes still apply on the arm: these checks keep a plan
from reaching them, they do not replace them.

Units: SI throughout (m, kg, s, rad, N m). Nothing is computed at import time.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pinocchio as pin

import robot_models

G0 = 9.81  # m/s^2, gravity along -z of the base frame


@dataclass(frozen=True)
class Payload:
    """A point mass (kg) rigidly attached to the flange, at `com` (m) in the tool frame."""

    mass: float = 0.5
    com: tuple = (0.0, 0.0, 0.0)

    def __post_init__(self):
        if not (np.isfinite(self.mass) and self.mass >= 0):
            raise ValueError(f"payload mass must be finite and >= 0 kg, got {self.mass}")
        if np.shape(self.com) != (3,) or not np.all(np.isfinite(self.com)):
            raise ValueError(f"payload com must be 3 finite numbers (m, tool frame), got {self.com!r}")


def load_inertials(robot: str = "fr3", path: str | Path | None = None) -> dict:
    """The inertials file of `robot` (robot_models/<robot>/inertials.json), checked: one entry per link
    <robot>_link1..7 with a positive mass and a positive definite inertia that satisfies the triangle
    inequality of its principal moments (a physically possible rigid body)."""
    path = Path(path) if path is not None else robot_models.inertials_path(robot)
    doc = json.loads(path.read_text())
    for i in range(1, 8):
        name = f"{robot}_link{i}"
        if name not in doc["links"]:
            raise ValueError(f"{path}: no inertial parameters for {name}")
        link = doc["links"][name]
        e = np.linalg.eigvalsh(inertia_matrix(link["inertia"]))
        if not link["mass"] > 0 or e[0] <= 0 or e[0] + e[1] < e[2] * (1 - 1e-9):
            raise ValueError(f"{path}: {name} is not a physical rigid body (mass {link['mass']}, principal "
                             f"moments {e.tolist()})")
    return doc


def default_payload(robot: str = "fr3") -> Payload:
    p = load_inertials(robot)["payload"]
    return Payload(float(p["mass"]), tuple(float(v) for v in p["com"]))


def inertia_matrix(i6) -> np.ndarray:
    """[ixx, ixy, ixz, iyy, iyz, izz] (URDF order) -> 3x3 symmetric tensor."""
    xx, xy, xz, yy, yz, zz = (float(v) for v in i6)
    return np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])


class DynamicModel:
    """The kinematic model of a `fluidlab_ros.robot.Robot` (with its tool frame) with the link inertias of
    robot_models/<robot>/inertials.json and a payload at the tool frame."""

    def __init__(self, robot, payload: Payload | None = None):
        self.robot = robot
        doc = load_inertials(robot.name)
        self.payload = payload if payload is not None else default_payload(robot.name)
        self.source = doc["source"]
        model = robot.model.copy()
        for j in range(1, model.njoints):  # the link a joint moves has the joint's frame (URDF child link)
            link = doc["links"][f"{robot.name}_link{j}"]
            model.inertias[j] = pin.Inertia(float(link["mass"]), np.asarray(link["com"], dtype=float),
                                            inertia_matrix(link["inertia"]))
        tool = model.frames[robot.tool_id]
        com = tool.placement.act(np.asarray(self.payload.com, dtype=float))  # in the joint 7 frame
        model.inertias[tool.parentJoint] = model.inertias[tool.parentJoint] + pin.Inertia(
            float(self.payload.mass), com, np.zeros((3, 3)))
        model.gravity = pin.Motion(np.array([0.0, 0.0, -G0]), np.zeros(3))
        self.model, self.data = model, model.createData()
        self.limits = robot.limits
        self.effort = np.asarray(robot.limits.effort, dtype=float)
        self.effort_rate = np.asarray(robot.limits.effort_rate, dtype=float)

    @property
    def joint_names(self):
        return self.robot.joint_names

    def torques(self, q, qd, qdd) -> np.ndarray:
        """tau (N, dof) in N m by RNEA for rows of q (rad), qd (rad/s), qdd (rad/s^2)."""
        q, qd, qdd = (np.atleast_2d(np.asarray(a, dtype=float)) for a in (q, qd, qdd))
        model, data = self.model, self.data
        return np.array([pin.rnea(model, data, a, b, c) for a, b, c in zip(q, qd, qdd)]).reshape(q.shape)

    def gravity(self, q) -> np.ndarray:
        """g(q) (N, dof) in N m: the torques that hold the arm still."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        model, data = self.model, self.data
        return np.array([pin.computeGeneralizedGravity(model, data, a) for a in q]).reshape(q.shape)

    def mass_matrix(self, q) -> np.ndarray:
        """M(q) (dof, dof) in kg m^2, by the composite rigid body algorithm."""
        m = pin.crba(self.model, self.data, np.asarray(q, dtype=float))
        return np.triu(m) + np.triu(m, 1).T

    def potential_energy(self, q) -> float:
        """V(q) in J, zero at the base frame's z = 0."""
        return float(pin.computePotentialEnergy(self.model, self.data, np.asarray(q, dtype=float)))


def torque_rate_jerk(dyn: DynamicModel, qs, jerk, margin: float, share: float, light: float = 0.1) -> np.ndarray:
    """Joint jerk bounds J (dof,) in rad/s^3, at most `jerk` (the kinematic budget), with
    sum_j |M_ij| J_j <= b_i = share x margin x dtau_max_i for every joint i, |M_ij| the largest over the joint
    positions `qs` (N, dof): the dominant term of (2) then stays within the torque-rate budget. A joint whose
    jerk moves little mass (its column uses at most `light` of every row's budget at its full jerk: the
    wrist's last joint) keeps its full jerk; the others share what is left of each row's budget with one
    uniform bound."""
    qs = np.atleast_2d(np.asarray(qs, dtype=float))
    jerk = np.asarray(jerk, dtype=float)
    m_abs = np.zeros((dyn.model.nv, dyn.model.nv))
    for q in qs:
        m_abs = np.maximum(m_abs, np.abs(dyn.mass_matrix(q)))
    budget = share * margin * dyn.effort_rate
    is_light = np.all(m_abs * jerk[None, :] <= light * budget[:, None], axis=0)
    rest = budget - m_abs[:, is_light] @ jerk[is_light]
    heavy = m_abs[:, ~is_light].sum(axis=1)
    with np.errstate(divide="ignore"):
        alpha = np.min(np.where(heavy > 0, rest / heavy, np.inf))
    return np.where(is_light, jerk, np.minimum(jerk, alpha))


@dataclass
class TorqueCheck:
    ok: bool
    violations: list[str]
    torque: np.ndarray  # (N, dof) N m
    torque_rate: np.ndarray  # (N - 1, dof) N m/s
    peak: dict = field(default_factory=dict)  # "torque", "torque_rate" -> (dof,) peak fraction of the limit
    peak_torque: np.ndarray | None = None  # (dof,) N m, max |tau|
    peak_torque_rate: np.ndarray | None = None  # (dof,) N m/s


def check_torques(dyn: DynamicModel, q, qd, qdd, dt: float, margin: float = 0.8, t0: float = 0.0) -> TorqueCheck:
    """Torques (1) and torque rates (finite differences over dt, s) along samples q, qd, qdd (N, dof) taken
    every dt from time t0 (s), against margin x Franka's tau_max and dtau_max. Violations name the joint,
    the value, the time and the limit (the first sample of each kind)."""
    tau = dyn.torques(q, qd, qdd)
    rate = np.diff(tau, axis=0) / dt if len(tau) > 1 else np.zeros((0, tau.shape[1]))
    frac = np.abs(tau) / dyn.effort
    rate_frac = np.abs(rate) / dyn.effort_rate
    names = dyn.joint_names
    violations = []
    bad = np.argwhere(frac > margin)
    if len(bad):
        k, i = (int(v) for v in bad[0])
        violations.append(f"{names[i]} torque {tau[k, i]:.1f} N m at t = {t0 + k * dt:.3f} s exceeds {margin:g} x "
                          f"{dyn.effort[i]:g} N m (peak {np.abs(tau[:, i]).max():.1f} N m; payload "
                          f"{dyn.payload.mass:g} kg)")
    bad = np.argwhere(rate_frac > margin)
    if len(bad):
        k, i = (int(v) for v in bad[0])
        violations.append(f"{names[i]} torque rate {rate[k, i]:.4g} N m/s at t = {t0 + (k + 0.5) * dt:.3f} s "
                          f"exceeds {margin:g} x {dyn.effort_rate[i]:g} N m/s (peak {np.abs(rate[:, i]).max():.4g} "
                          f"N m/s)")
    zeros = np.zeros(tau.shape[1])
    return TorqueCheck(not violations, violations, tau, rate,
                       {"torque": frac.max(axis=0), "torque_rate": rate_frac.max(axis=0) if len(rate) else zeros},
                       np.abs(tau).max(axis=0), np.abs(rate).max(axis=0) if len(rate) else zeros)


def smooth_derivatives(positions, dt: float):
    """(q, qd, qdd) from positions sampled every dt (s) by central differences (one-sided at the ends; at rest
    before and after), for a stream whose smooth profile is not at hand (e.g. a recorded plan)."""
    q = np.asarray(positions, dtype=float)
    qd = np.gradient(q, dt, axis=0) if len(q) > 1 else np.zeros_like(q)
    qdd = np.gradient(qd, dt, axis=0) if len(q) > 1 else np.zeros_like(q)
    return q, qd, qdd
