"""A Franka arm for planning: its URDF loaded with Pinocchio (offline, from robot_models/), its limits, and
an optional tool frame fixed to the flange (the task's mounting).

Frames: the world frame is the arm's base frame `<robot>_link0` (x forward, y left, z up); the flange is
`<robot>_link8`; the tool frame is added as an operational frame `tool` on the flange.

The documented start posture is Franka's ready pose READY_Q = [0, -pi/4, 0, -3pi/4, 0, pi/2, pi/4] rad
(flange about 0.31 m in front of the base, 0.59 m up, pointing down); the pipeline moves from there (or from
a measured joint state given by the caller) to the trajectory's first pose.
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin

import robot_models
from fluidlab_ros.frames import pose_to_se3
from fluidlab_ros.limits import JointLimits

READY_Q = np.array([0.0, -np.pi / 4, 0.0, -3 * np.pi / 4, 0.0, np.pi / 2, np.pi / 4])


class Robot:
    """Kinematic model of one arm, with the tool frame `tool` at `flange_to_tool` (identity if None)."""

    def __init__(self, name: str = "fr3", flange_to_tool=None):
        self.name = name
        self.limits = JointLimits.load(name)
        self.model = pin.buildModelFromUrdf(str(robot_models.urdf_path(name)))
        names = tuple(self.model.names[1:])
        if names != self.limits.joint_names or self.model.nq != self.limits.dof:
            raise ValueError(f"{name}: URDF joints {names} differ from the limits file's {self.limits.joint_names}")
        self.base_frame = f"{name}_link0"
        self.flange_frame = f"{name}_link8"
        flange = self.model.getFrameId(self.flange_frame)
        f = self.model.frames[flange]
        placement = pose_to_se3(flange_to_tool) if flange_to_tool is not None else pin.SE3.Identity()
        self.flange_to_tool = placement
        self.tool_id = self.model.addFrame(
            pin.Frame("tool", f.parentJoint, flange, f.placement * placement, pin.FrameType.OP_FRAME))
        self.flange_id = flange
        self.data = self.model.createData()

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self.limits.joint_names

    @property
    def dof(self) -> int:
        return self.model.nq

    def frame_placement(self, q, frame_id: int | None = None) -> pin.SE3:
        """Pose of a frame (default: the tool) in the base frame at joint positions q (rad)."""
        fid = self.tool_id if frame_id is None else frame_id
        pin.forwardKinematics(self.model, self.data, np.asarray(q, dtype=float))
        return pin.updateFramePlacement(self.model, self.data, fid).copy()

    def tool_positions_rotations(self, qs: np.ndarray, frame_id: int | None = None):
        """Positions (N, 3) and rotation matrices (N, 3, 3) of a frame (default: the tool) for each row of qs."""
        fid = self.tool_id if frame_id is None else frame_id
        qs = np.asarray(qs, dtype=float)
        pos = np.empty((len(qs), 3))
        rot = np.empty((len(qs), 3, 3))
        model, data = self.model, self.data
        for k, q in enumerate(qs):
            pin.forwardKinematics(model, data, q)
            m = pin.updateFramePlacement(model, data, fid)
            pos[k] = m.translation
            rot[k] = m.rotation
        return pos, rot


def load_robot(name: str = "fr3", flange_to_tool=None) -> Robot:
    """The FR3 (default) or the Panda, with the tool frame at `flange_to_tool` ([x, y, z, qx, qy, qz, qw])."""
    return Robot(name, flange_to_tool)
