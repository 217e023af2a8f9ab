"""The camera's path as the robot base's odometry (REP 105): what ``~/odom`` publishes.

The stream's path (core/camera_path.py) holds the camera's optical poses in the path's frame
(the first camera's REP 103 body axes), chained window by window; the chaining may step where a
fresh map meets the path. :class:`BaseOdometry` turns the poses of one topic (one units: the
path's poses in metres, or in SfM units) into what a fusion stack reads as wheel-like odometry:

* the base, not the camera: T_odom_base = T_odom_cam · T_cam_base, T_base_cam the camera's
  mounting (:func:`parse_camera_mount`: x y z in the units of the path, roll pitch yaw in
  degrees, of the optical frame in the base frame; ``0 0 0 -90 0 -90`` is REP 103's optical
  frame at the base's origin looking along its x);
* a gravity-aligned ``odom`` where the ground is known: fixed at the topic's first pose, its
  origin that base's position; when that pose's window measured the ground plane
  (``metric.source: camera_height``: :attr:`PathPose.ground_up`) odom's z is the plane's up
  and its x the base's heading projected on the plane; otherwise odom's axes are the first
  base pose's (REP 103 by the mount). odom never turns afterwards (REP 105: odom -> base
  continuous);
* continuous: the jump J a window chained by a fit carries (:attr:`PathPose.jump`) is absorbed
  into odom (odom_from_path ← odom_from_path·J, what REP 105 lets ``map`` -> ``odom`` do, never
  ``odom`` -> base), so the base's step across it is the window's own motion; a break already
  continues from the path's end on the constant-velocity guess (core/camera_path.py);
* the pose's covariance (diagonal, x y z then rotations about x y z): the path's local
  precision (position plus the rotation's lever arm |t_cam_base|²·σ²_rot; at least
  :data:`MIN_VARIANCE`), plus the jumps absorbed (their translation² and angle²), plus the
  drift: position σ grows by :data:`DRIFT_PER_DISTANCE` of the distance the base travelled on
  this topic. The heading's drift is not measured on its own (it is inside the end-point drift);
  the rotations' variance has no distance term;
* the twist (the base's body frame, child_frame_id) from the previous pose of the topic: the
  motion D = T_{k−1}⁻¹·T_k over dt, v = R_{k−1}ᵀ(p_k − p_{k−1})/dt, ω = log(R_{k−1}ᵀR_k)/dt,
  variance (σ²_{k−1} + σ²_k)/dt² of their
  local precisions (a bound: consecutive poses share most of their error); without a previous
  pose (or dt <= 0) zero with covariance[0] = -1 (unknown, :data:`UNKNOWN_TWIST`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sfm_ttr_ros.core.camera_path import PathPose
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.geometry import rotation_angle

#: 1-sigma position drift per unit travelled: the stream path's end-point drift measured on the
#: generated drives (BENCHMARKS.md, "The camera's path": 2.10 % on B 300, 1.25 % on B 600),
#: rounded up to the worse.
DRIFT_PER_DISTANCE = 0.02
#: The least variance of a published pose (units², rad²): never certain (1 mm, 1 mrad in metres).
MIN_VARIANCE = 1e-6
#: covariance[0] of a twist with no previous pose to difference: unknown (nav_msgs' convention).
UNKNOWN_TWIST = -1.0
#: REP 103's optical frame at the base's origin, looking along the base's x.
DEFAULT_CAMERA_MOUNT = "0 0 0 -90 0 -90"


def rpy_rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw)·Ry(pitch)·Rx(roll), radians (REP 103's fixed-axis roll, pitch, yaw)."""
    cr, sr, cp, sp, cy, sy = (f(a) for a in (roll, pitch, yaw) for f in (math.cos, math.sin))
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    Ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    Rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    return Rz @ Ry @ Rx


def parse_camera_mount(text: str) -> np.ndarray:
    """``odom.camera_mount`` "x y z roll pitch yaw" (spaces or commas; angles in degrees) → the
    4x4 base_from_camera (the camera optical frame's pose in the base frame)."""
    parts = str(text).replace(",", " ").split()
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 6 or not all(math.isfinite(v) for v in values):
        raise InputError("odom.camera_mount must be six numbers 'x y z roll pitch yaw' (the "
                         f"camera optical frame in the base frame, degrees), got {text!r}")
    T = np.eye(4)
    T[:3, :3] = rpy_rotation(*np.radians(values[3:]))
    T[:3, 3] = values[:3]
    return T


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """log(R): the axis times the angle (rad) of a rotation matrix."""
    angle = rotation_angle(R)
    w = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s = float(np.linalg.norm(w))
    if s > 1e-9:
        return w * (angle / s)
    if angle < 1.0:  # the identity
        return np.zeros(3)
    B = 0.5 * (R + np.eye(3))  # a half turn: R = 2aaᵀ − I
    axis = B[:, int(np.argmax(np.diag(B)))]
    return axis / np.linalg.norm(axis) * angle


def _inverse(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def odom_from_first(path_from_base: np.ndarray, up: np.ndarray | None) -> np.ndarray:
    """odom_from_path for odom fixed at the base pose ``path_from_base`` (module docstring):
    z along ``up`` (in the path's axes) and x the base's heading on the plane, or the base's
    own axes without ``up``."""
    F = path_from_base.copy()
    if up is not None and np.linalg.norm(up) > 0:
        z = np.asarray(up, np.float64) / np.linalg.norm(up)
        for heading in (F[:3, 0], F[:3, 2], F[:3, 1]):  # x, or another axis when x is vertical
            x = heading - (heading @ z) * z
            if np.linalg.norm(x) > 1e-6:
                break
        x /= np.linalg.norm(x)
        F[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    return _inverse(F)


@dataclass
class OdometryPose:
    """One ``~/odom`` message's numbers: the base's pose in odom (4x4), its 6x6 covariance, the
    twist (vx vy vz ωx ωy ωz in the base frame) and its 6x6 covariance ([0, 0] = -1: unknown)."""

    stamp: float
    odom_from_base: np.ndarray
    covariance: np.ndarray
    twist: np.ndarray
    twist_covariance: np.ndarray

    @property
    def twist_known(self) -> bool:
        return bool(self.twist_covariance[0, 0] != UNKNOWN_TWIST)


class BaseOdometry:
    """One topic's odometry of the base from the path's camera poses (module docstring)."""

    def __init__(self, base_from_camera: np.ndarray) -> None:
        self.camera_from_base = _inverse(np.asarray(base_from_camera, np.float64))
        self.lever2 = float(self.camera_from_base[:3, 3] @ self.camera_from_base[:3, 3])
        self.odom_from_path: np.ndarray | None = None
        self.travelled = 0.0  # the base's distance on this topic, in its units
        self.absorbed = np.zeros(2)  # the jumps absorbed: translation², angle²
        self._last: tuple[OdometryPose, np.ndarray] | None = None  # and its local variances

    def add(self, pose: PathPose) -> OdometryPose:
        """The base's odometry at the path's ``pose`` (the topic's poses in stamp order)."""
        path_from_base = pose.odom_from_camera @ self.camera_from_base
        if self.odom_from_path is None:
            self.odom_from_path = odom_from_first(path_from_base, pose.ground_up)
        elif pose.jump is not None:
            self.odom_from_path = self.odom_from_path @ pose.jump
            self.absorbed += [float(pose.jump[:3, 3] @ pose.jump[:3, 3]),
                              rotation_angle(pose.jump[:3, :3]) ** 2]
        T = self.odom_from_path @ path_from_base
        local = np.maximum([pose.position_var + self.lever2 * pose.rotation_var,
                            pose.rotation_var], MIN_VARIANCE)
        twist, twist_cov = np.zeros(6), np.zeros((6, 6))
        twist_cov[0, 0] = UNKNOWN_TWIST
        if self._last is not None:
            last, last_local = self._last
            self.travelled += float(np.linalg.norm(T[:3, 3] - last.odom_from_base[:3, 3]))
            dt = pose.stamp - last.stamp
            if dt > 0:
                twist, twist_cov = _twist(last.odom_from_base, T, dt, last_local + local)
        position_var = local[0] + self.absorbed[0] + (DRIFT_PER_DISTANCE * self.travelled) ** 2
        out = OdometryPose(pose.stamp, T, np.diag([position_var] * 3
                                                  + [local[1] + self.absorbed[1]] * 3),
                           twist, twist_cov)
        self._last = (out, local)
        return out


def _twist(before: np.ndarray, after: np.ndarray, dt: float,
           variances: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(twist, its covariance) of the base moving from ``before`` to ``after`` (odom_from_base)
    in ``dt`` seconds, ``variances`` the two poses' summed (position, rotation) variances."""
    v = before[:3, :3].T @ (after[:3, 3] - before[:3, 3]) / dt
    w = rotation_vector(before[:3, :3].T @ after[:3, :3]) / dt
    return np.concatenate([v, w]), np.diag([variances[0]] * 3 + [variances[1]] * 3) / dt**2
