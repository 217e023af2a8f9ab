"""Frames, intrinsics and windows: the data every stage of SfM-TTR passes around.

A *window* is the set of consecutive frames that one SfM reconstruction and one test-time
refinement run over (Sec. 3 of Izquierdo & Civera, CVPR 2023, runs over a whole sequence; the
online node runs it over sliding windows of ``window_size`` frames, ``window_stride`` new ones
between consecutive windows).
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from sfm_ttr_ros.core.errors import InputError


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of an image of ``width`` x ``height`` pixels."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        given = (self.fx, self.fy, self.cx, self.cy)
        try:
            fx, fy, cx, cy = (float(v) for v in given)
            w, h = float(self.width), float(self.height)
        except (TypeError, ValueError) as exc:
            raise InputError(f"intrinsics must be numbers, got fx,fy,cx,cy = {given}, size "
                             f"{self.width!r} x {self.height!r}") from exc
        if not all(math.isfinite(v) for v in (fx, fy, cx, cy)):
            raise InputError(f"intrinsics must be finite, got fx,fy,cx,cy = {given}")
        if fx <= 0 or fy <= 0:
            raise InputError(f"focal lengths must be positive, got fx={fx}, fy={fy}")
        if not (math.isfinite(w) and math.isfinite(h) and w.is_integer() and h.is_integer()
                and w > 0 and h > 0):
            raise InputError(f"image size must be positive whole numbers, got "
                             f"{self.width}x{self.height}")
        w, h = int(w), int(h)
        # Pixel centres at integers: the image spans [-0.5, w - 0.5] x [-0.5, h - 0.5]. A
        # principal point outside it almost always means a K meant for another image size.
        if not (-0.5 <= cx <= w - 0.5 and -0.5 <= cy <= h - 0.5):
            raise InputError(f"principal point (cx, cy) = ({cx:g}, {cy:g}) lies outside the "
                             f"{w}x{h} image: are these intrinsics for another image size?")
        for name, value in (("fx", fx), ("fy", fy), ("cx", cx), ("cy", cy), ("width", w),
                            ("height", h)):
            object.__setattr__(self, name, value)  # plain float / int (numpy scalars, strings)

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the usual name of the matrix
        return np.array(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=np.float64
        )

    @classmethod
    def from_K(cls, K: np.ndarray, width: int, height: int) -> Intrinsics:  # noqa: N802
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise InputError(f"K must be 3x3, got shape {K.shape}")
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), width, height)

    @classmethod
    def from_file(cls, path: str | Path, width: int, height: int) -> Intrinsics:
        """Read a 3x3 K (9 numbers, e.g. ``K.txt``) or ``fx fy cx cy`` from a text file."""
        try:
            vals = np.loadtxt(path, dtype=np.float64).ravel()
        except (OSError, ValueError) as exc:
            raise InputError(f"cannot read intrinsics from {path}: {exc}") from exc
        if vals.size == 9:
            return cls.from_K(vals.reshape(3, 3), width, height)
        if vals.size == 4:
            return cls(*map(float, vals), width, height)
        raise InputError(f"{path}: expected 9 numbers (K) or 4 (fx fy cx cy), got {vals.size}")

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float) -> Intrinsics:
        """Intrinsics assumed for an uncalibrated camera: f = (width / 2) / tan(hfov / 2) for
        both axes (square pixels), the principal point at the image centre."""
        if not 0 < float(hfov_deg) < 180:
            raise InputError(f"a horizontal field of view must be in (0, 180) deg, got "
                             f"{hfov_deg}")
        f = 0.5 * int(width) / math.tan(math.radians(float(hfov_deg)) / 2)
        return cls(f, f, (int(width) - 1) / 2.0, (int(height) - 1) / 2.0, width, height)

    def scaled(self, width: int, height: int) -> Intrinsics:
        """Intrinsics of the same camera with the image resized to ``width`` x ``height``."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(
            self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, int(width), int(height)
        )


@dataclass
class Frame:
    """One RGB image of a sequence. ``image`` is H x W x 3 uint8 RGB."""

    index: int
    image: np.ndarray
    stamp: float = 0.0
    name: str = ""
    header: object = field(default=None, repr=False)  # opaque (e.g. a ROS header), passed through
    # set by the live server (core/stream/live.py) once the frame's depth went out on the live
    # output: the stream then need not predict it again when no window refines it
    # (republish_unrefined)
    served_live: bool = field(default=False, repr=False, compare=False)
    # set by the intrinsics resolver (ros/camera.py) when the frame got the fallback fx, fy:
    # the stream lets the first received intrinsics replace them while it holds the frame
    fallback_intrinsics: bool = field(default=False, repr=False, compare=False)
    # set by the same resolver when the camera is uncalibrated (a CameraInfo with K all zero)
    # and the intrinsics are assumed from a field of view: SfM refines their focal length
    # window after window (core/sfm/self_calibration.py)
    assumed_intrinsics: bool = field(default=False, repr=False, compare=False)
    # opaque, set by the same resolver: where the frame's intrinsics came from (the node
    # publishes the CameraInfo beside its depth from it); passed through like ``header``
    camera: object = field(default=None, repr=False, compare=False)
    # set by the same resolver when the image was undistorted (core/undistort.py): the frame's
    # depth is then of the rectified image, published beside a CameraInfo with D = 0
    rectified: bool = field(default=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not self.name:
            self.name = f"{self.index:010d}"

    @property
    def size(self) -> tuple[int, int]:
        """(width, height)."""
        return int(self.image.shape[1]), int(self.image.shape[0])


def check_rgb_image(image: np.ndarray, what: str = "image") -> np.ndarray:
    """Validate an H x W x 3 uint8 image (grayscale is expanded); return it contiguous."""
    if not isinstance(image, np.ndarray):
        raise InputError(f"{what}: expected a numpy array, got {type(image).__name__}")
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] != 3:
        raise InputError(f"{what}: expected H x W x 3, got shape {image.shape}")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise InputError(f"{what}: zero-size image {image.shape}")
    if image.dtype != np.uint8:
        raise InputError(f"{what}: expected uint8, got {image.dtype}")
    return np.ascontiguousarray(image)


def check_window(frames: Sequence[Frame], intrinsics: Intrinsics) -> None:
    """Raise :class:`InputError` unless ``frames`` is a usable window for ``intrinsics``.

    Grayscale (H x W) images are expanded to RGB in place (``frame.image`` is replaced), so every
    later stage sees H x W x 3 uint8.
    """
    if not isinstance(intrinsics, Intrinsics):
        raise InputError(f"intrinsics must be an Intrinsics, got {type(intrinsics).__name__}")
    if not isinstance(frames, Sequence):
        raise InputError(f"a window must be a sequence (list, tuple) of Frame, got "
                         f"{type(frames).__name__}")
    if len(frames) == 0:
        raise InputError("empty window: no frames given")
    for i, f in enumerate(frames):
        if not isinstance(f, Frame):
            raise InputError(f"window item {i} is a {type(f).__name__}, not a Frame")
        f.image = check_rgb_image(f.image, f"frame {f.name}")
        if f.size != (intrinsics.width, intrinsics.height):
            raise InputError(
                f"frame {f.name} is {f.size[0]}x{f.size[1]} but the intrinsics are for "
                f"{intrinsics.width}x{intrinsics.height}: all frames of a window"
                " must share one size"
            )
    names = [f.name for f in frames]
    if len(set(names)) != len(names):
        raise InputError("frame names in a window must be unique")


def image_digest(image: np.ndarray) -> bytes:
    """Identity of a frame's pixels (a few ms for a full KITTI frame)."""
    h = hashlib.blake2b(digest_size=16)
    h.update(repr((image.shape, image.dtype.str)).encode())
    h.update(np.ascontiguousarray(image).data)
    return h.digest()


def load_rgb(path: str | Path) -> np.ndarray:
    """Read an image file as H x W x 3 uint8 RGB, with a clear error if it cannot be read."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"image file not found: {path}")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read image file {path}: {exc}") from exc
    problem = _truncated(data)
    if problem:
        raise InputError(f"corrupt image file {path}: {problem}")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise InputError(f"cannot decode image file: {path}")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _truncated(data: bytes) -> str:
    """Why a PNG / JPEG file is cut short ("" if it is not, or is another format).

    OpenCV decodes a truncated JPEG silently (the missing part grey) and reports a truncated PNG
    only through libpng's message on stderr; a whole file has its end marker (a JPEG may carry
    more data after it, e.g. a motion photo's video, so the marker is looked for anywhere).
    """
    if data.startswith(b"\x89PNG\r\n\x1a\n") and data.rfind(b"IEND") < 0:
        return "truncated PNG (no IEND chunk)"
    if data.startswith(b"\xff\xd8") and data.rfind(b"\xff\xd9") < 0:
        return "truncated JPEG (no end-of-image marker)"
    return ""


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".ppm", ".tif", ".tiff")


def list_images(folder: str | Path) -> list[Path]:
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"image folder not found: {folder}")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise InputError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in {folder}")
    return files
