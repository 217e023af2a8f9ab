"""The camera's height above the ground, in SfM units, from a window's sparse points.

A driving camera (and most robot cameras) sits at a known height above a near-planar ground,
with its image's y axis roughly along gravity. With the registered cameras' centres C_j and
down axes d_j = R_jᵀ·(0, 1, 0) (R_j: cam_from_world), the mean down axis d = Σ d_j / |Σ d_j|,
a plane n·X = c is fitted by RANSAC (three points) to the SfM points below the cameras
((X − C̄)·d > 0), keeping only planes whose normal lies within ``max_tilt_deg`` of d and
counting a point as an inlier when |n·X − c| < ``inlier_tolerance`` · h, h the plane's
distance to the mean camera centre (a tolerance that scales with the unknown SfM unit).

The ground is the road the cameras drive on (:class:`Axes`): with v the direction of travel
(first to last centre), a plane's normal must lie within ``max_slope_deg`` of square to v (the
cameras move along their ground: a plane pitched against the path is not it) and, across v,
within ``max_roll_deg`` of d (a car rolls with its lane); only points within ``corridor`` · h
aside of the track count as inliers. On a road with real edges (the generated domain C: a
cambered road of plain asphalt with few features, a raised sidewalk and a wall on one side, a
raised tram bed on the other) the plane with the most inliers otherwise is a slope rolled by
10-20° through the few road points and the points off the road, its height 1.3-3.5x off.

The best plane is refined by least squares on its inliers, then on those within half the
tolerance (the lane under the camera, not a cambered road's far side), and each camera's height
is h_j = n·C_j − c (n oriented so that the cameras lie above: the ground's up, which the camera's
path takes for its odom frame's z, core/camera_path.py). The window's height is the median
h_j; metres per SfM unit = camera_height / median h_j.

Refused (no estimate, with the reason) when the cameras' down axes disagree (a rolling
hand-held camera), fewer than ``min_ground_points`` inliers support the plane (no ground in
view), or the cameras' heights spread by more than ``max_height_spread`` (the plane is not the
ground the camera moves over).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from sfm_ttr_ros.core.geometry import camera_centre
from sfm_ttr_ros.core.metric.metric_config import MetricConfig
from sfm_ttr_ros.core.sfm.result import SfmResult

RANSAC_ITERATIONS = 1000


@dataclass
class GroundPlane:
    """A window's ground plane: ``height`` (median camera height, SfM units; NaN = none),
    its ``inliers`` and ``spread`` (max − min camera height over the median), or ``reason``."""

    height: float = float("nan")
    inliers: int = 0
    spread: float = float("nan")
    pitch_deg: float = float("nan")  # the cameras' mean optical axis against the plane
    extent: float = float("nan")  # the inliers' extent on the plane, in camera heights
    reason: str = ""
    up: np.ndarray | None = None  # the plane's unit normal towards the cameras (SfM world)


def cameras(sfm: SfmResult, registered: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """(centres N x 3, down axes N x 3) of the registered cameras in SfM world coordinates."""
    T = np.stack([np.asarray(sfm.frames[n].cam_from_world, np.float64) for n in registered])
    return camera_centre(T), T[:, 1, :3]  # R_jᵀ·(0, 1, 0) is R_j's second row


def ground_plane(sfm: SfmResult, registered: Sequence[str], cfg: MetricConfig,
                 seed: int = 0) -> GroundPlane:
    """The window's ground plane and camera height (module docstring)."""
    if len(registered) < 2 or sfm.points_xyz.shape[0] < cfg.min_ground_points:
        return GroundPlane(reason="too few registered frames or points")
    centres, downs = cameras(sfm, registered)
    total = downs.sum(0)
    agreement = float(np.linalg.norm(total) / len(downs))  # 1 = every down axis the same
    if agreement < math.cos(math.radians(cfg.max_tilt_deg)):
        return GroundPlane(reason=f"the cameras' down axes disagree ({agreement:.2f})")
    down = total / np.linalg.norm(total)
    mean_c = centres.mean(0)
    X = np.asarray(sfm.points_xyz, np.float64)
    X = X[(X - mean_c) @ down > 0]
    if X.shape[0] < cfg.min_ground_points:
        return GroundPlane(reason=f"{X.shape[0]} points below the cameras")
    travel = _travel(centres)
    plane = _ransac_plane(X, Axes(down, travel), mean_c, cfg, np.random.default_rng(seed))
    if plane is None:
        return GroundPlane(reason="no plane across the cameras' down axis")
    n, c, inliers = plane
    if inliers.sum() < cfg.min_ground_points:
        return GroundPlane(inliers=int(inliers.sum()),
                           reason=f"{int(inliers.sum())} points on the ground plane")
    n, c = _refit(X[inliers], down, mean_c, cfg)
    heights = centres @ n - c
    h = float(np.median(heights))
    plane = GroundPlane(inliers=int(inliers.sum()),
                        spread=float((heights.max() - heights.min()) / h) if h > 0 else math.inf,
                        pitch_deg=_pitch(sfm, registered, n), extent=_extent(X[inliers], n, h))
    if not h > 0 or plane.spread > cfg.max_height_spread:
        plane.reason = f"camera heights over the plane spread {plane.spread:.2f}"
    elif abs(plane.pitch_deg) > cfg.max_pitch_deg:
        plane.reason = (f"the cameras look {plane.pitch_deg:.0f} deg against the plane: not a "
                        "camera that looks along the ground")
    elif plane.extent < cfg.min_ground_extent:
        plane.reason = f"the plane spans {plane.extent:.1f} camera heights: not the ground"
    else:
        plane.height, plane.up = h, n
    return plane


def _pitch(sfm: SfmResult, registered: Sequence[str], n: np.ndarray) -> float:
    """Degrees between the cameras' mean optical axis and the plane (positive: looking
    down at it)."""
    axes = np.stack([np.asarray(sfm.frames[r].cam_from_world, np.float64)[2, :3]
                     for r in registered]).mean(0)
    axes /= np.linalg.norm(axes)
    return float(np.degrees(np.arcsin(np.clip(-axes @ n, -1.0, 1.0))))


def _extent(P: np.ndarray, n: np.ndarray, h: float) -> float:
    """The plane points' extent along their longest in-plane direction (5th to 95th
    percentile), in camera heights ``h``."""
    Q = P - P.mean(0)
    Q = Q - np.outer(Q @ n, n)
    _, _, vt = np.linalg.svd(Q, full_matrices=False)
    along = Q @ vt[0]
    return float((np.percentile(along, 95) - np.percentile(along, 5)) / h) if h > 0 else 0.0


@dataclass
class Axes:
    """The cameras' mean down axis and their direction of travel (None: they hardly moved)."""

    down: np.ndarray
    travel: np.ndarray | None

    def admits(self, n: np.ndarray, cfg: MetricConfig) -> bool:
        """Whether a plane normal ``n`` (oriented along ``down``) can be the ground: within
        ``max_tilt_deg`` of the down axis; with travel, within ``max_slope_deg`` of square to
        it (the camera moves along its ground) and, across the travel, within
        ``max_roll_deg`` of the down axis (a camera rolls with its ground)."""
        if n @ self.down < math.cos(math.radians(cfg.max_tilt_deg)):
            return False
        v = self.travel
        if v is None:
            return True
        if abs(n @ v) > math.sin(math.radians(cfg.max_slope_deg)):
            return False
        a, b = n - (n @ v) * v, self.down - (self.down @ v) * v
        cos_roll = (a @ b) / (np.linalg.norm(a) * np.linalg.norm(b))
        return bool(cos_roll >= math.cos(math.radians(cfg.max_roll_deg)))


    def lateral(self, offsets: np.ndarray) -> np.ndarray:
        """How far aside of the cameras' track ``offsets`` (from the mean centre) lie, across
        the travel and the down axis; zeros without travel."""
        if self.travel is None:
            return np.zeros(offsets.shape[0])
        across = np.cross(self.travel, self.down)
        return np.abs(offsets @ (across / np.linalg.norm(across)))


def _travel(centres: np.ndarray) -> np.ndarray | None:
    """The unit direction from the first to the last camera centre; None when the cameras
    stood (their path under a tenth of their spread... or no path at all)."""
    d = centres[-1] - centres[0]
    norm = float(np.linalg.norm(d))
    return d / norm if norm > 0 else None


def _ransac_plane(X: np.ndarray, axes: Axes, centre: np.ndarray, cfg: MetricConfig,
                  rng: np.random.Generator):
    """(n, c, inlier mask) of the plane with the most inliers among three-point samples whose
    normal :meth:`Axes.admits` (n oriented along the down axis), or None."""
    down = axes.down
    lateral = axes.lateral(X - centre)
    best, best_count = None, 0
    for _ in range(RANSAC_ITERATIONS):
        a, b, c3 = X[rng.choice(X.shape[0], 3, replace=False)]
        n = np.cross(b - a, c3 - a)
        norm = np.linalg.norm(n)
        if norm == 0:
            continue
        n = n / norm
        n = n if n @ down > 0 else -n
        if not axes.admits(n, cfg):
            continue
        c = float(n @ a)
        h = c - float(n @ centre)  # the plane lies below the cameras: c > n·C
        if h <= 0:
            continue
        inliers = (np.abs(X @ n - c) < cfg.inlier_tolerance * h) & (lateral < cfg.corridor * h)
        count = int(inliers.sum())
        if count > best_count:
            best, best_count = (n, c, inliers), count
    if best is None:
        return None
    n, c, inliers = best
    return -n, -c, inliers  # oriented so that the cameras (above) have n·C − c > 0


def _refit(P: np.ndarray, down: np.ndarray, centre: np.ndarray,
           cfg: MetricConfig) -> tuple[np.ndarray, float]:
    """The plane by least squares on the RANSAC inliers ``P``, then again on those within half
    the inlier tolerance of it (a cambered road's far side, a kerb's top out: the lane under
    the camera), unless fewer than ``min_ground_points`` remain."""
    n, c = _refine(P, down)
    near = np.abs(P @ n - c) < 0.5 * cfg.inlier_tolerance * (n @ centre - c)
    return _refine(P[near], down) if near.sum() >= cfg.min_ground_points else (n, c)


def _refine(P: np.ndarray, down: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane through ``P`` (its smallest principal axis), oriented against
    ``down`` so that points above the plane (the cameras) have n·X − c > 0."""
    mean = P.mean(0)
    _, _, vt = np.linalg.svd(P - mean, full_matrices=False)
    n = vt[-1]
    n = -n if n @ down > 0 else n
    return n, float(n @ mean)
