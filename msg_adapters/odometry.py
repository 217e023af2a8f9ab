"""nav_msgs/Odometry <-> numbers: a camera's (or an IMU's) pose over time, e.g. for metric scale.

Reading (:func:`odometry_to_position`) is duck-typed: rclpy and rosbags messages alike.
Writing (:func:`odometry_msg`) builds a rosbags type store's classes (the bag tools) or rclpy's
from a 4x4 pose (``parent_from_child``: the child frame's pose in the parent frame, metres):
position = its translation, orientation = its rotation as a unit quaternion (x, y, z, w, w >= 0),
twist zero, covariances zero (not estimated).
"""

from __future__ import annotations

import importlib

import numpy as np

from msg_adapters.classes import make_header, rclpy_classes, typestore_classes
from msg_adapters.stamp import stamp_to_seconds
from sfm_ttr_ros.core.errors import InputError

ODOMETRY_MSGTYPE = "nav_msgs/msg/Odometry"


class OdometryError(InputError):
    """A pose that cannot be written as an Odometry, or an Odometry that cannot be read."""


def odometry_to_position(msg) -> tuple[float, np.ndarray]:
    """(header stamp in seconds, position x, y, z as a float64 array) of a nav_msgs/Odometry."""
    p = msg.pose.pose.position
    xyz = np.array([float(p.x), float(p.y), float(p.z)], np.float64)
    if not np.isfinite(xyz).all():
        raise OdometryError(f"Odometry position is not finite: {xyz.tolist()}")
    return stamp_to_seconds(msg.header.stamp), xyz


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """A 3x3 rotation matrix -> the unit quaternion (x, y, z, w) with w >= 0 (Shepperd's
    method: the largest of the four squared terms first, stable near 180 degrees)."""
    R = np.asarray(R, np.float64)
    if R.shape != (3, 3) or not np.isfinite(R).all():
        raise OdometryError(f"a rotation must be a finite 3x3 matrix, got shape {R.shape}")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise OdometryError("not a rotation matrix (R Rᵀ ≠ I or det < 0)")
    t = np.trace(R)
    cands = [t, R[0, 0], R[1, 1], R[2, 2]]
    k = int(np.argmax(cands))
    if k == 0:
        s = 2.0 * np.sqrt(1.0 + t)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, s / 4]
    elif k == 1:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [s / 4, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif k == 2:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 1] + R[1, 0]) / s, s / 4, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, s / 4, (R[1, 0] - R[0, 1]) / s]
    q = np.array(q) / np.linalg.norm(q)
    return -q if q[3] < 0 else q


def quaternion_to_rotation(q) -> np.ndarray:
    """The unit quaternion (x, y, z, w) -> its 3x3 rotation matrix."""
    x, y, z, w = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _rclpy_type(msgtype: str) -> type:
    pkg, kind, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)


def odometry_msg(stamp_ns: int, frame_id: str, child_frame_id: str, parent_from_child,
                 store=None):
    """A nav_msgs/Odometry stamped ``stamp_ns`` in ``frame_id`` whose pose is the 4x4
    ``parent_from_child`` of ``child_frame_id`` (metres). ``store``: a rosbags type store (its
    classes are built, for bags) or None (rclpy's)."""
    T = np.asarray(parent_from_child, np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise OdometryError(f"a pose must be a finite 4x4 matrix, got shape {T.shape}")
    q = rotation_to_quaternion(T[:3, :3])
    t = T[:3, 3]
    if store is None:
        classes, of = rclpy_classes(), _rclpy_type
    else:
        classes, of = typestore_classes(store), store.types.__getitem__
    point, quat = of("geometry_msgs/msg/Point"), of("geometry_msgs/msg/Quaternion")
    vec = of("geometry_msgs/msg/Vector3")
    zeros = classes.doubles_field(np.zeros(36))  # covariances: not estimated
    pose = of("geometry_msgs/msg/PoseWithCovariance")(
        pose=of("geometry_msgs/msg/Pose")(
            position=point(x=float(t[0]), y=float(t[1]), z=float(t[2])),
            orientation=quat(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))),
        covariance=zeros)
    twist = of("geometry_msgs/msg/TwistWithCovariance")(
        twist=of("geometry_msgs/msg/Twist")(linear=vec(x=0.0, y=0.0, z=0.0),
                                            angular=vec(x=0.0, y=0.0, z=0.0)),
        covariance=classes.doubles_field(np.zeros(36)))
    return of(ODOMETRY_MSGTYPE)(header=make_header(stamp_ns, frame_id, classes),
                                child_frame_id=str(child_frame_id), pose=pose, twist=twist)
