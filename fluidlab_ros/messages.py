"""ROS messages built from numpy arrays: velocity commands, poses, point clouds (with per-point colour),
sphere-list markers."""
from __future__ import annotations

import numpy as np
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import ColorRGBA, Float64MultiArray, MultiArrayDimension
from visualization_msgs.msg import Marker


def velocity_command(command: np.ndarray, order: np.ndarray) -> Float64MultiArray:
    """A JointGroupVelocityController command: joint velocities (rad/s) in the controller's joint order."""
    msg = Float64MultiArray()
    msg.layout.dim = [MultiArrayDimension(label="joints", size=len(command), stride=len(command))]
    msg.data = np.asarray(command, dtype=float)[order].tolist()
    return msg


def pose_msg(pose, frame_id: str, stamp_ns: int) -> PoseStamped:
    ps = PoseStamped()
    ps.header.frame_id = frame_id
    ps.header.stamp.sec, ps.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    ps.pose.position.x, ps.pose.position.y, ps.pose.position.z = (float(x) for x in pose[:3])
    o = ps.pose.orientation
    o.x, o.y, o.z, o.w = (float(x) for x in pose[3:])
    return ps


def marker(mid: int, name: str, points: np.ndarray, rgba, diameter: float, frame_id: str, stamp) -> Marker:
    from geometry_msgs.msg import Point

    m = Marker()
    m.header.frame_id, m.header.stamp = frame_id, stamp
    m.ns, m.id, m.type, m.action = name, mid, Marker.SPHERE_LIST, Marker.ADD
    m.pose.orientation.w = 1.0
    m.scale.x = m.scale.y = m.scale.z = float(diameter)
    m.color = ColorRGBA(r=float(rgba[0]), g=float(rgba[1]), b=float(rgba[2]), a=float(rgba[3]))
    m.points = [Point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in points]
    return m


def point_cloud(points: np.ndarray, frame_id: str, stamp, colors: np.ndarray | None = None) -> PointCloud2:
    """An unordered PointCloud2 of (N, 3) float32 x, y, z (m); with colors (N, 3) uint8, also the packed
    float32 `rgb` field that RViz and Foxglove colour by (0x00RRGGBB reinterpreted as float32, PCL's layout)."""
    pts = np.ascontiguousarray(points, dtype=np.float32)
    msg = PointCloud2()
    msg.header.frame_id = frame_id
    if stamp is not None:
        msg.header.stamp = stamp
    msg.height, msg.width = 1, len(pts)
    fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, n in enumerate("xyz")]
    if colors is not None and len(colors) == len(pts):
        c = np.asarray(colors, dtype=np.uint32)
        rgb = ((c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]).astype(np.uint32).view(np.float32)
        data = np.hstack([pts, rgb[:, None]])
        fields.append(PointField(name="rgb", offset=12, datatype=PointField.FLOAT32, count=1))
    else:
        data = pts
    msg.fields = fields
    step = 4 * data.shape[1]
    msg.is_bigendian, msg.point_step, msg.row_step, msg.is_dense = False, step, step * len(pts), True
    msg.data = np.ascontiguousarray(data, dtype=np.float32).tobytes()
    return msg
