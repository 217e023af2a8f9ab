"""Stage 1 of SfM-TTR: sparse SfM over a window of frames with pycolmap.

For each registered frame j and each 3D point X_l it observes the reconstruction gives
(Izquierdo & Civera, CVPR 2023, Sec. 3.1):

* the SfM depth  D_sfm(l, j) = [R_j X_l + t_j]_z  (up to the reconstruction's unknown scale),
* the observed keypoint p_lj (not the reprojection), and
* that observation's reprojection error r_lj = ||π(R_j X_l + t_j) − p_lj||.

One PINHOLE camera with the known intrinsics held fixed, SIFT features, sequential matching and
incremental mapping with initialisation thresholds that accept forward driving (COLMAP's
defaults reject it; see ``../shared/notes/pycolmap-on-these-machines.md``).

Features are extracted once per frame and pairs matched once: a :class:`SfmReconstructor`
keeps one COLMAP database across the windows of a stream, so overlapping windows only pay for
their new frames. The mapper, which from the same matches now and then settles on a wrong
reconstruction, runs again with another seed while the window's mean reprojection error is
high, and the best-fitting reconstruction is kept (``SfmConfig.mapping_attempts``).
"""

from __future__ import annotations

import hashlib
import logging
import shutil
import tempfile
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Frame, Intrinsics, check_window

log = logging.getLogger(__name__)

_PYCOLMAP_LOGGING_SET = False
MIN_MAX_IMAGE_SIZE = 16  # smallest SIFT downscale accepted (1 crashes pycolmap 4.2.1)
FEATURE_BACKENDS = ("colmap", "torch")  # sfm.features
RETRY_HISTORY = 10  # reconstructions of the stream whose median error sfm.retry_above_ratio scales


def quiet_pycolmap(verbose: bool = False) -> None:
    """Keep COLMAP's glog output (and its log files in the temp folder) out of the user's way."""
    import pycolmap

    global _PYCOLMAP_LOGGING_SET
    pycolmap.logging.logtostderr = True
    pycolmap.logging.minloglevel = 0 if verbose else 3
    pycolmap.logging.verbose_level = 1 if verbose else 0
    _PYCOLMAP_LOGGING_SET = True


@dataclass
class SfmConfig:
    """Options of the SfM stage (defaults: measured on KITTI-like data, see BENCHMARKS.md)."""

    max_image_size: int = 640  # SIFT runs on images downscaled to this longest side; <=0: full
    max_num_features: int = 8192
    first_octave: int = -1  # -1: COLMAP default (upsampled first octave); 0: ~3x faster
    num_threads: int = 2
    overlap: int = 10  # sequential matching: each frame with the next `overlap` frames
    init_min_tri_angle: float = 1.0  # degrees; COLMAP's 16 rejects consecutive driving frames
    init_min_num_inliers: int = 50
    init_max_forward_motion: float = 1.0  # COLMAP's 0.95 rejects forward motion
    min_tri_angle: float = 0.5  # filter / triangulation angle in degrees
    max_reproj_error: float = 4.0  # px, COLMAP's filter
    refine_intrinsics: bool = False  # hold the known intrinsics fixed (paper: better than not)
    min_registered: int = 2  # fewer registered frames than this: the window failed
    min_points: int = 20  # fewer 3D points than this: the window failed
    min_parallax_px: float = 1.0  # cheap pre-check on matched keypoint motion (full-res px)
    # The mapper, run again with the next seed while the best reconstruction so far has a mean
    # reprojection error above retry_above_error px (0: every attempt runs), keeps the best
    # (most frames registered, then the lowest error): see SfmReconstructor.reconstruct.
    mapping_attempts: int = 2
    retry_above_error: float = 0.8
    # ... or above this many times the median error of the stream's last RETRY_HISTORY
    # reconstructions (a camera whose reconstructions fit better than 0.8 px); 0: off
    retry_above_ratio: float = 1.3
    seed: int = 0
    verbose: bool = False
    # "colmap": pycolmap's SIFT and sequential matcher on the CPU (the reference); "torch": the
    # weight-free torch SIFT of core/sfm/features/sift_torch.py and mutual nearest-neighbour + ratio
    # matching on the accelerator when there is one, the matches verified by pycolmap
    features: str = "colmap"

    def __post_init__(self) -> None:
        # Values that reach pycolmap options known to end the process or to fail every window
        # (measured with pycolmap 4.2.1: max_image_size 1 segfaults in SIFT extraction,
        # init_min_tri_angle 0 fails the mapper's options check). Loop detection, which aborts
        # offline, is never enabled (see _match) and no option reaches it.
        if 0 < int(self.max_image_size) < MIN_MAX_IMAGE_SIZE:
            raise InputError(f"sfm.max_image_size must be 0 (full size) or >= "
                             f"{MIN_MAX_IMAGE_SIZE}, got {self.max_image_size}")
        if not float(self.init_min_tri_angle) > 0:
            raise InputError(f"sfm.init_min_tri_angle must be > 0, got "
                             f"{self.init_min_tri_angle}")
        if self.features not in FEATURE_BACKENDS:
            raise InputError(f"sfm.features must be one of {list(FEATURE_BACKENDS)}, got "
                             f"{self.features!r}")
        if int(self.mapping_attempts) < 1:
            raise InputError(f"sfm.mapping_attempts must be >= 1, got {self.mapping_attempts}")
        for name in ("retry_above_error", "retry_above_ratio"):
            if not float(getattr(self, name)) >= 0:
                raise InputError(f"sfm.{name} must be >= 0, got {getattr(self, name)}")


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


class SfmCancelled(RuntimeError):
    """Raised when :meth:`SfmReconstructor.cancel` interrupts a reconstruction."""


class SfmReconstructor:
    """Reconstructs windows of a stream, caching features and matches across windows.

    Frame names identify frames across the stream. A name that comes back with different pixels
    (e.g. a second sequence whose frames are again named by index) starts a fresh database, so
    stale features are never reused. The workspace (a temporary folder unless given) holds
    ``images/`` and ``database.db``. Changing the intrinsics (e.g. a resolution change) starts a
    fresh database too. ``frames_extracted`` counts the frames whose features were extracted.
    """

    def __init__(self, config: SfmConfig | None = None, workspace: str | Path | None = None,
                 max_cached_frames: int = 200, feature_device: str | None = None):
        self.config = config or SfmConfig()
        # torch device of sfm.features "torch" (None: the GPU when torch sees one, else CPU)
        self.feature_device = feature_device
        self._torch_db = None  # TorchFeatureDatabase of this generation (sfm.features "torch")
        self._db_features = self.config.features  # the feature kind the database holds
        self._own_workspace = workspace is None
        self._root = Path(workspace or tempfile.mkdtemp(prefix="sfm_ttr_"))
        self.max_cached_frames = max_cached_frames
        self._intrinsics: Intrinsics | None = None
        self._camera_id: int | None = None
        self._names: list[str] = []  # frames in the database, in insertion order
        # mean reprojection errors of the stream's last reconstructions (sfm.retry_above_ratio)
        self._errors: deque[float] = deque(maxlen=RETRY_HISTORY)
        self._digests: dict[str, bytes] = {}  # name -> digest of the pixels it was extracted from
        self.frames_extracted = 0
        self._generation = 0
        self._lock = threading.Lock()
        self._token = None
        self._cancelled = False
        quiet_pycolmap(self.config.verbose)

    # -- workspace ---------------------------------------------------------------------------
    @property
    def workspace(self) -> Path:
        return self._root / f"ws{self._generation}"

    @property
    def database_path(self) -> Path:
        return self.workspace / "database.db"

    @property
    def image_dir(self) -> Path:
        return self.workspace / "images"

    def reset(self) -> None:
        """Forget every cached frame (new database)."""
        shutil.rmtree(self.workspace, ignore_errors=True)
        self._generation += 1
        self._names = []
        self._digests = {}
        self._camera_id = None
        self._torch_db = None
        self._errors.clear()

    def close(self) -> None:
        if self._own_workspace:
            shutil.rmtree(self._root, ignore_errors=True)

    def __enter__(self) -> SfmReconstructor:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def cancel(self) -> None:
        """Interrupt the running reconstruction (from another thread); it raises SfmCancelled."""
        self._cancelled = True
        with self._lock:
            if self._token is not None:
                self._token.cancel()

    # -- pipeline ----------------------------------------------------------------------------
    def reconstruct(self, frames: Sequence[Frame], intrinsics: Intrinsics) -> SfmResult:
        """Reconstruct ``frames`` (one window). Never raises for a window that cannot be
        reconstructed (the result says why); raises :class:`InputError` for bad input and
        :class:`SfmCancelled` when cancelled."""
        import pycolmap

        check_window(frames, intrinsics)
        self._cancelled = False
        timings: dict[str, float] = {}
        if self._intrinsics != intrinsics:
            if self._intrinsics is not None:
                self.reset()
            self._intrinsics = intrinsics
        if self._names and self._db_features != self.config.features:
            self.reset()  # keypoints of one feature kind are never matched with the other's
        self._db_features = self.config.features
        names = [f.name for f in frames]
        if len(frames) < 2:
            return SfmResult(False, "a window needs at least 2 frames", len(frames))
        digests = {f.name: image_digest(f.image) for f in frames}
        changed = [n for n, d in digests.items() if self._digests.get(n, d) != d]
        if changed:
            log.info("frame %s came back with other pixels: new SfM database", changed[0])
            self.reset()
        self._prune_cache(keep=set(names))

        token = pycolmap.CancellationToken()
        with self._lock:
            self._token = token
        try:
            t0 = time.perf_counter()
            new = [f for f in frames if f.name not in self._digests]
            self._extract(new, intrinsics, token)
            self._digests.update((f.name, digests[f.name]) for f in new)
            timings["extract"] = time.perf_counter() - t0
            self._torch_timings(timings, "extract", new)
            self._check_cancel(token)

            t0 = time.perf_counter()
            self._match(token)
            timings["match"] = time.perf_counter() - t0
            self._torch_timings(timings, "match", True)
            self._check_cancel(token)

            reason = self._precheck(names)
            if reason:
                return SfmResult(False, reason, len(frames), timings=timings)

            t0 = time.perf_counter()
            result = self._map_best(names, timings, token)
            timings["map"] = time.perf_counter() - t0
        finally:
            with self._lock:
                self._token = None
        if result.num_points:
            result.points_rgb = _point_colours(result, {f.name: f.image for f in frames})
        return result

    def _map_best(self, names: list[str], timings: dict[str, float], token) -> SfmResult:
        """Run the mapper up to ``mapping_attempts`` times (seeds ``seed``, ``seed`` + 1, ...)
        and keep the reconstruction with the most registered frames, then the lowest mean
        reprojection error. A further run happens only while the best so far has a mean error
        above ``retry_above_error`` or above ``retry_above_ratio`` times the median of the
        stream's last :data:`RETRY_HISTORY` reconstructions, or failed with a model (too few
        points or frames): from the
        same matches pycolmap's incremental mapper now and then settles on a wrong
        reconstruction of a window that another seed reconstructs right, with about twice the
        reprojection error (hololens_000 windows 1 and 3: 0.98-1.07 px against 0.60-0.65 px,
        refinement then made them worse), or on a few frames and points (BENCHMARKS.md "Window
        checks"). A run that found no model at all is not repeated (it can take seconds)."""
        cfg = self.config
        limit = float(cfg.retry_above_error)
        if cfg.retry_above_ratio > 0 and self._errors:
            limit = min(limit, cfg.retry_above_ratio * float(np.median(self._errors)))
        best: SfmResult | None = None
        best_key: tuple = ()
        attempts: list[dict] = []
        for attempt in range(cfg.mapping_attempts):
            t0 = time.perf_counter()
            recs = self._map(names, token, cfg.seed + attempt)
            self._check_cancel(token)
            result = self._collect(recs, names, timings)
            error = result.reprojection_error
            attempts.append({"seed": cfg.seed + attempt, "registered": result.num_registered,
                             "points": result.num_points, "reprojection_error": error,
                             "seconds": time.perf_counter() - t0, "kept": False})
            key = (result.ok, result.num_registered, -error)  # more is better
            if best is None or key > best_key:
                best, best_key, kept = result, key, attempts[-1]
            if not (kept["reprojection_error"] > limit if best.ok else best.num_registered > 0):
                break
        kept["kept"] = True
        best.attempts = attempts
        if best.ok:
            self._errors.append(kept["reprojection_error"])
        return best

    def _torch_timings(self, timings: dict[str, float], stage: str, ran) -> None:
        """The torch features' steps inside a stage (e.g. ``extract.detect_describe``,
        ``match.verify``), when sfm.features is "torch" and the stage ran."""
        if self._torch_db is not None and ran:
            timings.update((f"{stage}.{k}", v) for k, v in self._torch_db.timings.items())

    def _check_cancel(self, token) -> None:
        if self._cancelled or token.is_cancelled:
            raise SfmCancelled("SfM cancelled")

    def _extract(self, frames: Sequence[Frame], intr: Intrinsics, token) -> None:
        import pycolmap

        if not frames:
            return
        self.image_dir.mkdir(parents=True, exist_ok=True)
        for f in frames:
            cv2.imwrite(str(self.image_dir / f"{f.name}.png"),
                        cv2.cvtColor(f.image, cv2.COLOR_RGB2BGR),
                        [cv2.IMWRITE_PNG_COMPRESSION, 1])
        cfg = self.config
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        # COLMAP puts pixel centres at +0.5; our intrinsics use OpenCV's integer centres.
        reader.camera_params = f"{intr.fx},{intr.fy},{intr.cx + 0.5},{intr.cy + 0.5}"
        if self._camera_id is not None:
            reader.existing_camera_id = self._camera_id
        if cfg.features == "torch":
            self._extract_torch(frames, reader)
        else:
            self._extract_colmap(frames, reader, token)
        for f in frames:
            (self.image_dir / f"{f.name}.png").unlink(missing_ok=True)  # keypoints suffice now
        with pycolmap.Database.open(self.database_path) as db:
            if self._camera_id is None:
                self._camera_id = int(db.read_all_cameras()[0].camera_id)
        self._names.extend(f.name for f in frames)
        self.frames_extracted += len(frames)

    def _torch_features(self):
        from sfm_ttr_ros.core.sfm.features.database import TorchFeatureDatabase
        from sfm_ttr_ros.core.sfm.features.sift_torch import TorchSiftConfig

        if self._torch_db is None:
            cfg = self.config
            sift = TorchSiftConfig(first_octave=cfg.first_octave,
                                   max_num_features=cfg.max_num_features)
            self._torch_db = TorchFeatureDatabase(self.database_path, self.feature_device,
                                                  sift, keep=cfg.overlap + 2)
        return self._torch_db

    def _extract_torch(self, frames: Sequence[Frame], reader) -> None:
        """sfm.features "torch": images imported by pycolmap (camera, rig, frame), then torch
        SIFT keypoints and descriptors written into the database (core/features_database)."""
        import pycolmap

        with pycolmap.Database.open(self.database_path):
            pass  # import_images needs the database file to exist
        pycolmap.import_images(self.database_path, self.image_dir,
                               camera_mode=pycolmap.CameraMode.SINGLE,
                               image_names=[f"{f.name}.png" for f in frames], options=reader)
        self._torch_features().extract([(f"{f.name}.png", f.image) for f in frames],
                                       self.config.max_image_size)

    def _extract_colmap(self, frames: Sequence[Frame], reader, token) -> None:
        import pycolmap

        cfg = self.config
        ext = pycolmap.FeatureExtractionOptions()
        ext.num_threads = cfg.num_threads
        ext.max_image_size = cfg.max_image_size if cfg.max_image_size > 0 else -1
        ext.sift.max_num_features = cfg.max_num_features
        ext.sift.first_octave = cfg.first_octave
        pycolmap.extract_features(
            self.database_path, self.image_dir, image_names=[f"{f.name}.png" for f in frames],
            camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
            extraction_options=ext, device=pycolmap.Device.cpu, cancellation_token=token,
        )

    def _match(self, token) -> None:
        import pycolmap

        cfg = self.config
        if cfg.features == "torch":
            # sequential matching in stream order, each pair verified by pycolmap
            self._torch_features().match([f"{n}.png" for n in self._names], cfg.overlap,
                                         cfg.num_threads, token,
                                         check=lambda: self._check_cancel(token))
            return
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = cfg.num_threads
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = cfg.overlap
        pairing.quadratic_overlap = False
        pairing.loop_detection = False  # would download a vocabulary tree and abort offline
        pycolmap.match_sequential(self.database_path, matching_options=matching,
                                  pairing_options=pairing, device=pycolmap.Device.cpu,
                                  cancellation_token=token)

    def _precheck(self, names: list[str]) -> str:
        """Cheap reasons a window cannot be reconstructed, before the (slow) mapper runs."""
        import pycolmap

        with pycolmap.Database.open(self.database_path) as db:
            ids = {img.name: int(img.image_id) for img in db.read_all_images()}
            window_ids = {ids[f"{n}.png"] for n in names if f"{n}.png" in ids}
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
                if m is None or len(m) < 15:
                    continue
                verified += 1
                k1 = db.read_keypoints(i1)[m[:, 0], :2]
                k2 = db.read_keypoints(i2)[m[:, 1], :2]
                best_parallax = max(best_parallax,
                                    float(np.median(np.linalg.norm(k1 - k2, axis=1))))
        if verified == 0:
            return "no frame pair of the window could be matched"
        if best_parallax < self.config.min_parallax_px:
            return (f"too little motion: median keypoint motion {best_parallax:.2f} px < "
                    f"{self.config.min_parallax_px} px")
        return ""

    def _mapper_options(self, names: list[str], seed: int):
        import pycolmap

        cfg = self.config
        opts = pycolmap.IncrementalPipelineOptions()
        opts.image_names = [f"{n}.png" for n in names]
        opts.multiple_models = False
        opts.min_model_size = 2
        opts.num_threads = cfg.num_threads
        opts.random_seed = seed
        opts.extract_colors = False  # images are deleted after extraction; colours come later
        opts.ba_refine_focal_length = cfg.refine_intrinsics
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
        m = opts.mapper
        m.init_max_forward_motion = cfg.init_max_forward_motion
        m.init_min_tri_angle = cfg.init_min_tri_angle
        m.init_min_num_inliers = cfg.init_min_num_inliers
        m.abs_pose_refine_focal_length = cfg.refine_intrinsics
        m.abs_pose_refine_extra_params = False
        m.filter_max_reproj_error = cfg.max_reproj_error
        m.filter_min_tri_angle = cfg.min_tri_angle
        m.num_threads = cfg.num_threads
        m.random_seed = seed
        opts.triangulation.min_angle = cfg.min_tri_angle
        return opts

    def _map(self, names: list[str], token, seed: int):
        import pycolmap

        out = self.workspace / "sparse"
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir(parents=True)
        return pycolmap.incremental_mapping(self.database_path, self.image_dir, out,
                                            options=self._mapper_options(names, seed),
                                            cancellation_token=token)

    def _collect(self, recs, names: list[str], timings: dict[str, float]) -> SfmResult:
        if not recs:
            return SfmResult(False, "mapping found no initial pair / produced no model",
                             len(names), timings=timings)
        rec = max(recs.values(), key=lambda r: r.num_reg_images())
        result = SfmResult(True, "", len(names), timings=timings)
        cam = next(iter(rec.cameras.values()))
        fx, fy, cx, cy = (float(v) for v in cam.params[:4])
        result.intrinsics = Intrinsics(fx, fy, cx - 0.5, cy - 0.5, cam.width, cam.height)
        wanted = {f"{n}.png": n for n in names}
        for image in rec.images.values():
            if not image.has_pose or image.name not in wanted:
                continue
            T = image.cam_from_world().matrix()
            R, t = T[:, :3], T[:, 3]
            obs = [(p.xy, p.point3D_id) for p in image.points2D if p.has_point3D()]
            if not obs:
                continue
            xy = np.array([o[0] for o in obs], np.float64)
            pids = np.array([o[1] for o in obs], np.int64)
            X = np.array([rec.points3D[int(i)].xyz for i in pids])
            Xc = X @ R.T + t
            cam = image.camera
            fx, fy, cx, cy = cam.params[:4]
            proj = np.stack([fx * Xc[:, 0] / Xc[:, 2] + cx, fy * Xc[:, 1] / Xc[:, 2] + cy], 1)
            track_err = np.array([rec.points3D[int(i)].error for i in pids])
            result.frames[wanted[image.name]] = FrameObservations(
                name=wanted[image.name],
                pixels=(xy - 0.5).astype(np.float32),
                depths=Xc[:, 2],
                reproj_errors=np.linalg.norm(proj - xy, axis=1),
                track_errors=track_err,
                point_ids=pids,
                cam_from_world=np.vstack([T, [0, 0, 0, 1]]),
            )
        pids = np.array(sorted(rec.points3D.keys()), np.int64)
        result.point_ids = pids
        result.points_xyz = np.array([rec.points3D[int(i)].xyz for i in pids]).reshape(-1, 3)
        result.points_error = np.array([rec.points3D[int(i)].error for i in pids])
        cfg = self.config
        if result.num_registered < cfg.min_registered:
            result.ok = False
            result.reason = (f"only {result.num_registered} of {len(names)} frames registered "
                             f"(< {cfg.min_registered})")
        elif result.num_points < cfg.min_points:
            result.ok = False
            result.reason = f"only {result.num_points} 3D points (< {cfg.min_points})"
        return result

    def _prune_cache(self, keep: set[str]) -> None:
        """Bound the database: past ``max_cached_frames`` cached frames, start a fresh one."""
        if len(self._names) > self.max_cached_frames and not keep.issuperset(self._names):
            self.reset()


def image_digest(image: np.ndarray) -> bytes:
    """Identity of a frame's pixels (a few ms for a full KITTI frame)."""
    h = hashlib.blake2b(digest_size=16)
    h.update(repr((image.shape, image.dtype.str)).encode())
    h.update(np.ascontiguousarray(image).data)
    return h.digest()


def _point_colours(result: SfmResult, images: dict[str, np.ndarray]) -> np.ndarray:
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


def reconstruct_window(frames: Sequence[Frame], intrinsics: Intrinsics,
                       config: SfmConfig | None = None) -> SfmResult:
    """One-shot reconstruction of a window in a temporary workspace."""
    with SfmReconstructor(config) as rec:
        return rec.reconstruct(frames, intrinsics)
