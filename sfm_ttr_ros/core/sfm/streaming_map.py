"""A reconstruction that carries over from window to window: stage 1 of SfM-TTR (Izquierdo &
Civera, CVPR 2023, Sec. 3.1) on a stream.

:class:`StreamingSfm` takes each keyframe as it arrives (:meth:`StreamingSfm.admit`: the front
end's features and verified pairs, then the frame registered into the map, triangulated and
locally adjusted), and gives a window the same :class:`SfmResult` the batch
:class:`SfmReconstructor` gives (:meth:`StreamingSfm.reconstruct`): D_sfm = [R_j X_l + t_j]_z,
p_lj and r_lj of every registered frame of the window, read from the shared map, so consecutive
windows share one scale. A fresh mapping of the window alone (the batch reconstructor's mapper
runs: seeds, retries, the best kept) replaces the continuation when there is no map or the
continuation fits badly; ``attempts`` and the result's ``mapping`` and ``mapping_reason`` say
which and why. After a window the map keeps its last ``sfm.overlap`` frames (the next frames'
match partners) and deregisters the rest.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence

import numpy as np

from sfm_ttr_ros.core.frames import Frame, Intrinsics, check_window
from sfm_ttr_ros.core.sfm.frontend import AdmitTimings, StreamFrontend
from sfm_ttr_ros.core.sfm.map_cache import build_cache, continue_reconstruction
from sfm_ttr_ros.core.sfm.mapping import Mapper, mapper_options, rank
from sfm_ttr_ros.core.sfm.names import frame_name
from sfm_ttr_ros.core.sfm.result import SfmResult, collect_result, point_colours
from sfm_ttr_ros.core.sfm.sfm_config import SfmConfig

log = logging.getLogger(__name__)


#: frames of the map before a window mapped afresh with it (its anchors: the camera's path
#: chains through them)
FRESH_ANCHORS = 3


#: the keys of :meth:`StreamingSfm.stats` that count (they only grow), and the one that does not
STATS_COUNTS = ("continued", "fresh", "frames_extracted")
STATS_KEYS = (*STATS_COUNTS, "admitted_unmapped")


#: a continuation that registered fewer than this fraction of a window's frames (or failed, or
#: fits worse than the batch mapper's retry limit) is replaced by a fresh mapping
MIN_REGISTERED_FRACTION = 0.8


class WindowMapper:
    """The batch reconstructor's fresh mapping (its :class:`Mapper`: options, seeds, retry rule
    and result), run over a cache of the front end's data instead of a database."""

    def __init__(self, config: SfmConfig, frontend: StreamFrontend):
        self.config = config
        self.frontend = frontend
        self.mapper = Mapper(None, runner=self._map)
        self.recs: dict[int, object] = {}  # seed -> the largest model of that mapper run

    def map_best(self, names: list[str], timings: dict[str, float]) -> SfmResult:
        """The batch mapper's best of its runs over ``names`` (never cancelled)."""
        import pycolmap

        self.recs.clear()
        return self.mapper.map_best(self.config, names, timings, pycolmap.CancellationToken(),
                                    check=lambda: None)

    def collect(self, rec, names: list[str], timings: dict[str, float]) -> SfmResult:
        """The window's result read from ``rec`` (the batch reconstructor's collection)."""
        return collect_result({0: rec}, names, timings, self.config)

    def error_limit(self) -> float:
        """The mean reprojection error above which the batch mapper runs again."""
        return self.mapper.retry_limit(self.config)

    def options(self):
        """The batch mapper's options (no image list: the cache holds exactly the frames)."""
        return mapper_options(self.config, [], self.config.seed)

    def _map(self, config: SfmConfig, names: list[str], token, seed: int):
        import pycolmap

        manager = pycolmap.ReconstructionManager()
        pipeline = pycolmap.IncrementalPipeline(mapper_options(config, names, seed),
                                                build_cache(self.frontend, names), manager)
        pipeline.run()
        recs = {i: manager.get(i) for i in range(manager.size())}
        if recs:
            self.recs[seed] = max(recs.values(), key=lambda r: r.num_reg_images())
        return recs


class StreamingSfm:
    """One stream's SfM: features as keyframes arrive, one map continued across windows."""

    def __init__(self, config: SfmConfig | None = None):
        self.config = config or SfmConfig()
        self.frontend = StreamFrontend(self.config)
        self._fresh = WindowMapper(self.config, self.frontend)
        self.rec = None  # pycolmap.Reconstruction: the map
        self._generation = self.frontend.generation
        self._open: list[str] = []  # admitted, not yet reconstructed in a window
        # name -> (SIFT, matching and verification, mapping on admit) s
        self._spent: dict[str, tuple[float, float, float]] = {}
        self.continuations = 0
        self.fresh_mappings = 0

    def close(self) -> None:
        """Nothing on disk: the front end and the map live in memory."""

    def __enter__(self) -> StreamingSfm:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- per frame ---------------------------------------------------------------------------
    def admit(self, frame: Frame, intrinsics: Intrinsics) -> AdmitTimings:
        """A keyframe arrives: its features and verified pairs, then it is registered into the
        map (when there is one), triangulated and locally adjusted."""
        timings = self.frontend.admit(frame, intrinsics)
        if self.frontend.generation != self._generation:
            self._generation = self.frontend.generation
            self._drop_map("the front end started afresh")
        if timings.extract == 0.0 and frame.name in self._spent:
            return timings  # held already with the same pixels
        if frame.name not in self._open:
            self._open.append(frame.name)
        self._pin()
        t0 = time.perf_counter()
        if self.rec is not None:
            self._extend()
        self._spent[frame.name] = (timings.extract, timings.match + timings.verify,
                                   time.perf_counter() - t0)
        return timings

    def retain(self, names: Sequence[str]) -> None:
        """The stream's future windows hold only ``names`` among the frames admitted and not yet
        reconstructed: the others (left a window without one: overload, a flush, a stamp that
        went back) are forgotten, so the map neither registers nor pins them."""
        keep = set(names)
        gone = [n for n in self._open if n not in keep]
        if not gone:
            return
        self._open = [n for n in self._open if n in keep]
        for n in gone:
            self._spent.pop(n, None)
        self._pin()
        self.frontend.prune()

    def set_config(self, config: SfmConfig) -> None:
        """New SfM options from the next frame on (the mapper's at once, the SIFT options for
        the frames extracted from now)."""
        self.config = config
        self.frontend.config = config
        self._fresh.config = config

    def unmapped(self) -> int:
        """Keyframes admitted but not registered into the map yet (the front end's lag)."""
        registered = set(self._registered_names())
        return sum(n not in registered for n in self._open)

    def stats(self) -> dict[str, int]:
        """Windows continued and mapped afresh, frames whose features were extracted,
        keyframes admitted but not registered yet (:meth:`unmapped`): :data:`STATS_KEYS`."""
        return {"continued": self.continuations, "fresh": self.fresh_mappings,
                "admitted_unmapped": self.unmapped(),
                "frames_extracted": self.frontend.frames_extracted}

    def held_frames(self) -> list[str]:
        """The frames whose features the front end holds, oldest first."""
        return list(self.frontend.features)

    # -- per window --------------------------------------------------------------------------
    def reconstruct(self, frames: Sequence[Frame], intrinsics: Intrinsics) -> SfmResult:
        """The window's :class:`SfmResult` from the shared map (frames not admitted yet are
        admitted first). Never raises for a window that cannot be reconstructed; raises
        :class:`InputError` for bad input."""
        check_window(frames, intrinsics)
        names = [f.name for f in frames]
        if len(frames) < 2:
            return SfmResult(False, "a window needs at least 2 frames", len(frames))
        for f in frames:  # the stream admitted most of them already: not hashed again
            if (f.name not in self._spent or f.name not in self.frontend.features
                    or intrinsics != self.frontend.intrinsics):
                self.admit(f, intrinsics)
        # the batch's keys (extract, match: matching and verification) and the front end's sum
        timings = {k: sum(self._spent[n][i] for n in names)
                   for i, k in enumerate(("extract", "match", "map_on_admit"))}
        timings["frontend"] = timings["extract"] + timings["match"]
        t0 = time.perf_counter()
        result = self._map_window(names, timings)
        timings["map"] = time.perf_counter() - t0
        result.timings = timings
        if result.num_points:
            result.points_rgb = point_colours(result, {f.name: f.image for f in frames})
        self._slide(names)
        return result

    def _map_window(self, names: list[str], timings: dict[str, float]) -> SfmResult:
        """The continued map's result for ``names``, or a fresh mapping's when the
        continuation fits badly (the better of the two is kept)."""
        import pycolmap

        continued, reason = None, "no map to continue"
        if self.rec is not None:
            self._extend()
            continued = self._window_result(self.rec, names, timings)
            reason = self._fit_reason(continued, len(names))
            if not reason:
                return self._keep_continued(continued, "")
        fresh = self._fresh_with_anchors(names, timings)
        if continued is not None and rank(continued) >= rank(fresh):
            return self._keep_continued(continued, reason + "; a fresh mapping did no better")
        kept = next((a for a in fresh.attempts if a["kept"]), None)
        if fresh.ok and kept is not None:
            self.rec = pycolmap.Reconstruction(self._fresh.recs[kept["seed"]])
        else:
            self._drop_map(f"fresh mapping failed: {fresh.reason}")
        for attempt in fresh.attempts:
            attempt["mode"] = "fresh"
        fresh.attempts.insert(0, {"mode": "continue", "rejected": reason})
        self.fresh_mappings += 1
        fresh.mapping, fresh.mapping_reason = "fresh", reason
        log.info("window %s..%s mapped afresh: %s", names[0], names[-1], reason)
        return fresh

    def _fresh_with_anchors(self, names: list[str], timings: dict[str, float]) -> SfmResult:
        """A fresh mapping of the window with the map's last :data:`FRESH_ANCHORS` frames
        before it: they are kept apart in ``anchors`` (the window's frames, points and checks
        are its own), where the camera's path finds frames it already holds
        (core/camera_path.py) instead of a break."""
        anchors = [n for n in self._registered_names()
                   if n not in names and n in self.frontend.features][-FRESH_ANCHORS:]
        fresh = self._fresh.map_best(anchors + names, timings)
        fresh.anchors = {n: fresh.frames.pop(n) for n in anchors if n in fresh.frames}
        fresh.num_frames = len(names)
        return _window_points(fresh)

    def _keep_continued(self, result: SfmResult, note: str) -> SfmResult:
        result.attempts = [{"mode": "continue", "registered": result.num_registered,
                            "points": result.num_points,
                            "reprojection_error": result.reprojection_error, "kept": True,
                            "note": note}]
        if result.ok:
            self._fresh.mapper.errors.append(result.reprojection_error)
        self.continuations += 1
        result.mapping, result.mapping_reason = "continued", note
        return result

    def _fit_reason(self, result: SfmResult, num_frames: int) -> str:
        """Why a continued window fits badly ("" when it fits)."""
        if not result.ok:
            return f"continuation failed: {result.reason}"
        need = math.ceil(MIN_REGISTERED_FRACTION * num_frames)
        if result.num_registered < need:
            return (f"continuation registered {result.num_registered} of {num_frames} frames "
                    f"(< {need})")
        limit = self._fresh.error_limit()
        if result.reprojection_error > limit:
            return (f"continuation fits badly: mean reprojection error "
                    f"{result.reprojection_error:.2f} px > {limit:.2f} px")
        return ""

    def _window_result(self, rec, names: list[str], timings: dict[str, float]) -> SfmResult:
        return _window_points(self._fresh.collect(rec, names, timings))

    # -- the map -----------------------------------------------------------------------------
    def _registered_names(self) -> list[str]:
        return [frame_name(self.rec.image(i).name)
                for i in self.rec.reg_image_ids()] if self.rec is not None else []

    def _extend(self) -> None:
        """Register the open frames the map can take (a new cache and mapper over the map's
        frames and the open ones); a continuation that raises drops the map."""
        registered = self._registered_names()
        todo = [n for n in self._open if n not in registered and n in self.frontend.features]
        if not todo:
            return
        cache = build_cache(self.frontend, registered + todo)
        options = self._fresh.options()
        try:
            continue_reconstruction(self.rec, cache, options)
        except (RuntimeError, ValueError, IndexError) as exc:  # pycolmap's checks
            self._drop_map(f"continuation raised {type(exc).__name__}: {exc}")

    def _slide(self, names: list[str]) -> None:
        """Keep the window's last ``sfm.overlap`` registered frames (the next frames' match
        partners, and any frame admitted for the next window); deregister the rest and drop
        what only they held."""
        done = set(names)
        self._open = [n for n in self._open if n not in done]
        for n in names:
            self._spent.pop(n, None)
        if self.rec is not None:
            keep = set(names[-int(self.config.overlap):]) | set(self._open)
            for iid in list(self.rec.reg_image_ids()):
                image = self.rec.image(iid)
                if frame_name(image.name) not in keep:
                    self.rec.deregister_frame(image.frame_id)
            self.rec.tear_down()
        self._pin()
        self.frontend.prune()

    def _pin(self) -> None:
        self.frontend.pinned = set(self._registered_names()) | set(self._open)

    def _drop_map(self, reason: str) -> None:
        if self.rec is not None:
            log.info("streaming map dropped: %s", reason)
        self.rec = None


def _window_points(result: SfmResult) -> SfmResult:
    """Only the 3D points a window frame observes (the map also holds its anchors' points)."""
    if not result.frames or not result.num_points:
        return result
    seen = np.unique(np.concatenate([f.point_ids for f in result.frames.values()]))
    rows = np.isin(result.point_ids, seen)
    result.point_ids = result.point_ids[rows]
    result.points_xyz = result.points_xyz[rows]
    result.points_error = result.points_error[rows]
    return result


