"""Stage 1 of SfM-TTR: sparse SfM over a window of frames with pycolmap.

For each registered frame j and each 3D point X_l it observes the reconstruction gives
(Izquierdo & Civera, CVPR 2023, Sec. 3.1):

* the SfM depth  D_sfm(l, j) = [R_j X_l + t_j]_z  (up to the reconstruction's unknown scale),
* the observed keypoint p_lj (not the reprojection), and
* that observation's reprojection error r_lj = ||π(R_j X_l + t_j) − p_lj||.

One PINHOLE camera with the known intrinsics held fixed, SIFT features, sequential matching and
incremental mapping with initialisation thresholds that accept forward driving (COLMAP's
defaults reject it).

Features are extracted once per frame and pairs matched once: a :class:`SfmReconstructor`
keeps one COLMAP database across the windows of a stream (:mod:`.workspace`), so overlapping
windows only pay for their new frames (:mod:`.extraction`). The mapper, which from the same
matches now and then settles on a wrong reconstruction, runs again with another seed while the
window's mean reprojection error is high, and the best-fitting reconstruction is kept
(:mod:`.mapping`); :mod:`.result` collects D_sfm, p_lj and r_lj.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Sequence
from pathlib import Path

from sfm_ttr_ros.core.frames import Frame, Intrinsics, check_window, image_digest
from sfm_ttr_ros.core.sfm.extraction import FeatureMatcher
from sfm_ttr_ros.core.sfm.mapping import Mapper
from sfm_ttr_ros.core.sfm.result import SfmResult, point_colours
from sfm_ttr_ros.core.sfm.sfm_config import SfmConfig
from sfm_ttr_ros.core.sfm.workspace import SfmWorkspace

log = logging.getLogger(__name__)

_PYCOLMAP_LOGGING_SET = False


def quiet_pycolmap(verbose: bool = False) -> None:
    """Keep COLMAP's glog output (and its log files in the temp folder) out of the user's way."""
    import pycolmap

    global _PYCOLMAP_LOGGING_SET
    pycolmap.logging.logtostderr = True
    pycolmap.logging.minloglevel = 0 if verbose else 3
    pycolmap.logging.verbose_level = 1 if verbose else 0
    _PYCOLMAP_LOGGING_SET = True


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
        self.workspace = SfmWorkspace(workspace)
        self.features = FeatureMatcher(self.workspace, feature_device)
        self.mapper = Mapper(self.workspace)
        self._db_features = self.config.features  # the feature kind the database holds
        self.max_cached_frames = max_cached_frames
        self._intrinsics: Intrinsics | None = None
        self.frames_extracted = 0
        self._lock = threading.Lock()
        self._token = None
        self._cancelled = False
        quiet_pycolmap(self.config.verbose)

    def reset(self) -> None:
        """Forget every cached frame (new database) and the stream's reconstruction errors."""
        self.workspace.reset()
        self.features.reset()
        self.mapper.reset()

    def close(self) -> None:
        self.workspace.close()

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

    def reconstruct(self, frames: Sequence[Frame], intrinsics: Intrinsics) -> SfmResult:
        """Reconstruct ``frames`` (one window). Never raises for a window that cannot be
        reconstructed (the result says why); raises :class:`InputError` for bad input and
        :class:`SfmCancelled` when cancelled."""
        import pycolmap

        check_window(frames, intrinsics)
        self._cancelled = False
        self._renew_database(intrinsics)
        if len(frames) < 2:
            return SfmResult(False, "a window needs at least 2 frames", len(frames))
        digests = {f.name: image_digest(f.image) for f in frames}
        changed = [n for n, d in digests.items() if self.workspace.digests.get(n, d) != d]
        if changed:
            log.info("frame %s came back with other pixels: new SfM database", changed[0])
            self.reset()
        names = [f.name for f in frames]
        if self.workspace.full(set(names), self.max_cached_frames):
            self.reset()  # bound the database: a fresh one past max_cached_frames
        token = pycolmap.CancellationToken()
        with self._lock:
            self._token = token
        try:
            result = self._run(frames, digests, intrinsics, token)
        finally:
            with self._lock:
                self._token = None
        if result.num_points:
            result.points_rgb = point_colours(result, {f.name: f.image for f in frames})
        return result

    def _renew_database(self, intrinsics: Intrinsics) -> None:
        """A fresh database for other intrinsics (e.g. a resolution change) or another feature
        kind (keypoints of one kind are never matched with the other's)."""
        if self._intrinsics != intrinsics:
            if self._intrinsics is not None:
                self.reset()
            self._intrinsics = intrinsics
        if self.workspace.names and self._db_features != self.config.features:
            self.reset()
        self._db_features = self.config.features

    def _run(self, frames: Sequence[Frame], digests: dict[str, bytes], intrinsics: Intrinsics,
             token) -> SfmResult:
        """Extraction of the new frames, matching, the prechecks and the mapper, timed."""
        cfg, timings = self.config, {}
        names = [f.name for f in frames]
        t0 = time.perf_counter()
        new = [f for f in frames if f.name not in self.workspace.digests]
        self.features.extract(cfg, new, intrinsics, token)
        self.frames_extracted += len(new)
        self.workspace.digests.update((f.name, digests[f.name]) for f in new)
        timings["extract"] = time.perf_counter() - t0
        self.features.torch_timings(timings, "extract", new)
        self._check_cancel(token)

        t0 = time.perf_counter()
        self.features.match(cfg, token, check=lambda: self._check_cancel(token))
        timings["match"] = time.perf_counter() - t0
        self.features.torch_timings(timings, "match", True)
        self._check_cancel(token)

        reason = self.mapper.precheck(cfg, names)
        if reason:
            return SfmResult(False, reason, len(frames), timings=timings)
        t0 = time.perf_counter()
        result = self.mapper.map_best(cfg, names, timings, token,
                                      check=lambda: self._check_cancel(token))
        timings["map"] = time.perf_counter() - t0
        return result

    def _check_cancel(self, token) -> None:
        if self._cancelled or token.is_cancelled:
            raise SfmCancelled("SfM cancelled")
