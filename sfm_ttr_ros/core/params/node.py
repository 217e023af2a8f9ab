"""The refiner node's own settings (camera fallback, transport, outputs, weights files, threads):
ROS-free and self-validating like the core's configs, so that the one parameter schema
(:mod:`sfm_ttr_ros.core.params`) reads their defaults and types from here."""

from __future__ import annotations

import math
from dataclasses import dataclass

from sfm_ttr_ros.core.errors import InputError

QOS_RELIABILITIES = ("reliable", "best_effort")
IMAGE_TRANSPORTS = ("raw", "compressed")  # sensor_msgs/Image on image, CompressedImage on
# image/compressed (the image_transport convention)
USE_PROJECTION_CHOICES = ("auto", "true", "false")


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

    ``fx``/``fy``/``cx``/``cy``: fallback intrinsics until a CameraInfo arrives (0 = unset; cx,
    cy 0 = image centre). ``camera_info_use_projection``: ``"auto"``, ``"true"``/True (P) or
    ``"false"``/False (K). ``image_transport``: ``"raw"`` (sensor_msgs/Image on ``image``) or
    ``"compressed"`` (sensor_msgs/CompressedImage on ``<image>/compressed``).
    ``torch_num_threads`` 0 = torch's default."""

    fx: float = 0.0
    fy: float = 0.0
    cx: float = 0.0
    cy: float = 0.0
    camera_info_use_projection: str | bool = "auto"
    image_transport: str = "raw"
    qos_reliability: str = "reliable"
    qos_depth: int = 30
    publish_live: bool = True
    publish_refined: bool = True
    publish_colored: bool = True
    publish_points: bool = True
    publish_diagnostics: bool = True
    diagnostics_period_s: float = 1.0
    torch_num_threads: int = 0
    load_weights_path: str = ""
    save_weights_path: str = ""

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v >= 0):
                raise InputError(f"{name} must be a finite number >= 0, got {v}")
        if (self.fx > 0) != (self.fy > 0):
            raise InputError("set both fallback focal lengths fx and fy, or neither "
                             f"(got fx={self.fx}, fy={self.fy})")
        parse_use_projection(self.camera_info_use_projection)
        if self.image_transport not in IMAGE_TRANSPORTS:
            raise InputError(f"image_transport must be one of {', '.join(IMAGE_TRANSPORTS)}; "
                             f"got {self.image_transport!r}")
        if self.qos_reliability not in QOS_RELIABILITIES:
            raise InputError(f"qos_reliability must be one of {', '.join(QOS_RELIABILITIES)}; "
                             f"got {self.qos_reliability!r}")
        if self.qos_depth < 1:
            raise InputError(f"qos_depth must be >= 1, got {self.qos_depth}")
        if not (math.isfinite(self.diagnostics_period_s) and self.diagnostics_period_s > 0):
            raise InputError(f"diagnostics_period_s must be > 0, got "
                             f"{self.diagnostics_period_s}")
        if self.torch_num_threads < 0:
            raise InputError(f"torch_num_threads must be >= 0, got {self.torch_num_threads}")

    @property
    def use_projection(self) -> bool | None:
        """:func:`parse_use_projection` of ``camera_info_use_projection``."""
        return parse_use_projection(self.camera_info_use_projection)
