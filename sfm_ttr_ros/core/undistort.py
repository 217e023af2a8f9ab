"""Undistortion of a distorted camera's images, so that every later stage sees a pinhole camera.

The SfM (a PINHOLE camera with fixed intrinsics) and the depth network both assume a pinhole
image. A camera whose description carries lens distortion (a CameraInfo with D != 0, REP 104)
has its frames *rectified* first, as image_proc's ``image_rect`` would be:
``cv2.initUndistortRectifyMap(K, D, R, K')`` (``cv2.fisheye``'s for ``equidistant``) computed
once per distinct :class:`Distortion` (:class:`RectifierCache`), then one ``cv2.remap`` per
frame. The rectified image's intrinsics ``K'`` (:func:`rectified_K`) are P's left 3x3 when P
is set (image_geometry's rectification: the image is then the very ``image_rect`` a ROS user
gets from image_proc, and P is what its consumers read), else the matrix that keeps only
valid pixels (``getOptimalNewCameraMatrix`` with alpha 0; ``balance`` 0 for the fisheye
model): no black border, whose fixed edges would give SfM false matches and the network a
frame it never saw.

The lens models are ROS's (sensor_msgs/distortion_models.hpp): ``plumb_bob`` (k1 k2 p1 p2 k3),
``rational_polynomial`` (k1 k2 p1 p2 k3 k4 k5 k6), both OpenCV's standard model, and
``equidistant`` (k1..k4, OpenCV's fisheye model). Any other is refused
(:class:`UnknownDistortionModel`).
"""

from __future__ import annotations

import collections
import threading
from dataclasses import dataclass

import cv2
import numpy as np

from sfm_ttr_ros.core.errors import InputError

STANDARD_MODELS = ("plumb_bob", "rational_polynomial")  # OpenCV's standard (Brown) model
FISHEYE_MODEL = "equidistant"  # OpenCV's fisheye (Kannala-Brandt) model
KNOWN_MODELS = (*STANDARD_MODELS, FISHEYE_MODEL)
_STANDARD_SIZES = (4, 5, 8, 12, 14)  # the coefficient counts cv2's standard model accepts


class UnknownDistortionModel(InputError):
    """A distortion model this package cannot undistort (not one of :data:`KNOWN_MODELS`)."""


@dataclass(frozen=True)
class Distortion:
    """A distorted camera as its description gives it: ``model`` and ``coefficients`` (D),
    ``K`` (3x3) and ``R`` (3x3), ``P`` (3x4, all zero when unset), row-major, for images of
    ``width`` x ``height`` pixels. Hashable: the key of :class:`RectifierCache`."""

    model: str
    coefficients: tuple[float, ...]
    K: tuple[float, ...]  # noqa: N815 - the usual names of the matrices
    R: tuple[float, ...]  # noqa: N815
    P: tuple[float, ...]  # noqa: N815
    width: int
    height: int

    def matrix(self, name: str) -> np.ndarray:
        """``K``, ``R`` or ``P`` as an array."""
        values = np.asarray(getattr(self, name), dtype=np.float64)
        return values.reshape(3, 4) if name == "P" else values.reshape(3, 3)

    def check(self) -> None:
        """Raise :class:`UnknownDistortionModel` for a model not in :data:`KNOWN_MODELS`,
        :class:`InputError` for coefficients the model cannot take."""
        n = len(self.coefficients)
        if self.model not in KNOWN_MODELS:
            raise UnknownDistortionModel(f"distortion model {self.model!r} cannot be "
                                         f"undistorted (known: {', '.join(KNOWN_MODELS)})")
        if self.model == FISHEYE_MODEL and n != 4 or (
                self.model in STANDARD_MODELS and n not in _STANDARD_SIZES):
            raise InputError(f"distortion model {self.model!r} with {n} coefficients")
        if not np.all(np.isfinite(self.coefficients)):
            raise InputError(f"distortion coefficients must be finite, got {self.coefficients}")


def rectified_K(distortion: Distortion) -> np.ndarray:  # noqa: N802
    """The intrinsics of the rectified image (module docstring): P's left 3x3 when P is set,
    else the matrix that keeps only valid pixels (alpha / balance 0)."""
    P = distortion.matrix("P")
    if np.any(P[:, :3]):
        return P[:, :3].copy()
    K, R = distortion.matrix("K"), distortion.matrix("R")
    D, size = np.asarray(distortion.coefficients, np.float64), (distortion.width,
                                                                 distortion.height)
    if distortion.model == FISHEYE_MODEL:
        return cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(K, D, size, R,
                                                                      balance=0.0)
    return cv2.getOptimalNewCameraMatrix(K, D, size, 0.0, size)[0]


class Rectifier:
    """The undistortion of one :class:`Distortion`: ``K`` (3x3) of the rectified image, of the
    same size; :meth:`remap` rectifies an image (the maps computed once, here)."""

    def __init__(self, distortion: Distortion):
        distortion.check()
        self.distortion = distortion
        self.size = (int(distortion.width), int(distortion.height))
        self.K = rectified_K(distortion)  # noqa: N806 - the usual name
        K, R = distortion.matrix("K"), distortion.matrix("R")
        D = np.asarray(distortion.coefficients, np.float64)
        build = (cv2.fisheye.initUndistortRectifyMap if distortion.model == FISHEYE_MODEL
                 else cv2.initUndistortRectifyMap)
        self._maps = build(K, D, R, self.K, self.size, cv2.CV_16SC2)  # fixed point: fast remap

    def remap(self, image: np.ndarray) -> np.ndarray:
        """``image`` (``size``) rectified: bilinear, pixels from outside it black."""
        return cv2.remap(image, *self._maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


class RectifierCache:
    """The :class:`Rectifier` of each distinct :class:`Distortion`, built once (the last
    ``keep`` kept); thread-safe. ``built`` counts the rectifiers built."""

    def __init__(self, keep: int = 4):
        self._keep = int(keep)
        self._rectifiers: collections.OrderedDict[Distortion, Rectifier] = (
            collections.OrderedDict())
        self._lock = threading.Lock()
        self.built = 0

    def get(self, distortion: Distortion) -> Rectifier:
        with self._lock:
            rectifier = self._rectifiers.get(distortion)
            if rectifier is None:
                rectifier = self._rectifiers[distortion] = Rectifier(distortion)
                self.built += 1
            self._rectifiers.move_to_end(distortion)
            while len(self._rectifiers) > self._keep:
                self._rectifiers.popitem(last=False)
            return rectifier
