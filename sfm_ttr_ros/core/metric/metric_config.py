"""The metric scale's settings (the node's ``metric.*`` parameters)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from sfm_ttr_ros.core.alignment.affine import AFFINE_OUTPUT_KINDS
from sfm_ttr_ros.core.errors import InputError, check_choice

#: Where the metric scale comes from: none (the network's units, said in the diagnostics),
#: camera_height (a ground plane under the camera), odometry (travelled distance), fixed (a
#: factor the user gives).
METRIC_SOURCES = ("none", "camera_height", "odometry", "fixed")


def check_source_for_output(source: str, output_kind: str) -> None:
    """InputError when ``source`` gives metres (any but ``none``) to a network whose output is
    ``output_kind`` affine-invariant inverse depth: up to a scale AND a shift, so no factor
    makes it depth in metres (``fixed`` would publish factor x inverse depth as metres; an
    estimate of ``camera_height`` / ``odometry`` scales SfM depth, not that output)."""
    if source != "none" and output_kind in AFFINE_OUTPUT_KINDS:
        raise InputError(
            f"metric.source {source!r} needs a network that predicts depth (metric or up to "
            f"scale); this one predicts {output_kind} (affine-invariant: up to scale and "
            "shift), which no factor turns into metres: set metric.source none (the depth "
            "goes out on the relative topics) or use a depth network")


@dataclass
class MetricConfig:
    source: str = "none"
    camera_height: float = 1.65  # m above the ground plane (KITTI's colour cameras)
    factor: float = 1.0  # fixed: metres per network depth unit
    # windows whose estimates make the steady factor (their median)
    history: int = 10
    # a window's estimate further than this factor from the steady one is refused like a scale
    # jump (0 = never): its reconstruction or its ground plane is wrong
    max_jump: float = 2.0
    # the supervision targets in metres (the network learns metres; measured best) instead of
    # the outputs scaled by the windows' factor (docs/decisions.md)
    learn: bool = True
    # camera_height: a ground plane's normal within this angle (degrees) of the cameras' down
    # axis, inliers within this share of the camera height, at least this many of them, and the
    # registered cameras' heights above it within this relative spread
    max_tilt_deg: float = 20.0
    inlier_tolerance: float = 0.04
    min_ground_points: int = 12
    max_height_spread: float = 0.25
    # ... and the cameras looking along it (their optical axis within this angle of the plane:
    # a vehicle's camera, not one looking down at a table), the plane's inliers spanning at
    # least this many camera heights (a ground, not a table top)
    max_pitch_deg: float = 25.0
    min_ground_extent: float = 3.0
    # ... and, for cameras that travel, its normal within this angle of square to the travel
    # (they move along their ground) and, across the travel, within this angle of the
    # cameras' down axis (a camera rolls with its ground: a plane rolled further is a slope
    # through the road and the kerb side, not the road)
    max_slope_deg: float = 3.0
    max_roll_deg: float = 3.0
    # ... and only the points within this many camera heights aside of the cameras' track
    # count for it (the road they drive on, not a track bed, a sidewalk or a wall's foot)
    corridor: float = 1.5
    # odometry: the least travel (m) a window's frames must span
    min_travel: float = 0.2
    # the anchor (core/metric/anchor.py): windows agree when their k lie within this relative
    # tolerance of each other; this many agreeing windows confirm the first estimate (state
    # ``confirming`` until then), and this many recent windows that agree with each other and
    # not with the anchor re-anchor it
    agreement: float = 0.15
    confirm_windows: int = 2
    reanchor_windows: int = 3
    # once ``metric``, the state demotes to ``stale`` when its source stops: odometry silent
    # for this long (s), or this many windows in a row without a camera-height estimate
    odometry_timeout_s: float = 5.0
    stale_windows: int = 3

    def __post_init__(self) -> None:
        check_choice("metric.source", self.source, METRIC_SOURCES)
        for name in ("camera_height", "factor", "inlier_tolerance", "min_travel", "agreement",
                     "odometry_timeout_s"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"metric.{name} must be a finite number > 0, got {v}")
        if not (self.max_jump == 0 or self.max_jump >= 1):
            raise InputError(f"metric.max_jump is a factor >= 1 (or 0 = off), got "
                             f"{self.max_jump}")
        if self.history < 1 or self.min_ground_points < 3:
            raise InputError("metric.history must be >= 1 and min_ground_points >= 3")
        if min(self.confirm_windows, self.reanchor_windows, self.stale_windows) < 1:
            raise InputError("metric.confirm_windows, reanchor_windows and stale_windows must "
                             "be >= 1")
        if not 0 < self.max_tilt_deg < 90 or not self.max_height_spread > 0:
            raise InputError("metric.max_tilt_deg must lie in (0, 90) and max_height_spread > 0")
