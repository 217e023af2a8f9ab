"""sensor_msgs/CameraInfo <-> :class:`sfm_ttr_ros.core.frames.Intrinsics`, and the CameraInfo
published beside an image.

Reading is duck-typed (rclpy and rosbags messages); building (:func:`camera_info_msg`) makes
rclpy's class by default or a rosbags type store's (:mod:`msg_adapters.classes`).

Beside each depth image the node publishes a CameraInfo (image_transport's camera-publisher
convention): :func:`camera_info_for` republishes the CameraInfo the camera sent, with the
image's header, scaled by :func:`scale_camera_info` only when the image has another size;
:func:`intrinsics_to_camera_info` describes bare intrinsics (the node's fallback).
:func:`projection_of` reads the pinhole a consumer such as depth_image_proc uses (P).
A distorted camera's lens (D != 0) is read by :func:`camera_info_distortion` into the core's
:class:`~sfm_ttr_ros.core.undistort.Distortion`; :func:`rectified_camera_info` describes its
rectified images (D = 0)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from msg_adapters.classes import MessageClasses, empty_header, rclpy_classes
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Intrinsics
from sfm_ttr_ros.core.undistort import Distortion

if TYPE_CHECKING:
    from sensor_msgs.msg import CameraInfo
    from std_msgs.msg import Header


class CameraInfoError(InputError):
    """A sensor_msgs/CameraInfo that does not describe a usable pinhole camera."""


class UncalibratedCameraInfo(CameraInfoError):
    """A CameraInfo whose matrix is all zero: an uncalibrated camera's driver (REP 104: "K = 0
    means uncalibrated"), not a broken message."""


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
        raise UncalibratedCameraInfo(f"CameraInfo {what} is all zero: camera not "
                                     f"calibrated{hint}")
    fx, fy, cx, cy = float(M[0, 0]), float(M[1, 1]), float(M[0, 2]), float(M[1, 2])
    x0, y0, width, height, bx, by = _roi_and_binning(msg)
    cx, cy = cx - x0, cy - y0
    if bx > 1 or by > 1:
        fx, cx, fy, cy = fx / bx, cx / bx, fy / by, cy / by
        width, height = width // bx, height // by
    try:
        return Intrinsics(fx, fy, cx, cy, width, height)
    except InputError as exc:
        raise CameraInfoError(f"CameraInfo {what}: {exc}") from exc


def camera_info_distortion(msg) -> Distortion | None:
    """The lens distortion of the images that come with ``msg`` (a CameraInfo), or None when D
    is empty or all zero (a pinhole camera, or images already rectified). K and P are those of
    the images as received: ROI and binning applied as in :func:`camera_info_to_intrinsics`
    (the distortion acts on normalised coordinates, which neither changes). Raises
    :class:`CameraInfoError` for non-finite coefficients."""
    D = np.asarray(msg.d, dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(D)):
        raise CameraInfoError(f"CameraInfo D has non-finite values: {D.tolist()}")
    if not np.any(D):
        return None
    K = _matrix(msg.k, 3, 3, "K").copy()
    P = _matrix(msg.p, 3, 4, "P").copy()
    p_set = bool(np.any(P))
    x0, y0, width, height, bx, by = _roi_and_binning(msg)
    for M in (K, P):
        M[0, 2] -= x0
        M[1, 2] -= y0
        M[0] /= bx
        M[1] /= by
    if not p_set:  # unset: stays all zero (the ROI shift above made its cx, cy nonzero)
        P[:] = 0.0
    return Distortion(str(msg.distortion_model), tuple(D.tolist()), tuple(K.ravel().tolist()),
                      tuple(_matrix(msg.r, 3, 3, "R").ravel().tolist()),
                      tuple(P.ravel().tolist()), width // bx, height // by)


def rectified_camera_info(distortion: Distortion, K: np.ndarray, header=None):  # noqa: N803
    """The CameraInfo of the rectified images of the camera ``distortion`` describes, whose
    intrinsics are ``K`` (3x3): D all zero (``plumb_bob``), R the identity (the rectified image
    is already rotated by R), P the camera's when set (its Tx, Ty kept), else [K | 0]."""
    P = distortion.matrix("P")
    if not np.any(P):
        P = np.hstack([np.asarray(K, np.float64), np.zeros((3, 1))])
    return camera_info_msg(distortion.width, distortion.height, K, P, D=np.zeros(5),
                           header=header)


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
    intr: Intrinsics, header: Header | None = None, frame_id: str | None = None, *,
    size: tuple[int, int] | None = None
) -> CameraInfo:
    """A CameraInfo for an undistorted pinhole camera: K from ``intr``, P = [K | 0], R = I,
    D empty, distortion_model ``plumb_bob``. ``frame_id`` (when given) overrides the header's.
    ``size`` = (width, height), when given, is the image size written (default ``intr``'s):
    fx, fy, cx, cy stay as they are (the node's fallback intrinsics are in the pixels of
    whatever image they stand for)."""
    c = rclpy_classes()
    if frame_id is not None:  # a new Header: never modify the caller's
        stamp = c.time() if header is None else header.stamp
        header = c.header(stamp=stamp, frame_id=str(frame_id))
    K = intr.K
    width, height = (intr.width, intr.height) if size is None else size
    return camera_info_msg(width, height, K, np.hstack([K, np.zeros((3, 1))]),
                           header=header, classes=c)


def _roi_and_binning(msg) -> tuple[float, float, int, int, int, int]:
    """(x offset, y offset, width, height, binning x, binning y) of ``msg``: its ROI when one
    is set (else no offset and the full size), binning factors at least 1 (image_geometry's
    rule, REP 104: the ROI first, then the binning)."""
    roi = msg.roi
    if int(roi.width) > 0 and int(roi.height) > 0:
        x0, y0, w, h = float(roi.x_offset), float(roi.y_offset), int(roi.width), int(roi.height)
    else:
        x0, y0, w, h = 0.0, 0.0, int(msg.width), int(msg.height)
    return x0, y0, w, h, max(int(msg.binning_x), 1), max(int(msg.binning_y), 1)


def _effective_size(msg) -> tuple[int, int]:
    """The size of the images ``msg`` describes: its ROI when one is set, then divided by the
    binning factors (image_geometry's rule, REP 104)."""
    _, _, w, h, bx, by = _roi_and_binning(msg)
    return w // bx, h // by


def scale_camera_info(msg, width: int, height: int, header=None, *,
                      classes: MessageClasses | None = None):
    """A CameraInfo of the camera ``msg`` describes for its image resized to ``width`` x
    ``height``: ROI and binning applied to K and P first (cx, cy shifted by the ROI offset, then
    rows divided by the binning; the result has neither), then the first two rows of K and P
    multiplied by width / w and height / h (P's Tx, Ty included), as the core's
    ``Intrinsics.scaled``. D, R and the distortion model are kept. ``header`` (default
    ``msg``'s) is the new message's."""
    width, height = int(width), int(height)
    if width <= 0 or height <= 0:
        raise CameraInfoError(f"cannot scale a CameraInfo to {width}x{height}")
    x0, y0, _, _, bx, by = _roi_and_binning(msg)
    w, h = _effective_size(msg)
    if w <= 0 or h <= 0:
        raise CameraInfoError(f"CameraInfo describes a {w}x{h} image: nothing to scale")
    K = _matrix(msg.k, 3, 3, "K").copy()
    P = _matrix(msg.p, 3, 4, "P").copy()
    for M in (K, P):
        M[0, 2] -= x0
        M[1, 2] -= y0
    sx, sy = width / w / bx, height / h / by
    for M in (K, P):
        M[0] *= sx
        M[1] *= sy
    return camera_info_msg(width, height, K, P, D=np.asarray(msg.d, np.float64).reshape(-1),
                           R=_matrix(msg.r, 3, 3, "R"),
                           header=msg.header if header is None else header,
                           distortion_model=str(msg.distortion_model), classes=classes)


def camera_info_for(source, width: int, height: int, header, *,
                    classes: MessageClasses | None = None):
    """The CameraInfo to publish beside a ``width`` x ``height`` image of the camera that
    ``source`` (a CameraInfo received from it) describes, with the image's ``header``.

    When ``source`` describes images of that size (after its ROI and binning), every field is
    kept as received (K, D, R, P, distortion model, binning, ROI) and only the header changes;
    otherwise it is :func:`scale_camera_info` to that size."""
    c = classes or rclpy_classes()
    if _effective_size(source) != (int(width), int(height)):
        return scale_camera_info(source, width, height, header, classes=c)
    roi = source.roi
    return c.camera_info(
        header=header, height=int(source.height), width=int(source.width),
        distortion_model=str(source.distortion_model),
        d=c.doubles_field(np.asarray(source.d, np.float64)),
        k=c.doubles_field(_matrix(source.k, 3, 3, "K")),
        r=c.doubles_field(_matrix(source.r, 3, 3, "R")),
        p=c.doubles_field(_matrix(source.p, 3, 4, "P")),
        binning_x=int(source.binning_x), binning_y=int(source.binning_y),
        roi=c.region_of_interest(x_offset=int(roi.x_offset), y_offset=int(roi.y_offset),
                                 height=int(roi.height), width=int(roi.width),
                                 do_rectify=bool(roi.do_rectify)))


def projection_of(msg) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of the pinhole a depth image with CameraInfo ``msg`` is back-projected
    with, as depth_image_proc does (image_geometry's ``fx()``, ``cx()`` read P); from K when P
    is all zero (uncalibrated P). Raises :class:`CameraInfoError` when neither gives positive
    finite focal lengths. ROI and binning are those of ``msg`` (a CameraInfo published beside
    an image has none unless it was received so)."""
    P = _matrix(msg.p, 3, 4, "P")
    M = P if np.any(P) else _matrix(msg.k, 3, 3, "K")
    fx, fy, cx, cy = float(M[0, 0]), float(M[1, 1]), float(M[0, 2]), float(M[1, 2])
    if not all(np.isfinite((fx, fy, cx, cy))) or fx <= 0 or fy <= 0:
        raise CameraInfoError(f"CameraInfo has no usable pinhole: fx={fx}, fy={fy}, cx={cx}, "
                              f"cy={cy}")
    return fx, fy, cx, cy
