"""A KITTI raw drive (+ the improved ground truth) as a rosbag2: :func:`kitti_to_bag`.

KITTI topics (kitti2bag's names, camera 02 = left colour camera):

* ``/kitti/camera_color_left/image_raw``: sensor_msgs/Image ``rgb8``, one per frame, stamped
  with ``image_02/timestamps.txt`` (nanoseconds exactly as written in the file); with
  ``compressed`` instead ``/kitti/camera_color_left/image_raw/compressed``:
  sensor_msgs/CompressedImage, JPEG at compressed_image_transport's default quality 95, format
  ``"rgb8; jpeg compressed bgr8"`` (the image_transport convention of recorded robot bags;
  :mod:`msg_adapters.compressed`);
* ``/kitti/camera_color_left/camera_info``: sensor_msgs/CameraInfo with the image's stamp,
  from ``P_rect_02`` / ``S_rect_02`` of ``calib_cam_to_cam.txt``
  (see :func:`camera_info_from_calib`);
* ``/kitti/camera_color_left/depth_gt`` (with ground truth): the improved ground truth as REP 118
  ``32FC1`` metres, NaN = no measurement, with the image's stamp, only for the frames that have
  a ground-truth PNG (frames without one are still written as image + camera_info).

* ``/kitti/odom``: nav_msgs/Odometry with the image's stamp, frame_id ``odom``, when the drive
  has poses (:func:`drive_odometry`): from ``<drive>/poses.txt`` (a generated drive, an image
  folder with poses) the camera's pose, child_frame_id = the camera's frame; from real KITTI's
  ``oxts/`` the IMU's pose as the KITTI devkit converts GPS/IMU (Mercator with the first frame's
  latitude scale, relative to the first frame: :mod:`sfm_ttr_ros.data.poses`), child_frame_id
  ``imu_link`` (kitti2bag's IMU frame): its positions give the distance travelled, its
  orientation is the IMU's, not the camera's. Metres. A drive with neither has no odometry
  (:attr:`ConvertResult.odometry` is empty and ``kitti-to-bag`` says so).

The image topics share frame_id ``camera_color_left``. In the bag, each message's log time is
its header stamp, and per frame camera_info is written first, then the image, then the GT, then
the odometry. Bag format and storages: :mod:`sfm_ttr_ros.ros.bag`.
"""

from __future__ import annotations

import calendar
import time
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np

from msg_adapters.camera_info import camera_info_msg
from msg_adapters.classes import make_header
from msg_adapters.compressed import rgb8_to_compressed
from msg_adapters.odometry import ODOMETRY_MSGTYPE, odometry_msg
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.data.kitti import KittiDrive, kitti_intrinsics, parse_kitti_timestamp
from sfm_ttr_ros.data.poses import POSES_FILE
from sfm_ttr_ros.ros.bag import (
    CAMERA_INFO_MSGTYPE,
    IMAGE_MSGTYPE,
    BagRecorder,
    ProgressBar,
    depth_msg,
    make_image_msg,
    message_classes,
    storage_plugin,
    typestore,
)

# kitti2bag's frame ids / topic namespaces per KITTI camera.
KITTI_CAMERA_NAMES = {"02": "camera_color_left", "03": "camera_color_right"}
KITTI_NAMESPACE = "/kitti"
IMAGE_TOPIC = "/kitti/camera_color_left/image_raw"
CAMERA_INFO_TOPIC = "/kitti/camera_color_left/camera_info"
DEPTH_GT_TOPIC = "/kitti/camera_color_left/depth_gt"
COMPRESSED_IMAGE_MSGTYPE = "sensor_msgs/msg/CompressedImage"
COMPRESSED_SUFFIX = "/compressed"  # image_transport's (sfm_ttr_ros.ros.names.compressed_topic)
ODOM_TOPIC = "/kitti/odom"
ODOM_FRAME = "odom"
IMU_FRAME = "imu_link"  # kitti2bag's frame of the OXTS IMU


def kitti_timestamp_ns(text: str) -> int:
    """``YYYY-MM-DD HH:MM:SS.fffffffff`` (UTC) -> integer nanoseconds since the epoch, exactly
    (a float of seconds since 1970 cannot hold nanoseconds)."""
    parse_kitti_timestamp(text)  # validates, with the reader's error message
    text = text.strip()
    head, _, frac = text.partition(".")
    secs = calendar.timegm(datetime.strptime(head, "%Y-%m-%d %H:%M:%S").timetuple())
    return secs * 1_000_000_000 + int(frac.ljust(9, "0") if frac else 0)


def camera_info_from_calib(calib: dict, cam: str, stamp_ns: int, frame_id: str):
    """A rosbags sensor_msgs/CameraInfo for the rectified images of KITTI camera ``cam``.

    The ``_sync`` images are already rectified, so the message describes a distortion-free
    pinhole camera: width x height = ``S_rect_<cam>``; P = ``P_rect_<cam>`` as it is (including
    its 4th column, the offset ``fx * tx`` to camera 00, as kitti2bag writes it); K = the left
    3x3 block of P, i.e. fx, fy, cx, cy of P_rect; D = five zeros with ``plumb_bob``; R = identity
    (not ``R_rect_00``: R is the rotation that rectifies the *raw* image, and applying R_rect to
    an already rectified image would rotate it a second time; image_geometry with D = 0, R = I,
    K = P[:3, :3] leaves the image as it is).
    """
    intr = kitti_intrinsics(calib, cam)  # validates P_rect and S_rect
    P = np.asarray(calib[f"P_rect_{cam}"], dtype=np.float64).reshape(3, 4)
    K = P[:, :3].copy()
    K[0, 1] = 0.0  # P_rect has no skew; keep K a clean pinhole matrix
    c = message_classes()
    return camera_info_msg(intr.width, intr.height, K, P, D=np.zeros(5), R=np.eye(3),
                           header=make_header(stamp_ns, frame_id, c), classes=c)


@dataclass
class ConvertResult:
    path: Path
    storage: str
    drive: str
    frames: int
    gt_frames: int
    counts: dict[str, int]
    width: int
    height: int
    start_ns: int
    end_ns: int
    seconds: float
    odometry: str = ""  # where /kitti/odom came from: "poses.txt", "oxts", or "" (none)


@dataclass(frozen=True)
class DriveOdometry:
    """The poses written on :data:`ODOM_TOPIC`: ``source`` ("poses.txt", "oxts" or "" = none),
    the child frame they are the pose of, and each frame's 4x4 pose by frame name."""

    source: str = ""
    child_frame_id: str = ""
    poses: dict = field(default_factory=dict)

    def pose(self, name: str) -> np.ndarray | None:
        return None if not self.source else self.poses[name]


def drive_odometry(kd: KittiDrive, camera_frame: str) -> DriveOdometry:
    """The drive's poses (:meth:`KittiDrive.poses`): ``poses.txt``'s for the camera
    ``camera_frame``, real KITTI's OXTS for the IMU, else none."""
    source, poses = kd.poses()
    if poses is None:
        return DriveOdometry()
    child = camera_frame if source == POSES_FILE else IMU_FRAME
    return DriveOdometry(source, child, dict(zip(kd.frame_names, poses, strict=True)))


def _drive_stamps_ns(drive) -> list[int]:
    """Per frame of a :class:`~sfm_ttr_ros.data.kitti.KittiDrive`, its stamp in integer ns: read
    from ``timestamps.txt`` (line = frame number) as KittiDrive does, or its 10 Hz fallback."""
    if not drive.stamps_from_file:
        return [round(s * 1e9) for s in drive.stamps]
    ts_path = drive.drive_dir / f"image_{drive.camera}" / "timestamps.txt"
    lines = [ln for ln in ts_path.read_text().splitlines() if ln.strip()]
    out = []
    for name in drive.frame_names:  # KittiDrive already checked every frame has a line
        out.append(kitti_timestamp_ns(lines[int(name)]))
    return out


def kitti_to_bag(
    raw_root: str | Path,
    drive: str,
    out: str | Path,
    gt_root: str | Path | None = None,
    storage: str = "mcap",
    *,
    camera: str = "02",
    start: int = 0,
    max_frames: int = 0,
    progress: bool = False,
    compressed: bool = False,
) -> ConvertResult:
    """Convert a KITTI raw drive (``raw_root/<date>/<drive>``) into the rosbag2 folder ``out``.

    Topics and conventions: see the module docstring. ``gt_root`` (the depth benchmark root,
    ``{train,val}/<drive>/proj_depth/groundtruth``) adds the improved ground truth; it is an
    error when that root has no ground truth for the drive. ``start`` / ``max_frames`` (0 = all)
    select a range of frames. ``compressed`` writes the images as JPEG CompressedImages on
    ``.../image_raw/compressed``. Frames are read and written one at a time. Raises
    :class:`InputError` for a missing drive / calibration / GT, an image whose size is not
    ``S_rect``, or an existing ``out``; a failed conversion leaves no partial bag behind.
    """
    kd, stop = _open_drive(raw_root, drive, gt_root, storage, camera, start, max_frames)
    stamps = _drive_stamps_ns(kd)
    topics = _DriveTopics.of(camera, compressed)
    odometry = drive_odometry(kd, topics.frame_id)
    t0 = time.perf_counter()
    gt_frames = 0
    bar = ProgressBar(stop - start, f"kitti-to-bag {drive}", enabled=progress)
    rec = BagRecorder(out, storage)
    try:
        rec.add_topic(topics.image, topics.image_type)
        rec.add_topic(topics.info, CAMERA_INFO_MSGTYPE)
        if kd.gt_dir is not None:
            rec.add_topic(topics.gt, IMAGE_MSGTYPE)
        if odometry.source:
            rec.add_topic(ODOM_TOPIC, ODOMETRY_MSGTYPE)
        for k, i in enumerate(range(start, stop)):
            gt_frames += _write_frame(rec, kd, i, stamps[i], topics)
            pose = odometry.pose(kd.frame_names[i])
            if pose is not None:
                rec.write(ODOM_TOPIC, odometry_msg(stamps[i], ODOM_FRAME,
                                                   odometry.child_frame_id, pose, typestore()))
            bar.update(k + 1, f"GT {gt_frames}")
    except BaseException:
        rec.abort()
        bar.close()
        raise
    rec.close()
    bar.close()
    intr = kd.intrinsics
    return ConvertResult(
        path=Path(out), storage=rec.storage, drive=drive, frames=stop - start,
        gt_frames=gt_frames, counts=dict(rec.counts), width=intr.width, height=intr.height,
        start_ns=stamps[start], end_ns=stamps[stop - 1], seconds=time.perf_counter() - t0,
        odometry=odometry.source)


def _open_drive(raw_root: str | Path, drive: str, gt_root: str | Path | None, storage: str,
                camera: str, start: int, max_frames: int) -> tuple[KittiDrive, int]:
    """The checked drive and the end (exclusive) of the frames selected from ``start``."""
    if camera not in KITTI_CAMERA_NAMES:
        raise InputError(f"camera must be one of {', '.join(KITTI_CAMERA_NAMES)} (colour), "
                         f"got {camera!r}")
    storage_plugin(storage)
    if start < 0 or max_frames < 0:
        raise InputError(f"start and max_frames must be >= 0, got {start}, {max_frames}")
    kd = KittiDrive(raw_root, drive, gt_root=gt_root, camera=camera)
    if gt_root is not None and kd.gt_dir is None:
        raise InputError(f"no ground truth for {drive} under {gt_root}: expected "
                         f"{gt_root}/{{train,val}}/{drive}/proj_depth/groundtruth/image_{camera}")
    stop = len(kd) if max_frames == 0 else min(len(kd), start + max_frames)
    if start >= stop:
        raise InputError(f"no frames selected: start={start}, drive has {len(kd)} frames")
    return kd, stop


@dataclass(frozen=True)
class _DriveTopics:
    """One camera's topics in the bag (kitti2bag's names), its image type and frame id."""

    image: str
    info: str
    gt: str
    image_type: str
    frame_id: str
    camera: str
    compressed: bool

    @classmethod
    def of(cls, camera: str, compressed: bool) -> _DriveTopics:
        name = KITTI_CAMERA_NAMES[camera]
        ns = f"{KITTI_NAMESPACE}/{name}"
        image, image_type = f"{ns}/image_raw", IMAGE_MSGTYPE
        if compressed:
            image, image_type = image + COMPRESSED_SUFFIX, COMPRESSED_IMAGE_MSGTYPE
        return cls(image, f"{ns}/camera_info", f"{ns}/depth_gt", image_type, name, camera,
                   compressed)


def _write_frame(rec: BagRecorder, kd: KittiDrive, i: int, stamp: int,
                 topics: _DriveTopics) -> bool:
    """Frame ``i``'s camera_info, image and (where it has one) GT; True when GT was written."""
    intr, frame_id = kd.intrinsics, topics.frame_id
    rgb = kd.load_image(i)
    if rgb.shape[:2] != (intr.height, intr.width):
        raise InputError(
            f"{kd.image_path(i)} is {rgb.shape[1]}x{rgb.shape[0]} but S_rect_{topics.camera} "
            f"of {kd.calib_path} says {intr.width}x{intr.height}")
    rec.write(topics.info, camera_info_from_calib(kd.calib, topics.camera, stamp, frame_id))
    if topics.compressed:
        c = message_classes()
        rec.write(topics.image, rgb8_to_compressed(
            rgb, "jpeg", make_header(stamp, frame_id, c), classes=c))
    else:
        rec.write(topics.image, make_image_msg(rgb, "rgb8", stamp, frame_id))
    gt = kd.load_gt(i)
    if gt is None:
        return False
    if gt.shape != rgb.shape[:2]:
        raise InputError(f"ground truth {kd.gt_path(i)} is {gt.shape[1]}x"
                         f"{gt.shape[0]}, its image {rgb.shape[1]}x{rgb.shape[0]}")
    rec.write(topics.gt, depth_msg(gt, stamp, frame_id))
    return True


__all__ = [
    "CAMERA_INFO_TOPIC", "COMPRESSED_IMAGE_MSGTYPE", "DEPTH_GT_TOPIC", "IMAGE_TOPIC",
    "KITTI_CAMERA_NAMES", "KITTI_NAMESPACE", "ODOM_TOPIC",
    "ConvertResult", "DriveOdometry", "camera_info_from_calib", "drive_odometry",
    "kitti_timestamp_ns", "kitti_to_bag",
]
