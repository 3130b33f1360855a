"""Differential inverse kinematics with Pinocchio: damped least squares on the tool pose error, with
joint-limit avoidance and a posture term in the null space.

For a target pose T and the tool pose F(q), the error is e = log6(F(q)^-1 T) (tool frame, [v, w]) and its
Jacobian J_e = -Jlog6(T^-1 F(q)) J(q) with J the tool frame's local Jacobian (as in Pinocchio's IK example).
One step is

    dq = -J_e^T (J_e J_e^T + lambda^2 I)^-1 e  +  (I - J_e^+ J_e) z dt

where lambda grows from `damping` to `max_damping` as the smallest singular value of J_e falls below
`singular_threshold` (adaptive damping near singularities), and the null-space velocity z (rad/s) pulls
each joint away from its limits inside a band of `limit_band` rad and towards a posture q_posture. Along a
path, each target is solved from the previous solution: the first step of each sample carries the
null-space term (it is a velocity over the sample's dt), then plain DLS iterations run until the residual is
below tolerance.
A target whose residual stays above `reject_position` / `reject_rotation` is refused as unreachable.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin
from scipy.spatial.transform import Rotation

from fluidlab_ros.errors import UnreachableError
from fluidlab_ros.robot import Robot


@dataclass(frozen=True)
class IKOptions:
    damping: float = 1e-4  # minimum DLS damping lambda
    max_damping: float = 0.05  # lambda at a singularity
    singular_threshold: float = 0.04  # smallest singular value below which damping grows
    max_iterations: int = 30  # per target
    tol_position: float = 1e-7  # m, stop iterating below this residual...
    tol_rotation: float = 1e-6  # rad, ...and this one
    reject_position: float = 1e-4  # m, a larger final residual refuses the target
    reject_rotation: float = 1e-3  # rad
    max_step: float = 0.1  # rad, largest joint change per iteration
    posture_gain: float = 0.5  # 1/s, null-space pull towards the posture
    limit_gain: float = 2.0  # rad/s at the limit, null-space push away from joint limits
    limit_band: float = 0.3  # rad, width of the band next to each limit where the push acts


@dataclass
class IKResult:
    q: np.ndarray  # (N, dof) joint positions, rad
    residual_position: np.ndarray  # (N,) m
    residual_rotation: np.ndarray  # (N,) rad
    iterations: np.ndarray  # (N,)


class DifferentialIK:
    def __init__(self, robot: Robot, options: IKOptions = IKOptions()):
        self.robot, self.opt = robot, options
        self.lower, self.upper = robot.limits.lower, robot.limits.upper

    def _error_and_jacobian(self, q, target: pin.SE3):
        model, data, fid = self.robot.model, self.robot.data, self.robot.tool_id
        pin.computeJointJacobians(model, data, q)  # forward kinematics and joint Jacobians in one pass
        cMt = pin.updateFramePlacement(model, data, fid).actInv(target)
        jac = pin.getFrameJacobian(model, data, fid, pin.LOCAL)
        return pin.log6(cMt).vector, -pin.Jlog6(cMt.inverse()) @ jac

    def _dls(self, jac_e):
        o = self.opt
        jjt = jac_e @ jac_e.T
        sigma_min = np.sqrt(max(np.linalg.eigvalsh(jjt)[0], 0.0))
        lam2 = o.damping ** 2
        if sigma_min < o.singular_threshold:
            lam2 += o.max_damping ** 2 * (1.0 - (sigma_min / o.singular_threshold) ** 2)
        return np.linalg.solve(jjt + lam2 * np.eye(6), jac_e).T

    def null_space_velocity(self, q, q_posture) -> np.ndarray:
        """z (rad/s): away from joint limits inside the band, towards the posture elsewhere."""
        o = self.opt
        z = -o.posture_gain * (q - q_posture)
        near_up = q > self.upper - o.limit_band
        near_lo = q < self.lower + o.limit_band
        z[near_up] -= o.limit_gain * (q[near_up] - (self.upper[near_up] - o.limit_band)) / o.limit_band
        z[near_lo] += o.limit_gain * ((self.lower[near_lo] + o.limit_band) - q[near_lo]) / o.limit_band
        return z

    def solve(self, target: pin.SE3, q, null_velocity=None, dt: float = 0.0):
        """Joint positions reaching `target` from q; returns (q, position residual m, rotation residual rad,
        iterations). The first step adds the null-space velocity (rad/s) over dt, projected at q, to the DLS
        step; later iterations are plain DLS until the residual is below tolerance."""
        o = self.opt
        q = np.array(q, dtype=float)
        with_null = null_velocity is not None and dt > 0
        for it in range(o.max_iterations + 1):
            err, jac_e = self._error_and_jacobian(q, target)
            res_p, res_r = np.linalg.norm(err[:3]), np.linalg.norm(err[3:])
            converged = res_p < o.tol_position and res_r < o.tol_rotation
            if (converged and not (it == 0 and with_null)) or it == o.max_iterations:
                break
            pinv = self._dls(jac_e)
            dq = -pinv @ err
            if it == 0 and with_null:
                dq += (np.eye(len(q)) - pinv @ jac_e) @ (null_velocity * dt)
            step = np.max(np.abs(dq))
            if step > o.max_step:
                dq *= o.max_step / step
            q = q + dq
        return q, res_p, res_r, it

    def track(self, poses: np.ndarray, q0, dt: float, q_posture=None, what: str = "trajectory",
              null_weight=None) -> IKResult:
        """Solve every pose (N, 7) in turn, each from the previous solution; the first from q0. The null-space
        velocity at sample i is scaled by null_weight[i] (default 1), e.g. to fade self-motion out where a
        segment comes to rest. Raises UnreachableError at the first pose whose residual stays above the
        rejection tolerance."""
        o = self.opt
        q = np.array(q0, dtype=float)
        q_posture = q.copy() if q_posture is None else np.asarray(q_posture, dtype=float)
        out = np.empty((len(poses), len(q)))
        rotations = Rotation.from_quat(poses[:, 3:]).as_matrix()
        res_p, res_r, iters = np.empty(len(poses)), np.empty(len(poses)), np.empty(len(poses), dtype=int)
        for i, pose in enumerate(poses):
            null = None
            if i > 0:
                null = self.null_space_velocity(q, q_posture) * (1.0 if null_weight is None else null_weight[i])
            target = pin.SE3(rotations[i], pose[:3].copy())
            q, res_p[i], res_r[i], iters[i] = self.solve(target, q, null, dt)
            if not np.all(np.isfinite(q)):
                raise UnreachableError(f"{what} step {i}: inverse kinematics produced NaN", step=i)
            if res_p[i] > o.reject_position or res_r[i] > o.reject_rotation:
                raise UnreachableError(
                    f"{what} step {i} (t = {i * dt:.3f} s): pose {np.round(pose[:3], 4).tolist()} m is unreachable "
                    f"for the {self.robot.name}: inverse kinematics residual {res_p[i] * 1e3:.3g} mm, "
                    f"{np.degrees(res_r[i]):.3g} deg after {iters[i]} iterations (tolerance "
                    f"{o.reject_position * 1e3:.3g} mm, {np.degrees(o.reject_rotation):.3g} deg)",
                    step=i, residual_position=float(res_p[i]), residual_rotation=float(res_r[i]))
            out[i] = q
        return IKResult(out, res_p, res_r, iters)
