"""KITTI raw and depth-benchmark layouts: reading real drives, writing synthetic ones.

Raw drive (camera 02 = left colour)::

    <raw_root>/<date>/calib_cam_to_cam.txt
    <raw_root>/<date>/<date>_drive_XXXX_sync/image_02/data/NNNNNNNNNN.png
    <raw_root>/<date>/<date>_drive_XXXX_sync/image_02/timestamps.txt
    <raw_root>/<date>/<date>_drive_XXXX_sync/image_02/segments.txt   (generated drives with
        segment labels only, not KITTI's: one line ``index label`` per frame)
    <raw_root>/<date>/<date>_drive_XXXX_sync/poses.txt, camera_height.txt   (generated drives
        and image folders with poses, not KITTI's: :mod:`sfm_ttr_ros.data.poses`)
    <raw_root>/<date>/<date>_drive_XXXX_sync/oxts/data/NNNNNNNNNN.txt, oxts/timestamps.txt
        (real KITTI: GPS/IMU, read by :func:`sfm_ttr_ros.data.poses.drive_oxts_poses`)

Improved depth ground truth (KITTI depth benchmark; uint16 PNG, metres x 256, 0 = none; the
first and last 5 frames of every drive have none)::

    <gt_root>/{train,val}/<date>_drive_XXXX_sync/proj_depth/groundtruth/image_02/NNNNNNNNNN.png
"""

from __future__ import annotations

import calendar
import math
import re
import shutil
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path

import cv2
import numpy as np

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Frame, Intrinsics, load_rgb
from sfm_ttr_ros.data.poses import (
    CAMERA_HEIGHT_FILE,
    POSES_FILE,
    drive_oxts_poses,
    read_frame_poses,
    write_camera_height,
    write_poses,
)

KITTI_DEPTH_SCALE = 256.0
CAMERAS = ("00", "01", "02", "03")
# x translation of each rectified camera relative to camera 00 (P_rect_NN[0, 3] / fx in the real
# 2011_09_26 calibration): grey pair 0.54 m apart, colour camera 02 6 cm left of camera 00.
KITTI_CAMERA_TX = {"00": 0.0, "01": -0.5372, "02": 0.0622, "03": -0.4706}
_DRIVE_RE = re.compile(r"^(\d{4}_\d{2}_\d{2})_drive_(\d{4})_sync$")

# ---------------------------------------------------------------------------------------------
# Calibration
# ---------------------------------------------------------------------------------------------


def read_calib_cam_to_cam(path: str | Path) -> dict[str, np.ndarray | str]:
    """Parse a KITTI ``calib_cam_to_cam.txt``: ``key: numbers`` lines -> float64 arrays.

    A value that is not a list of numbers (the real file's ``calib_time: 09-Jan-2012 13:57:47``)
    is kept as its string. Raises :class:`InputError` for a missing or unreadable file or a line
    without a ``key:``.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"KITTI calibration file not found: {path}")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read KITTI calibration file {path}: {exc}") from exc
    calib: dict[str, np.ndarray | str] = {}
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        key, sep, value = line.partition(":")
        key = key.strip()
        if not sep or not key:
            raise InputError(f"{path}:{lineno}: expected 'key: values', got {line!r}")
        try:
            calib[key] = np.array([float(x) for x in value.split()], dtype=np.float64)
        except ValueError:
            calib[key] = value.strip()
    return calib


def kitti_intrinsics(calib: dict[str, np.ndarray | str], cam: str = "02") -> Intrinsics:
    """Rectified intrinsics of camera ``cam`` from ``P_rect_<cam>`` and ``S_rect_<cam>``."""
    P = calib.get(f"P_rect_{cam}")
    S = calib.get(f"S_rect_{cam}")
    if not isinstance(P, np.ndarray) or P.size != 12:
        raise InputError(f"calibration: P_rect_{cam} missing or not 12 numbers")
    if not isinstance(S, np.ndarray) or S.size != 2:
        raise InputError(f"calibration: S_rect_{cam} missing or not 2 numbers (width height)")
    P = P.reshape(3, 4)
    w, h = float(S[0]), float(S[1])
    if not (math.isfinite(w) and math.isfinite(h)) or w <= 0 or h <= 0:
        raise InputError(f"calibration: bad S_rect_{cam} = {S.tolist()}")
    return Intrinsics(
        float(P[0, 0]), float(P[1, 1]), float(P[0, 2]), float(P[1, 2]), round(w), round(h)
    )


def _fmt(values) -> str:
    """KITTI style (``7.215377e+02``) but lossless: shortest round-trip digits, at least 6."""
    return " ".join(
        np.format_float_scientific(float(v), unique=True, min_digits=6, exp_digits=2)
        for v in np.asarray(values, dtype=np.float64).ravel()
    )


def write_calib_cam_to_cam(
    path: str | Path,
    intrinsics: Intrinsics,
    calib_time: str = "09-Jan-2012 13:57:47",
    camera_tx: dict[str, float] | None = None,
) -> None:
    """Write a ``calib_cam_to_cam.txt`` with the same fields as the real KITTI file.

    Every camera 00..03 gets the (already rectified, distortion-free) ``intrinsics``; they differ
    by their x translation (``camera_tx``, default KITTI's) in ``T_NN`` and ``P_rect_NN[0, 3] =
    fx * tx``, like the real stereo rig. Camera 02 carries exactly ``intrinsics``.
    """
    tx = dict(KITTI_CAMERA_TX if camera_tx is None else camera_tx)
    K = intrinsics.K
    size = [intrinsics.width, intrinsics.height]
    lines = [f"calib_time: {calib_time}", f"corner_dist: {_fmt([0.0995])}"]
    for cam in CAMERAS:
        t = float(tx.get(cam, 0.0))
        P = np.hstack([K, np.array([[intrinsics.fx * t], [0.0], [0.0]])])
        lines += [
            f"S_{cam}: {_fmt(size)}",
            f"K_{cam}: {_fmt(K)}",
            f"D_{cam}: {_fmt(np.zeros(5))}",
            f"R_{cam}: {_fmt(np.eye(3))}",
            f"T_{cam}: {_fmt([t, 0.0, 0.0])}",
            f"S_rect_{cam}: {_fmt(size)}",
            f"R_rect_{cam}: {_fmt(np.eye(3))}",
            f"P_rect_{cam}: {_fmt(P)}",
        ]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


# ---------------------------------------------------------------------------------------------
# Timestamps and depth PNGs
# ---------------------------------------------------------------------------------------------

_TS_RE = re.compile(r"^(\d{4}-\d{2}-\d{2} \d{2}:\d{2}:\d{2})(?:\.(\d{1,9}))?$")


def parse_kitti_timestamp(text: str) -> float:
    """``YYYY-MM-DD HH:MM:SS.fffffffff`` (UTC, up to nanoseconds) -> float seconds since epoch."""
    m = _TS_RE.match(text.strip())
    if not m:
        raise InputError(f"bad KITTI timestamp {text!r}: expected 'YYYY-MM-DD HH:MM:SS.fffffffff'")
    try:
        dt = datetime.strptime(m.group(1), "%Y-%m-%d %H:%M:%S")
    except ValueError as exc:
        raise InputError(f"bad KITTI timestamp {text!r}: {exc}") from exc
    ns = int((m.group(2) or "0").ljust(9, "0"))
    return calendar.timegm(dt.timetuple()) + ns * 1e-9


def format_kitti_timestamp(stamp: float) -> str:
    """Float seconds since epoch (UTC) -> ``YYYY-MM-DD HH:MM:SS.fffffffff``."""
    if not math.isfinite(stamp) or stamp < 0:
        raise InputError(f"cannot format timestamp {stamp!r}")
    secs = math.floor(stamp)
    ns = round((stamp - secs) * 1e9)
    if ns >= 1_000_000_000:
        secs, ns = secs + 1, ns - 1_000_000_000
    dt = datetime.fromtimestamp(secs, tz=UTC)
    return f"{dt:%Y-%m-%d %H:%M:%S}.{ns:09d}"


def read_timestamps(path: str | Path) -> list[float]:
    """All timestamps of a KITTI ``timestamps.txt`` (one per line, blank lines ignored)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"timestamps file not found: {path}")
    out = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        if line.strip():
            try:
                out.append(parse_kitti_timestamp(line))
            except InputError as exc:
                raise InputError(f"{path}:{lineno}: {exc}") from exc
    return out


def write_timestamps(path: str | Path, stamps: Sequence[float]) -> None:
    Path(path).write_text("".join(format_kitti_timestamp(float(s)) + "\n" for s in stamps))


SEGMENTS_FILE = "segments.txt"  # beside image_02/data: per-frame labels of a scenario drive


def _check_labels(labels: Sequence[str]) -> None:
    for i, label in enumerate(labels):
        if not isinstance(label, str) or label.split() != [label]:
            raise InputError(f"segment label of frame {i} must be one word, got {label!r}")


def write_segments(path: str | Path, labels: Sequence[str]) -> None:
    """One line ``index label`` per frame (``index`` from 0, like the image names)."""
    _check_labels(labels)
    Path(path).write_text("".join(f"{i} {label}\n" for i, label in enumerate(labels)))


def read_segments(path: str | Path) -> list[str]:
    """The per-frame labels of a ``segments.txt`` (:func:`write_segments`), in frame order;
    every index 0 .. n-1 exactly once."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"segments file not found: {path}")
    labels: dict[int, str] = {}
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        parts = line.split()
        if len(parts) != 2 or not parts[0].isdigit() or int(parts[0]) in labels:
            raise InputError(f"{path}:{lineno}: expected 'index label' with a new index, "
                             f"got {line!r}")
        labels[int(parts[0])] = parts[1]
    if sorted(labels) != list(range(len(labels))):
        raise InputError(f"{path}: frame indices are not 0 .. {len(labels) - 1}")
    return [labels[i] for i in range(len(labels))]


def read_depth_png(path: str | Path, scale: float = KITTI_DEPTH_SCALE) -> np.ndarray:
    """A uint16 depth PNG -> float32 metres (value / ``scale``; 0 stays 0 = no depth).

    KITTI uses ``scale`` 256, the HoloLens ground truth 1000 (millimetres).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"depth PNG not found: {path}")
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise InputError(f"cannot decode depth PNG: {path}")
    if raw.ndim != 2 or raw.dtype not in (np.uint16, np.uint8):
        raise InputError(
            f"{path}: expected a single-channel 16-bit depth PNG, got {raw.dtype} {raw.shape}"
        )
    return raw.astype(np.float32) / np.float32(scale)


def write_depth_png(path: str | Path, depth: np.ndarray, scale: float = KITTI_DEPTH_SCALE) -> None:
    """Float metres -> uint16 PNG of ``round(depth * scale)``; 0 where the depth is <= 0, not
    finite, or too large for 16 bits (``> 65535 / scale`` m)."""
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2:
        raise InputError(f"depth must be H x W, got shape {depth.shape}")
    q = np.round(np.where(np.isfinite(depth), depth, 0.0) * scale)
    q[(q <= 0) | (q > 65535)] = 0
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), q.astype(np.uint16)):
        raise InputError(f"cannot write depth PNG {path}")


def lidar_like_mask(
    height: int, width: int, density: float, rng: np.random.Generator, top_empty: float = 0.3
) -> np.ndarray:
    """A sparse, LiDAR-like sampling mask: evenly spaced scan-line rows below the top
    ``top_empty`` fraction of the image (where a Velodyne sees nothing), with random column
    drop-out, ``density`` of all pixels in total (at most ``1 - top_empty``)."""
    if not 0 < density <= 1:
        raise InputError(f"gt_density must be in (0, 1], got {density}")
    mask = np.zeros((height, width), bool)
    r0 = int(math.ceil(top_empty * height))
    avail = height - r0
    if avail <= 0:
        return mask
    target = density * height * width
    if target >= avail * width:
        mask[r0:] = True
        return mask
    n_rows = min(avail, max(1, math.ceil(target / (0.9 * width))))
    rows = np.unique(np.round(np.linspace(r0, height - 1, n_rows)).astype(int))
    keep = min(1.0, target / (len(rows) * width))
    mask[rows] = rng.random((len(rows), width)) < keep
    return mask


# ---------------------------------------------------------------------------------------------
# Reading a drive
# ---------------------------------------------------------------------------------------------


class KittiDrive:
    """One KITTI raw drive (camera ``02``) with optional improved depth ground truth.

    ``drive`` is the folder name ``<date>_drive_XXXX_sync``; the date is its first 10 characters.
    The ground truth is looked up in ``gt_root/<split>/<drive>/proj_depth/groundtruth/image_02``
    for the given ``split``, else in whichever of ``train`` / ``val`` exists (``gt_dir`` is None
    when neither does). ``stamps`` come from ``image_02/timestamps.txt``; if that file is missing
    they are ``index * 0.1`` s (KITTI's 10 Hz) and ``stamps_from_file`` is False.
    """

    def __init__(
        self,
        raw_root: str | Path,
        drive: str,
        gt_root: str | Path | None = None,
        split: str | None = None,
        camera: str = "02",
    ) -> None:
        self.raw_root = Path(raw_root)
        self.drive = str(drive)
        if len(self.drive) < 10:
            raise InputError(f"bad KITTI drive name {drive!r}: expected <date>_drive_XXXX_sync")
        self.date = self.drive[:10]
        self.camera = camera
        self.drive_dir = self.raw_root / self.date / self.drive
        if not self.drive_dir.is_dir():
            raise InputError(f"KITTI drive folder not found: {self.drive_dir}")
        self.image_dir = self.drive_dir / f"image_{camera}" / "data"
        if not self.image_dir.is_dir():
            raise InputError(f"KITTI image folder not found: {self.image_dir}")
        self.frame_names = sorted(p.stem for p in self.image_dir.glob("*.png"))
        if not self.frame_names:
            raise InputError(f"no PNG images in {self.image_dir}")
        self.calib_path = self.raw_root / self.date / "calib_cam_to_cam.txt"
        self.calib = read_calib_cam_to_cam(self.calib_path)
        try:
            self.intrinsics = kitti_intrinsics(self.calib, camera)
        except InputError as exc:
            raise InputError(f"{self.calib_path}: {exc}") from exc

        ts_path = self.drive_dir / f"image_{camera}" / "timestamps.txt"
        self.stamps_from_file = ts_path.is_file()
        if self.stamps_from_file:
            all_stamps = read_timestamps(ts_path)
            self.stamps = []
            for name in self.frame_names:
                k = int(name) if name.isdigit() else -1
                if not 0 <= k < len(all_stamps):
                    raise InputError(
                        f"{ts_path} has {len(all_stamps)} lines: no timestamp for frame {name}"
                    )
                self.stamps.append(all_stamps[k])
        else:
            self.stamps = [
                (int(n) if n.isdigit() else i) * 0.1 for i, n in enumerate(self.frame_names)
            ]

        self.gt_dir: Path | None = None
        if gt_root is not None:
            gt_root = Path(gt_root)
            if not gt_root.is_dir():
                raise InputError(f"KITTI ground-truth root not found: {gt_root}")
            for sp in [split] if split else ["train", "val"]:
                cand = gt_root / sp / self.drive / "proj_depth" / "groundtruth" / f"image_{camera}"
                if cand.is_dir():
                    self.gt_dir = cand
                    break
            if split and self.gt_dir is None:
                raise InputError(f"no ground truth for {self.drive} in {gt_root / split}")

    def __len__(self) -> int:
        return len(self.frame_names)

    def _check(self, i: int) -> int:
        if not -len(self) <= i < len(self):
            raise InputError(f"frame index {i} out of range for {self.drive} ({len(self)} frames)")
        return i % len(self)

    def image_path(self, i: int) -> Path:
        return self.image_dir / f"{self.frame_names[self._check(i)]}.png"

    def load_image(self, i: int) -> np.ndarray:
        """H x W x 3 uint8 RGB."""
        return load_rgb(self.image_path(i))

    def gt_path(self, i: int) -> Path | None:
        """Ground-truth PNG of frame ``i``, or None if it has none."""
        name = self.frame_names[self._check(i)]
        if self.gt_dir is None:
            return None
        p = self.gt_dir / f"{name}.png"
        return p if p.is_file() else None

    def load_gt(self, i: int) -> np.ndarray | None:
        """Ground-truth depth of frame ``i`` in metres (float32, 0 = none), or None."""
        p = self.gt_path(i)
        return None if p is None else read_depth_png(p, KITTI_DEPTH_SCALE)

    def poses(self) -> tuple[str, np.ndarray | None]:
        """(source, N x 4 x 4 poses per frame): ``"poses.txt"`` (a generated drive's or an
        image folder's camera-to-world, camera 02's), else ``"oxts"`` (real KITTI's IMU, the
        distance travelled), else ``("", None)``."""
        if self.camera == "02":
            poses = read_frame_poses(self.drive_dir / POSES_FILE, len(self))
            if poses is not None:
                return POSES_FILE, poses
        poses = drive_oxts_poses(self.drive_dir, self.frame_names)
        return ("oxts", poses) if poses is not None else ("", None)

    def frames(self, indices: Sequence[int] | None = None) -> list[Frame]:
        idx = range(len(self)) if indices is None else [self._check(i) for i in indices]
        return [
            Frame(index=i, image=self.load_image(i), stamp=self.stamps[i], name=self.frame_names[i])
            for i in idx
        ]


# ---------------------------------------------------------------------------------------------
# Writing a (synthetic) drive
# ---------------------------------------------------------------------------------------------


def drive_name(date: str, drive_number: int) -> str:
    return f"{date}_drive_{int(drive_number):04d}_sync"


def write_kitti_drive(
    seq,
    raw_root: str | Path,
    gt_root: str | Path | None = None,
    date: str = "2011_09_26",
    drive_number: int = 1,
    gt_skip_ends: int = 5,
    gt_density: float = 1.0,
    gt_split: str = "val",
    gt_seed: int = 0,
    overwrite: bool = False,
) -> str:
    """Write ``seq`` (a :class:`~sfm_ttr_ros.data.synthetic.SyntheticSequence`, or anything with
    ``images``, ``depths``, ``stamps``, ``intrinsics``) as a KITTI raw drive; return its name.

    Its camera poses, when it has them (``cam_from_world``, a generated drive's, or
    ``cam_to_world``, e.g. an image folder's ``poses.txt``), go to ``<drive>/poses.txt`` (4x4
    camera-to-world per frame, :mod:`sfm_ttr_ros.data.poses`), and its camera height above the
    road (``params.camera_height`` of a generated drive) to ``<drive>/camera_height.txt``.

    Images go to ``image_02/data`` as RGB PNGs, stamps to ``image_02/timestamps.txt``, the
    intrinsics to ``<raw_root>/<date>/calib_cam_to_cam.txt`` (an existing calibration for that
    date must have the same camera-02 intrinsics). With ``gt_root``, depth ground truth goes to
    ``<gt_root>/<gt_split>/<drive>/proj_depth/groundtruth/image_02`` for all but the first and
    last ``gt_skip_ends`` frames (like KITTI): dense for ``gt_density`` 1, else sparse LiDAR-like
    (:func:`lidar_like_mask`, seeded by ``gt_seed`` and the frame index). A sequence with
    per-frame ``labels`` (a scenario drive) also gets ``image_02/segments.txt``
    (:func:`write_segments`). A ``None`` depth (a frame without ground truth) writes no GT PNG.
    """
    labels = _checked_drive(seq, gt_root, date, gt_skip_ends, gt_density)
    intr: Intrinsics = seq.intrinsics
    name = drive_name(date, drive_number)
    date_dir = Path(raw_root) / date
    drive_dir = date_dir / name
    img_dir = drive_dir / "image_02" / "data"
    gt_dir = None
    if gt_root is not None:
        gt_dir = Path(gt_root) / gt_split / name / "proj_depth" / "groundtruth" / "image_02"
    if img_dir.is_dir() and any(img_dir.iterdir()):
        if not overwrite:
            raise InputError(f"drive folder already holds images: {img_dir} (overwrite=False)")
        shutil.rmtree(img_dir)
        if gt_dir is not None and gt_dir.is_dir():
            shutil.rmtree(gt_dir)
    _write_date_calibration(date_dir / "calib_cam_to_cam.txt", intr)
    _write_drive_images(img_dir, seq.images, intr)
    write_timestamps(drive_dir / "image_02" / "timestamps.txt", seq.stamps)
    segments_path = drive_dir / "image_02" / SEGMENTS_FILE
    if labels:
        write_segments(segments_path, labels)
    else:
        segments_path.unlink(missing_ok=True)  # a stale one of an overwritten drive
    if gt_dir is not None:
        _write_drive_gt(gt_dir, seq.depths, range(gt_skip_ends, len(seq.images) - gt_skip_ends),
                        gt_density, gt_seed)
    _write_drive_motion(drive_dir, seq)
    return name


def _write_drive_motion(drive_dir: Path, seq) -> None:
    """``poses.txt`` and ``camera_height.txt`` of the drive when ``seq`` knows them (stale ones
    of an overwritten drive removed otherwise)."""
    poses = getattr(seq, "cam_to_world", None)
    if poses is None and getattr(seq, "cam_from_world", None) is not None:
        poses = [np.linalg.inv(T) for T in seq.cam_from_world]
    if poses is not None and len(poses) != len(seq.images):
        raise InputError(f"{len(poses)} camera poses for {len(seq.images)} images")
    path = drive_dir / POSES_FILE
    if poses is not None:
        write_poses(path, poses)
    else:
        path.unlink(missing_ok=True)
    height = getattr(getattr(seq, "params", None), "camera_height", None)
    path = drive_dir / CAMERA_HEIGHT_FILE
    if height is not None:
        write_camera_height(path, float(height))
    else:
        path.unlink(missing_ok=True)


def _checked_drive(seq, gt_root, date: str, gt_skip_ends: int, gt_density: float) -> list:
    """:func:`write_kitti_drive`'s arguments checked; the sequence's segment labels."""
    if not re.fullmatch(r"\d{4}_\d{2}_\d{2}", date):
        raise InputError(f"date must look like 2011_09_26, got {date!r}")
    if gt_skip_ends < 0:
        raise InputError(f"gt_skip_ends must be >= 0, got {gt_skip_ends}")
    if not 0 < gt_density <= 1:
        raise InputError(f"gt_density must be in (0, 1], got {gt_density}")
    n = len(seq.images)
    if n == 0 or len(seq.stamps) != n or (gt_root is not None and len(seq.depths) != n):
        raise InputError(
            f"sequence needs as many stamps / depths as images "
            f"({n} images, {len(seq.stamps)} stamps, {len(seq.depths)} depths)"
        )
    labels = list(getattr(seq, "labels", None) or [])
    if labels and len(labels) != n:
        raise InputError(f"sequence has {len(labels)} segment labels for {n} images")
    _check_labels(labels)
    return labels


def _write_date_calibration(calib_path: Path, intr: Intrinsics) -> None:
    """The date's ``calib_cam_to_cam.txt``, or a check that the existing one has ``intr`` as
    camera 02 (drives of one date share one calibration)."""
    if calib_path.is_file():
        existing = kitti_intrinsics(read_calib_cam_to_cam(calib_path), "02")
        if existing != intr:
            raise InputError(
                f"{calib_path} exists with other camera-02 intrinsics ({existing}); "
                f"drives of one date share one calibration"
            )
    else:
        write_calib_cam_to_cam(calib_path, intr)


def _write_drive_images(img_dir: Path, images, intr: Intrinsics) -> None:
    """Each RGB image as ``img_dir/<index:010d>.png``, checked against the intrinsics' size."""
    img_dir.mkdir(parents=True, exist_ok=True)
    for i, img in enumerate(images):
        img = np.asarray(img)
        if img.shape[:2] != (intr.height, intr.width) or img.dtype != np.uint8:
            raise InputError(
                f"image {i} is {img.shape} {img.dtype}, intrinsics are for "
                f"{intr.width}x{intr.height} uint8 RGB"
            )
        path = img_dir / f"{i:010d}.png"
        if not cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR)):
            raise InputError(f"cannot write image {path}")


def _write_drive_gt(gt_dir: Path, depths, frames: range, gt_density: float,
                    gt_seed: int) -> None:
    """The improved-GT PNG of each of ``frames`` that has a depth: dense, or sparse LiDAR-like
    for ``gt_density`` < 1 (seeded by ``gt_seed`` and the frame index)."""
    gt_dir.mkdir(parents=True, exist_ok=True)
    for i in frames:
        if depths[i] is None:
            continue
        depth = np.asarray(depths[i], dtype=np.float32)
        if gt_density < 1.0:
            rng = np.random.default_rng([int(gt_seed), i])
            depth = np.where(lidar_like_mask(*depth.shape, gt_density, rng), depth, 0.0)
        write_depth_png(gt_dir / f"{i:010d}.png", depth, KITTI_DEPTH_SCALE)


def parse_drive_name(drive: str) -> tuple[str, int]:
    """``2011_09_26_drive_0001_sync`` -> ``("2011_09_26", 1)``."""
    m = _DRIVE_RE.match(drive)
    if not m:
        raise InputError(f"bad KITTI drive name {drive!r}: expected <date>_drive_XXXX_sync")
    return m.group(1), int(m.group(2))
