"""sensor_msgs/CameraInfo <-> :class:`sfm_ttr_ros.core.frames.Intrinsics`.

Reading is duck-typed (rclpy and rosbags messages); building (:func:`camera_info_msg`) makes
rclpy's class by default or a rosbags type store's (:mod:`msg_adapters.classes`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from msg_adapters.classes import MessageClasses, empty_header, rclpy_classes
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Intrinsics

if TYPE_CHECKING:
    from sensor_msgs.msg import CameraInfo
    from std_msgs.msg import Header


class CameraInfoError(InputError):
    """A sensor_msgs/CameraInfo that does not describe a usable pinhole camera."""


def _matrix(values, rows: int, cols: int, what: str) -> np.ndarray:
    m = np.asarray(values, dtype=np.float64).reshape(-1)
    if m.size != rows * cols:
        raise CameraInfoError(f"CameraInfo {what} must have {rows * cols} values, got {m.size}")
    return m.reshape(rows, cols)


def camera_info_to_intrinsics(msg: CameraInfo, use_projection: bool | None = None) -> Intrinsics:
    """Pinhole intrinsics of the images that come with ``msg``.

    ``use_projection``: ``False`` reads fx, fy, cx, cy from K (the raw, possibly distorted
    image); ``True`` from P (the rectified image, e.g. ``image_rect``); ``None`` (default) picks
    P when P is set (nonzero) and D is empty or all zero - the image is then already rectified,
    as in KITTI's camera_info - and K otherwise.

    Binning and ROI are applied as image_geometry does (REP 104): cx, cy are shifted by the ROI
    offset, then fx, fy, cx, cy and the size are divided by the binning factors. K's skew term
    is ignored (the core's pinhole model has none).
    Raises :class:`CameraInfoError` for a zero image size, a non-finite or all-zero matrix, or
    non-positive focal lengths.
    """
    width, height = int(msg.width), int(msg.height)
    if width <= 0 or height <= 0:
        raise CameraInfoError(f"CameraInfo has zero image size: width={width}, height={height}")
    K = _matrix(msg.k, 3, 3, "K")
    P = _matrix(msg.p, 3, 4, "P")
    D = np.asarray(msg.d, dtype=np.float64).reshape(-1)
    if use_projection is None:
        p_set = bool(np.all(np.isfinite(P)) and np.any(P != 0))
        d_zero = bool(D.size == 0 or (np.all(np.isfinite(D)) and not np.any(D)))
        use_projection = p_set and d_zero
    M, what = (P, "P") if use_projection else (K, "K")
    if not np.all(np.isfinite(M)):
        raise CameraInfoError(f"CameraInfo {what} has non-finite values: {M.ravel().tolist()}")
    if not np.any(M):
        hint = ""
        if not use_projection and np.any(P):
            hint = " (P is set: pass use_projection=True to use it)"
        raise CameraInfoError(f"CameraInfo {what} is all zero: camera not calibrated{hint}")
    fx, fy, cx, cy = float(M[0, 0]), float(M[1, 1]), float(M[0, 2]), float(M[1, 2])
    roi = msg.roi
    if int(roi.width) > 0 and int(roi.height) > 0:
        cx -= float(roi.x_offset)
        cy -= float(roi.y_offset)
        width, height = int(roi.width), int(roi.height)
    bx, by = max(int(msg.binning_x), 1), max(int(msg.binning_y), 1)
    if bx > 1 or by > 1:
        fx, cx, fy, cy = fx / bx, cx / bx, fy / by, cy / by
        width, height = width // bx, height // by
    try:
        return Intrinsics(fx, fy, cx, cy, width, height)
    except InputError as exc:
        raise CameraInfoError(f"CameraInfo {what}: {exc}") from exc


def camera_info_msg(
    width: int,
    height: int,
    K: np.ndarray,
    P: np.ndarray,
    D=(),
    R: np.ndarray | None = None,
    header: Header | None = None,
    *,
    distortion_model: str = "plumb_bob",
    classes: MessageClasses | None = None,
) -> CameraInfo:
    """A CameraInfo of a ``width`` x ``height`` image: 3x3 ``K``, 3x4 ``P``, distortion ``D``
    (``distortion_model``), 3x3 ``R`` (default identity); no binning, no ROI. ``classes``: the
    message classes to build (default rclpy's; a rosbags type store's for bags)."""
    c = classes or rclpy_classes()
    return c.camera_info(
        header=empty_header(c) if header is None else header,
        height=int(height),
        width=int(width),
        distortion_model=str(distortion_model),
        d=c.doubles_field(np.asarray(D, np.float64)),
        k=c.doubles_field(_matrix(K, 3, 3, "K")),
        r=c.doubles_field(np.eye(3) if R is None else _matrix(R, 3, 3, "R")),
        p=c.doubles_field(_matrix(P, 3, 4, "P")),
        binning_x=0,
        binning_y=0,
        roi=c.region_of_interest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )


def intrinsics_to_camera_info(
    intr: Intrinsics, header: Header | None = None, frame_id: str | None = None
) -> CameraInfo:
    """A CameraInfo for an undistorted pinhole camera: K from ``intr``, P = [K | 0], R = I,
    D empty, distortion_model ``plumb_bob``. ``frame_id`` (when given) overrides the header's."""
    c = rclpy_classes()
    if frame_id is not None:  # a new Header: never modify the caller's
        stamp = c.time() if header is None else header.stamp
        header = c.header(stamp=stamp, frame_id=str(frame_id))
    K = intr.K
    return camera_info_msg(intr.width, intr.height, K, np.hstack([K, np.zeros((3, 1))]),
                           header=header, classes=c)
