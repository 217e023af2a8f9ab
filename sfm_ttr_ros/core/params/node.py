"""The refiner node's own settings (camera fallback, transport, outputs, weights files, threads):
ROS-free and self-validating like the core's configs, so that the one parameter schema
(:mod:`sfm_ttr_ros.core.params`) reads their defaults and types from here."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

from sfm_ttr_ros.core.errors import InputError, check_choice
from sfm_ttr_ros.core.stream.base_odometry import DEFAULT_CAMERA_MOUNT, parse_camera_mount

QOS_RELIABILITIES = ("reliable", "best_effort")
IMAGE_TRANSPORTS = ("raw", "compressed")  # sensor_msgs/Image on image, CompressedImage on
# image/compressed (the image_transport convention)
USE_PROJECTION_CHOICES = ("auto", "true", "false")
#: depth not (yet) in metres: on the outputs' relative twins (publish) or not at all (drop)
RELATIVE_DEPTH_CHOICES = ("publish", "drop")
#: The node's outputs (``outputs``): ~/depth (live), ~/depth_colored, ~/depth_refined
#: (windowed), ~/points (the windows' sparse clouds), /diagnostics, ~/cloud (the live depth
#: back-projected), compressed_depth (each published depth image also as image_transport's
#: ``<image>/compressedDepth``) and ~/odom (the camera's path); the last three off by default:
#: not in :data:`DEFAULT_OUTPUTS`.
OUTPUTS = ("depth", "depth_colored", "depth_refined", "points", "diagnostics", "cloud",
           "compressed_depth", "odom")
DEFAULT_OUTPUTS = ("depth", "depth_colored", "depth_refined", "points", "diagnostics")
#: The outputs made from the live depth (any of them starts live serving).
LIVE_OUTPUTS = ("depth", "depth_colored", "cloud")


def parse_outputs(text: str) -> frozenset[str]:
    """``outputs`` ("depth,points", any order, spaces allowed; empty = none) → the set."""
    names = [n.strip() for n in str(text).split(",") if n.strip()]
    unknown = [n for n in names if n not in OUTPUTS]
    if unknown:
        raise InputError(f"outputs: unknown output(s) {', '.join(map(repr, unknown))}; "
                         f"choose from {', '.join(OUTPUTS)}")
    return frozenset(names)


def _check_frame_id(name: str, value: str, *, empty: bool) -> None:
    """A TF frame name (REP 105): no whitespace, no leading '/' (tf2 refuses both)."""
    text = str(value)
    if (not text and not empty) or any(c.isspace() for c in text) or text.startswith("/"):
        raise InputError(f"{name} must be a frame name without spaces or a leading '/'"
                         f"{'' if empty else ', not empty'}, got {value!r}")


def parse_fallback_intrinsics(text: str) -> tuple[float, float, float, float] | None:
    """``fallback_intrinsics`` "fx fy cx cy" (spaces or commas) → the four numbers, None when
    empty; fx, fy > 0, cx, cy >= 0 (0 = the image centre)."""
    parts = str(text).replace(",", " ").split()
    if not parts:
        return None
    try:
        values = tuple(float(v) for v in parts)
    except ValueError:
        values = ()
    if len(values) != 4 or not all(math.isfinite(v) for v in values):
        raise InputError(f"fallback_intrinsics must be empty or four numbers 'fx fy cx cy', "
                         f"got {text!r}")
    fx, fy, cx, cy = values
    if fx <= 0 or fy <= 0 or cx < 0 or cy < 0:
        raise InputError(f"fallback_intrinsics: fx and fy must be > 0 and cx, cy >= 0, got "
                         f"{text!r}")
    return fx, fy, cx, cy


def parse_use_projection(value: str | bool) -> bool | None:
    """``camera_info_use_projection`` → None (auto), True (CameraInfo P) or False (K)."""
    if isinstance(value, bool):
        return value
    text = str(value).strip().lower()
    if text == "auto":
        return None
    if text in ("true", "p"):
        return True
    if text in ("false", "k"):
        return False
    raise InputError(f"camera_info_use_projection must be auto, true or false, got {value!r}")


@dataclass
class NodeSettings:
    """What the node reads itself (the core's configs hold the rest).

    ``fallback_intrinsics``: "fx fy cx cy" used until a CameraInfo arrives ("" = none; cx, cy
    0 = image centre). ``assumed_hfov_deg``: the horizontal field of view intrinsics are
    assumed from for an uncalibrated camera (a CameraInfo with K all zero; 0 = none, frames
    wait). ``outputs``: the outputs published (:data:`OUTPUTS`, comma-separated).
    ``camera_info_use_projection``: ``"auto"``, ``"true"``/True (P) or
    ``"false"``/False (K). ``image_transport``: ``"raw"`` (sensor_msgs/Image on ``image``) or
    ``"compressed"`` (sensor_msgs/CompressedImage on ``<image>/compressed``).
    ``cloud_stride``: ~/cloud takes every this-many-th pixel of the live depth, in both
    directions; ``cloud_max_range``: ~/cloud leaves out points farther than this from the camera
    (depth units; 0 = no limit). ``torch_num_threads`` 0 = torch's default.
    ``diagnostics_stale_after_s``: the stream status warns after this long without an image
    (0 = never);
    ``relative_depth``: depth, clouds and points not in metres on their relative topics
    (``publish``) or not at all (``drop``); ``compressed_depth_max`` /
    ``compressed_depth_png_level``: the compressedDepth outputs' ``depth_max`` (farther =
    none) and PNG level. ``odom_*``: ~/odom's frames and the camera's mounting on the base
    (:func:`~sfm_ttr_ros.core.stream.base_odometry.parse_camera_mount`)."""

    fallback_intrinsics: str = ""
    assumed_hfov_deg: float = 65.0
    camera_info_use_projection: str | bool = "auto"
    image_transport: str = "raw"
    qos_reliability: str = "reliable"
    qos_depth: int = 30
    outputs: str = ",".join(DEFAULT_OUTPUTS)
    cloud_stride: int = 4
    cloud_max_range: float = 0.0
    diagnostics_period_s: float = 1.0
    diagnostics_stale_after_s: float = 5.0
    torch_num_threads: int = 0
    load_weights_path: str = ""
    save_weights_path: str = ""
    relative_depth: str = "publish"
    compressed_depth_max: float = 100.0
    compressed_depth_png_level: int = 1
    odom_frame_id: str = "sfm_odom"
    odom_child_frame_id: str = "base_link"
    odom_camera_mount: str = DEFAULT_CAMERA_MOUNT
    odom_publish_tf: bool = False

    def __post_init__(self) -> None:
        _check_frame_id("odom.frame_id", self.odom_frame_id, empty=False)
        _check_frame_id("odom.child_frame_id", self.odom_child_frame_id, empty=False)
        parse_camera_mount(self.odom_camera_mount)
        parse_fallback_intrinsics(self.fallback_intrinsics)
        if not (0 <= self.assumed_hfov_deg < 180):
            raise InputError(f"assumed_hfov_deg must be in [0, 180) (0 = none), got "
                             f"{self.assumed_hfov_deg}")
        parse_outputs(self.outputs)
        parse_use_projection(self.camera_info_use_projection)
        check_choice("image_transport", self.image_transport, IMAGE_TRANSPORTS)
        check_choice("qos_reliability", self.qos_reliability, QOS_RELIABILITIES)
        if self.cloud_stride < 1:
            raise InputError(f"cloud.stride must be >= 1, got {self.cloud_stride}")
        if not (math.isfinite(self.cloud_max_range) and self.cloud_max_range >= 0):
            raise InputError(f"cloud.max_range must be >= 0 (0 = no limit), got "
                             f"{self.cloud_max_range}")
        if self.qos_depth < 1:
            raise InputError(f"qos_depth must be >= 1, got {self.qos_depth}")
        if not (math.isfinite(self.diagnostics_period_s) and self.diagnostics_period_s > 0):
            raise InputError(f"diagnostics_period_s must be > 0, got "
                             f"{self.diagnostics_period_s}")
        if self.torch_num_threads < 0:
            raise InputError(f"torch_num_threads must be >= 0, got {self.torch_num_threads}")
        check_choice("relative_depth", self.relative_depth, RELATIVE_DEPTH_CHOICES)
        if not (math.isfinite(self.compressed_depth_max) and self.compressed_depth_max > 0):
            raise InputError(f"compressed_depth.depth_max must be > 0, got "
                             f"{self.compressed_depth_max}")
        if not 0 <= self.compressed_depth_png_level <= 9:
            raise InputError(f"compressed_depth.png_level must be 0-9, got "
                             f"{self.compressed_depth_png_level}")

    # parsed once (read per frame); the settings are replaced, never changed, on a new value
    @cached_property
    def fallback(self) -> tuple[float, float, float, float] | None:
        """(fx, fy, cx, cy) of ``fallback_intrinsics``, None when unset."""
        return parse_fallback_intrinsics(self.fallback_intrinsics)

    @cached_property
    def published(self) -> frozenset[str]:
        """The outputs published (:data:`OUTPUTS`)."""
        return parse_outputs(self.outputs)

    @cached_property
    def use_projection(self) -> bool | None:
        """:func:`parse_use_projection` of ``camera_info_use_projection``."""
        return parse_use_projection(self.camera_info_use_projection)
