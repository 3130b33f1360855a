"""Poses as arrays [x, y, z, qx, qy, qz, qw] (metres, quaternion x, y, z, w) and their conversions to
Pinocchio's SE3, plus the interpolation of a Trajectory's pose samples that matches the simulator's twist
integration (p linear in time, R <- exp([w] t) R within a step)."""
from __future__ import annotations

import numpy as np
import pinocchio as pin
from scipy.spatial.transform import Rotation


def pose_to_se3(pose) -> pin.SE3:
    pose = np.asarray(pose, dtype=float)
    return pin.SE3(Rotation.from_quat(pose[3:7]).as_matrix(), pose[:3].copy())


def se3_to_pose(m: pin.SE3) -> np.ndarray:
    return np.concatenate([m.translation, Rotation.from_matrix(m.rotation).as_quat()])


def interpolate_poses(poses: np.ndarray, dt: float, r: np.ndarray) -> tuple[np.ndarray, Rotation]:
    """Positions (M, 3) and rotations (M) at trajectory times `r` (s) from samples `poses` (N + 1, 7) taken
    every `dt` seconds; times outside [0, N dt] are clamped to the ends."""
    n = len(poses) - 1
    r = np.clip(np.asarray(r, dtype=float), 0.0, n * dt)
    i = np.minimum((r / dt).astype(int), max(n - 1, 0))
    f = (r - i * dt) / dt if n > 0 else np.zeros_like(r)
    j = np.minimum(i + 1, n)
    p = poses[i, :3] + f[:, None] * (poses[j, :3] - poses[i, :3])
    r0, r1 = Rotation.from_quat(poses[i, 3:]), Rotation.from_quat(poses[j, 3:])
    step = (r1 * r0.inv()).as_rotvec()  # world-frame rotation over the step
    return p, Rotation.from_rotvec(f[:, None] * step) * r0


def rotation_angle(a: Rotation, b: Rotation) -> np.ndarray:
    """Angle (rad) of the rotation between a and b, elementwise."""
    return (a.inv() * b).magnitude()
