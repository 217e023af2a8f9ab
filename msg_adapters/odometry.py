"""nav_msgs/Odometry <-> numbers: a camera's (or an IMU's) pose over time, e.g. for metric scale.

Reading (:func:`odometry_to_position`) is duck-typed: rclpy and rosbags messages alike.
Writing (:func:`odometry_msg`) builds a rosbags type store's classes (the bag tools) or rclpy's
from a 4x4 pose (``parent_from_child``: the child frame's pose in the parent frame, metres):
position = its translation, orientation = its rotation as a unit quaternion (x, y, z, w, w >= 0);
the pose's covariance given (6x6 over x, y, z and the rotations about x, y, z, row-major, in the
header's frame: nav_msgs' convention) or zero (not estimated); the twist (vx vy vz ωx ωy ωz in
the child frame) and its covariance given, or zero; a twist covariance whose [0] is -1 says the
twist is unknown (nav_msgs' convention; its other numbers then zero). :func:`odometry_to_pose`
reads a pose and its covariance back, :func:`odometry_to_twist` the twist and its covariance;
:func:`transform_msg` writes the same pose as a geometry_msgs/TransformStamped for ``/tf``.
"""

from __future__ import annotations

import importlib

import numpy as np

from msg_adapters.classes import make_header, rclpy_classes, typestore_classes
from msg_adapters.stamp import stamp_to_seconds
from sfm_ttr_ros.core.errors import InputError

ODOMETRY_MSGTYPE = "nav_msgs/msg/Odometry"
UNKNOWN = -1.0  # covariance[0] of a quantity not provided


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


def _checked_pose(parent_from_child) -> tuple[np.ndarray, np.ndarray]:
    """(translation, quaternion x y z w) of a finite 4x4 rigid pose."""
    T = np.asarray(parent_from_child, np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise OdometryError(f"a pose must be a finite 4x4 matrix, got shape {T.shape}")
    return T[:3, 3], rotation_to_quaternion(T[:3, :3])


def _checked_covariance(covariance, what: str = "pose") -> np.ndarray:
    """36 finite numbers of a symmetric 6x6 covariance with a non-negative diagonal (zeros
    when None); for a twist also -1 then zeros (unknown)."""
    if covariance is None:
        return np.zeros(36)
    C = np.asarray(covariance, np.float64)
    if C.size != 36 or not np.isfinite(C).all():
        raise OdometryError(f"a {what} covariance must be 36 finite numbers (6x6), got {C.size}")
    C = C.ravel()
    if what == "twist" and C[0] == UNKNOWN and not C[1:].any():
        return C
    M = C.reshape(6, 6)
    if not np.allclose(M, M.T) or (np.diag(M) < 0).any():
        raise OdometryError(f"a {what} covariance must be symmetric with a diagonal >= 0")
    return C


def odometry_msg(stamp_ns: int, frame_id: str, child_frame_id: str, parent_from_child,
                 store=None, covariance=None, twist=None, twist_covariance=None):
    """A nav_msgs/Odometry stamped ``stamp_ns`` in ``frame_id`` whose pose is the 4x4
    ``parent_from_child`` of ``child_frame_id`` (metres) with the pose's 6x6 ``covariance``
    (None: zeros, not estimated), the ``twist`` (six numbers, None: zeros) and its
    ``twist_covariance`` (module docstring). ``store``: a rosbags type store (its classes are
    built, for bags) or None (rclpy's)."""
    t, q = _checked_pose(parent_from_child)
    cov = _checked_covariance(covariance)
    tw = np.zeros(6) if twist is None else np.asarray(twist, np.float64).ravel()
    if tw.size != 6 or not np.isfinite(tw).all():
        raise OdometryError(f"a twist must be six finite numbers, got {tw.size}")
    twist_cov = _checked_covariance(twist_covariance, "twist")
    if store is None:
        classes, of = rclpy_classes(), _rclpy_type
    else:
        classes, of = typestore_classes(store), store.types.__getitem__
    point, quat = of("geometry_msgs/msg/Point"), of("geometry_msgs/msg/Quaternion")
    vec = of("geometry_msgs/msg/Vector3")
    pose = of("geometry_msgs/msg/PoseWithCovariance")(
        pose=of("geometry_msgs/msg/Pose")(
            position=point(x=float(t[0]), y=float(t[1]), z=float(t[2])),
            orientation=quat(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))),
        covariance=classes.doubles_field(cov))
    twist = of("geometry_msgs/msg/TwistWithCovariance")(
        twist=of("geometry_msgs/msg/Twist")(
            linear=vec(x=float(tw[0]), y=float(tw[1]), z=float(tw[2])),
            angular=vec(x=float(tw[3]), y=float(tw[4]), z=float(tw[5]))),
        covariance=classes.doubles_field(twist_cov))
    return of(ODOMETRY_MSGTYPE)(header=make_header(stamp_ns, frame_id, classes),
                                child_frame_id=str(child_frame_id), pose=pose, twist=twist)


def odometry_to_pose(msg) -> tuple[float, np.ndarray, np.ndarray]:
    """(header stamp in seconds, the 4x4 pose, the 6x6 pose covariance) of a nav_msgs/Odometry."""
    stamp, xyz = odometry_to_position(msg)
    o = msg.pose.pose.orientation
    T = np.eye(4)
    T[:3, :3] = quaternion_to_rotation([float(o.x), float(o.y), float(o.z), float(o.w)])
    T[:3, 3] = xyz
    return stamp, T, _checked_covariance(list(msg.pose.covariance)).reshape(6, 6)


def odometry_to_twist(msg) -> tuple[np.ndarray, np.ndarray]:
    """(the twist vx vy vz ωx ωy ωz, its 6x6 covariance) of a nav_msgs/Odometry."""
    lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
    twist = np.array([float(v) for v in (lin.x, lin.y, lin.z, ang.x, ang.y, ang.z)])
    return twist, _checked_covariance(list(msg.twist.covariance), "twist").reshape(6, 6)


def transform_msg(stamp_ns: int, frame_id: str, child_frame_id: str, parent_from_child):
    """A geometry_msgs/TransformStamped (rclpy's): ``child_frame_id`` in ``frame_id``, the
    4x4 ``parent_from_child`` (what TF's ``/tf`` carries)."""
    from geometry_msgs.msg import Quaternion, Transform, TransformStamped, Vector3

    t, q = _checked_pose(parent_from_child)
    return TransformStamped(
        header=make_header(stamp_ns, frame_id), child_frame_id=str(child_frame_id),
        transform=Transform(translation=Vector3(x=float(t[0]), y=float(t[1]), z=float(t[2])),
                            rotation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                                w=float(q[3]))))


def tf_message_class() -> type:
    """tf2_msgs/TFMessage (rclpy's); InputError naming the package when it is not installed."""
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError as exc:
        raise InputError("TF output needs the tf2_msgs message package, which is not "
                         f"installed ({exc}); install ROS 2's tf2_msgs or leave TF off") from exc
    return TFMessage
