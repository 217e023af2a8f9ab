"""Incremental mapping of a window (Sec. 3.1) from the matches in the workspace's database:
cheap prechecks first, then pycolmap's mapper with thresholds that accept forward driving
(COLMAP's defaults reject it), run again
with another seed while the reconstruction fits badly, the best kept
(``SfmConfig.mapping_attempts``)."""

from __future__ import annotations

import math
import shutil
import time
from collections import deque
from collections.abc import Callable, Sequence

import numpy as np

from sfm_ttr_ros.core.sfm.names import image_name
from sfm_ttr_ros.core.sfm.result import SfmResult, collect_result
from sfm_ttr_ros.core.sfm.sfm_config import MIN_PAIR_INLIERS, RETRY_HISTORY, SfmConfig
from sfm_ttr_ros.core.sfm.workspace import SfmWorkspace

MapperRun = Callable[[SfmConfig, list[str], object, int], dict]


class Mapper:
    """The mapper of one workspace and the stream's last reconstruction errors (the
    reference of ``sfm.retry_above_ratio``)."""

    def __init__(self, workspace: SfmWorkspace | None, runner: MapperRun | None = None):
        self.workspace = workspace
        # one mapper run over other data than the workspace's database (the streaming SfM's
        # map cache): (config, names, token, seed) -> {index: pycolmap.Reconstruction}
        self.runner = runner
        # mean reprojection errors of the stream's last reconstructions (sfm.retry_above_ratio)
        self.errors: deque[float] = deque(maxlen=RETRY_HISTORY)

    def reset(self) -> None:
        """A new stream (or database): its errors are forgotten."""
        self.errors.clear()

    def map_best(self, config: SfmConfig, names: list[str], timings: dict[str, float], token,
                 check: Callable[[], None]) -> SfmResult:
        """Run the mapper up to ``mapping_attempts`` times (seeds ``seed``, ``seed`` + 1, ...)
        and keep the reconstruction with the most registered frames, then the lowest mean
        reprojection error. A further run happens only while the best so far has a mean error
        above ``retry_above_error`` or above ``retry_above_ratio`` times the median of the
        stream's last :data:`RETRY_HISTORY` reconstructions, or failed with a model (too few
        points or frames): from the same matches pycolmap's incremental mapper now and then
        settles on a wrong reconstruction of a window that another seed reconstructs right,
        with about twice the reprojection error (hololens_000 windows 1 and 3: 0.98-1.07 px
        against 0.60-0.65 px, refinement then made them worse), or on a few frames and points
        (BENCHMARKS.md "Window checks"). A run that found no model at all is not repeated (it
        can take seconds). ``check`` raises when the reconstruction is cancelled."""
        limit = self.retry_limit(config)
        best: SfmResult | None = None
        best_key: tuple = ()
        attempts: list[dict] = []
        for attempt in range(config.mapping_attempts):
            t0 = time.perf_counter()
            recs = self._map(config, names, token, config.seed + attempt)
            check()
            result = self._collect(config, recs, names, timings)
            error = result.reprojection_error
            attempts.append({"seed": config.seed + attempt, "registered": result.num_registered,
                             "points": result.num_points, "reprojection_error": error,
                             "seconds": time.perf_counter() - t0, "kept": False})
            key = rank(result)
            if best is None or key > best_key:
                best, best_key, kept = result, key, attempts[-1]
            if not (kept["reprojection_error"] > limit if best.ok else best.num_registered > 0):
                break
        kept["kept"] = True
        best.attempts = attempts
        if best.ok:
            self.errors.append(kept["reprojection_error"])
        return best

    def retry_limit(self, config: SfmConfig) -> float:
        """The mean reprojection error above which the mapper runs again: ``retry_above_error``,
        or ``retry_above_ratio`` times the median of the stream's last reconstructions."""
        limit = float(config.retry_above_error)
        if config.retry_above_ratio > 0 and self.errors:
            limit = min(limit, config.retry_above_ratio * float(np.median(self.errors)))
        return limit

    def precheck(self, config: SfmConfig, names: Sequence[str]) -> str:
        """Cheap reasons a window cannot be reconstructed, before the (slow) mapper runs."""
        import pycolmap

        with pycolmap.Database.open(self.workspace.database_path) as db:
            ids = {img.name: int(img.image_id) for img in db.read_all_images()}
            window_ids = {ids[image_name(n)] for n in names if image_name(n) in ids}
            nkp = [db.num_keypoints_for_image(i) for i in window_ids]
            if sum(k >= 50 for k in nkp) < 2:
                return f"too few features (keypoints per frame: {nkp})"
            pair_ids, geoms = db.read_two_view_geometries()
            best_parallax, verified = 0.0, 0
            for pid, g in zip(pair_ids, geoms, strict=True):
                i1, i2 = pycolmap.pair_id_to_image_pair(pid)
                if i1 not in window_ids or i2 not in window_ids:
                    continue
                m = g.inlier_matches
                if m is None or len(m) < MIN_PAIR_INLIERS:
                    continue
                verified += 1
                k1 = db.read_keypoints(i1)[m[:, 0], :2]
                k2 = db.read_keypoints(i2)[m[:, 1], :2]
                best_parallax = max(best_parallax,
                                    float(np.median(np.linalg.norm(k1 - k2, axis=1))))
        if verified == 0:
            return "no frame pair of the window could be matched"
        if best_parallax < config.min_parallax_px:
            return (f"too little motion: median keypoint motion {best_parallax:.2f} px < "
                    f"{config.min_parallax_px} px")
        return ""

    def _map(self, config: SfmConfig, names: list[str], token, seed: int):
        import pycolmap

        if self.runner is not None:
            return self.runner(config, names, token, seed)

        set_camera_model(self.workspace.database_path, config.refine_intrinsics)
        out = self.workspace.path / "sparse"
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir(parents=True)
        return pycolmap.incremental_mapping(self.workspace.database_path,
                                            self.workspace.image_dir, out,
                                            options=mapper_options(config, names, seed),
                                            cancellation_token=token)

    @staticmethod
    def _collect(config: SfmConfig, recs, names: list[str],
                 timings: dict[str, float]) -> SfmResult:
        return collect_result(recs, names, timings, config)


def set_camera_model(database_path, one_focal: bool) -> None:
    """The database's camera as the mapper takes it: PINHOLE (fx, fy held fixed), or with
    ``one_focal`` SIMPLE_PINHOLE, one focal length f = (fx + fy) / 2 that bundle adjustment
    refines (two free focal lengths drift apart: measured on a generated drive, fx 1570 and
    fy 39 px from 502 px). The principal point is kept; keypoints and matches do not depend
    on the model."""
    import pycolmap

    model = "SIMPLE_PINHOLE" if one_focal else "PINHOLE"
    with pycolmap.Database.open(database_path) as db:
        for cam in db.read_all_cameras():
            if cam.model.name == model:
                continue
            K = cam.calibration_matrix()
            fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
            params = [0.5 * (fx + fy), cx, cy] if one_focal else [fx, fy, cx, cy]
            new = pycolmap.Camera(model=model, width=cam.width, height=cam.height,
                                  params=params, camera_id=cam.camera_id)
            new.has_prior_focal_length = cam.has_prior_focal_length
            db.update_camera(new)


def mapper_options(config: SfmConfig, names: list[str], seed: int):
    """pycolmap's incremental mapper options for ``names``: one fixed PINHOLE camera (one
    focal length refined only with ``refine_intrinsics``: :func:`set_camera_model`), the
    forward-driving initialisation thresholds, COLMAP's filters at ``max_reproj_error`` and
    ``min_tri_angle``."""
    import pycolmap

    opts = pycolmap.IncrementalPipelineOptions()
    opts.image_names = [image_name(n) for n in names]
    opts.multiple_models = False
    opts.min_model_size = 2
    opts.num_threads = config.num_threads
    opts.random_seed = seed
    opts.extract_colors = False  # images are deleted after extraction; colours come later
    opts.ba_refine_focal_length = config.refine_intrinsics
    opts.ba_refine_principal_point = False
    opts.ba_refine_extra_params = False
    m = opts.mapper
    m.init_max_forward_motion = config.init_max_forward_motion
    m.init_min_tri_angle = config.init_min_tri_angle
    m.init_min_num_inliers = config.init_min_num_inliers
    m.abs_pose_refine_focal_length = config.refine_intrinsics
    m.abs_pose_refine_extra_params = False
    m.filter_max_reproj_error = config.max_reproj_error
    m.filter_min_tri_angle = config.min_tri_angle
    m.num_threads = config.num_threads
    m.random_seed = seed
    opts.triangulation.min_angle = config.min_tri_angle
    return opts


def rank(result: SfmResult) -> tuple:
    """The order of reconstructions of one window (greater is better): ok, then more frames
    registered, then a lower mean reprojection error (NaN: the worst)."""
    error = result.reprojection_error
    return (result.ok, result.num_registered, -error if error == error else -math.inf)
