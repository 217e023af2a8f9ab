"""What one window's reconstruction gives the method (Sec. 3.1), collected from pycolmap's.

For each registered frame j and each 3D point X_l it observes: the SfM depth
D_sfm(l, j) = [R_j X_l + t_j]_z, the observed keypoint p_lj (not the reprojection) and that
observation's reprojection error r_lj = ||π(R_j X_l + t_j) − p_lj|| (:func:`collect_result`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from sfm_ttr_ros.core.frames import Intrinsics
from sfm_ttr_ros.core.sfm.names import image_name
from sfm_ttr_ros.core.sfm.sfm_config import SfmConfig


@dataclass
class FrameObservations:
    """Sparse SfM depth of one registered frame (pixels in OpenCV convention, full-res)."""

    name: str
    pixels: np.ndarray  # N x 2 float32, (x, y), pixel centres at integers
    depths: np.ndarray  # N float64, z in the camera frame, reconstruction units
    reproj_errors: np.ndarray  # N float64, per-observation reprojection error r_lj in px
    track_errors: np.ndarray  # N float64, mean reprojection error of the point's whole track
    point_ids: np.ndarray  # N int64, COLMAP 3D point ids
    cam_from_world: np.ndarray  # 4 x 4

    def __len__(self) -> int:
        return int(self.depths.shape[0])


@dataclass
class SfmResult:
    """What one window's reconstruction produced; ``ok`` False says why in ``reason``."""

    ok: bool
    reason: str
    num_frames: int
    frames: dict[str, FrameObservations] = field(default_factory=dict)
    point_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    points_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    points_rgb: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))
    points_error: np.ndarray = field(default_factory=lambda: np.zeros(0))
    timings: dict[str, float] = field(default_factory=dict)
    intrinsics: Intrinsics | None = None  # as used (refined when refine_intrinsics is on)
    # one entry per mapper run (seed, registered, points, reprojection_error, seconds, kept)
    attempts: list[dict] = field(default_factory=list)
    # frames before the window mapped with it (the streaming map's last frames, in a fresh
    # mapping): not the window's, but their poses tie its reconstruction to the camera's path
    anchors: dict[str, FrameObservations] = field(default_factory=dict)
    # how it was mapped: "continued" (the streaming SfM's carried map) or "fresh" (the window
    # mapped anew), with the reason a fresh mapping replaced the continuation; "" for the
    # batch reconstructor's (each window mapped on its own) and a window that was not mapped
    mapping: str = ""
    mapping_reason: str = ""

    @property
    def num_registered(self) -> int:
        return len(self.frames)

    @property
    def reprojection_error(self) -> float:
        """Mean of r_lj (px) over every observation of the registered frames; NaN without
        any. (COLMAP's own mean averages per 3D point, not per observation.)"""
        errs = [f.reproj_errors for f in self.frames.values()]
        return float(np.concatenate(errs).mean()) if sum(map(len, errs)) else float("nan")

    @property
    def num_points(self) -> int:
        return int(self.point_ids.shape[0])

    def points_in_frame(self, name: str) -> np.ndarray:
        """All 3D points (M x 3) expressed in the optical frame of registered frame ``name``."""
        T = self.frames[name].cam_from_world
        return self.points_xyz @ T[:3, :3].T + T[:3, 3]


def collect_result(recs, names: Sequence[str], timings: dict[str, float],
                   config: SfmConfig) -> SfmResult:
    """The window's :class:`SfmResult` from pycolmap's reconstructions (the one with the most
    registered frames): D_sfm, p_lj, r_lj per registered frame of ``names``, the 3D points,
    and whether it has enough frames and points (``min_registered``, ``min_points``)."""
    if not recs:
        return SfmResult(False, "mapping found no initial pair / produced no model",
                         len(names), timings=timings)
    rec = max(recs.values(), key=lambda r: r.num_reg_images())
    result = SfmResult(True, "", len(names), timings=timings)
    cam = next(iter(rec.cameras.values()))
    fx, fy, cx, cy = _pinhole(cam)
    result.intrinsics = Intrinsics(fx, fy, cx - 0.5, cy - 0.5, cam.width, cam.height)
    wanted = {image_name(n): n for n in names}
    for image in rec.images.values():
        if not image.has_pose or image.name not in wanted:
            continue
        obs = _frame_observations(rec, image, wanted[image.name])
        if obs is not None:
            result.frames[obs.name] = obs
    pids = np.array(sorted(rec.points3D.keys()), np.int64)
    result.point_ids = pids
    result.points_xyz = np.array([rec.points3D[int(i)].xyz for i in pids]).reshape(-1, 3)
    result.points_error = np.array([rec.points3D[int(i)].error for i in pids])
    if result.num_registered < config.min_registered:
        result.ok = False
        result.reason = (f"only {result.num_registered} of {len(names)} frames registered "
                         f"(< {config.min_registered})")
    elif result.num_points < config.min_points:
        result.ok = False
        result.reason = f"only {result.num_points} 3D points (< {config.min_points})"
    return result


def _pinhole(camera) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of a PINHOLE or SIMPLE_PINHOLE (one focal length: the focal
    length refined for assumed intrinsics) pycolmap camera, COLMAP's pixel centres."""
    K = camera.calibration_matrix()
    return float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])


def _frame_observations(rec, image, name: str) -> FrameObservations | None:
    """D_sfm, p_lj and r_lj of one registered image (pixel centres moved from COLMAP's +0.5
    to OpenCV's integers); None when it observes no 3D point."""
    T = image.cam_from_world().matrix()
    R, t = T[:, :3], T[:, 3]
    obs = [(p.xy, p.point3D_id) for p in image.points2D if p.has_point3D()]
    if not obs:
        return None
    xy = np.array([o[0] for o in obs], np.float64)
    pids = np.array([o[1] for o in obs], np.int64)
    X = np.array([rec.points3D[int(i)].xyz for i in pids])
    Xc = X @ R.T + t
    fx, fy, cx, cy = _pinhole(image.camera)
    proj = np.stack([fx * Xc[:, 0] / Xc[:, 2] + cx, fy * Xc[:, 1] / Xc[:, 2] + cy], 1)
    track_err = np.array([rec.points3D[int(i)].error for i in pids])
    return FrameObservations(
        name=name,
        pixels=(xy - 0.5).astype(np.float32),
        depths=Xc[:, 2],
        reproj_errors=np.linalg.norm(proj - xy, axis=1),
        track_errors=track_err,
        point_ids=pids,
        cam_from_world=np.vstack([T, [0, 0, 0, 1]]),
    )


def point_colours(result: SfmResult, images: dict[str, np.ndarray]) -> np.ndarray:
    """RGB of every 3D point, read at its first observation's pixel."""
    colours = np.zeros((result.num_points, 3), np.uint8)
    index = {int(p): i for i, p in enumerate(result.point_ids)}
    for name, obs in result.frames.items():
        img = images[name]
        h, w = img.shape[:2]
        px = np.clip(np.rint(obs.pixels).astype(int), 0, [w - 1, h - 1])
        rows = np.array([index[int(p)] for p in obs.point_ids])
        colours[rows] = img[px[:, 1], px[:, 0]]
    return colours
