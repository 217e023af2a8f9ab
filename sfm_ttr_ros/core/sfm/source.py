"""Where a window's reconstruction comes from: one interface (:class:`SfmSource`), two kinds,
chosen once from ``sfm.mode`` by :func:`make_sfm_source`.

Batch (``sfm.mode: batch``, :class:`BatchSfmSource`): the window worker's reconstructor after
the window's last frame, or the reconstruction begun ahead
(:class:`~sfm_ttr_ros.core.sfm.prefetch.SfmPrefetch`) with its gate: no SfM is begun ahead while
the running window's own SfM has not ended (on a few cores two reconstructions at once slow
the current window's: docs/decisions.md, "Live serving"); the stream asks again at its next
frame. Keyframes are not
admitted one by one: the window does it all after its last frame.

Streaming (``sfm.mode: streaming``, :class:`StreamingSfmSource`): the stream's
:class:`~sfm_ttr_ros.core.sfm.streaming_map.StreamingSfm`, in a process of its own
(:class:`~sfm_ttr_ros.core.sfm.sfm_process.StreamingSfmProcess`: pycolmap's extractor and
mapper keep the GIL, which stalled live serving). The stream admits each keyframe as it
takes it (:meth:`SfmSource.admit`: features, matches, registration into the map), so a window's
:meth:`SfmSource.reconstruct` only maps what is left and collects; a fresh mapping replaces the
continuation when it fits badly (the result's ``mapping`` and ``mapping_reason`` say which and
why). Nothing is begun ahead (nothing is left to begin).

A configuration of the other mode (:func:`reconfigure_sfm_source`) closes the source and makes
one of that mode.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Protocol

from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.sfm.prefetch import SfmPrefetch
from sfm_ttr_ros.core.sfm.reconstruction import SfmReconstructor
from sfm_ttr_ros.core.sfm.result import SfmResult
from sfm_ttr_ros.core.sfm.sfm_config import SfmConfig
from sfm_ttr_ros.core.sfm.sfm_process import StreamingSfmProcess

#: what :meth:`SfmSource.counters` gives for reconstructions begun ahead when none can be
NOTHING_AHEAD = {"started": 0, "used": 0, "discarded": 0}


class SfmSource(Protocol):
    """A stream's reconstructions, one window after the other (stage 1, Sec. 3.1): the one
    interface the pipeline and the stream call, whatever ``mode``."""

    mode: str  # the sfm.mode this kind of source serves
    config: SfmConfig
    workspace: str | Path | None  # the batch reconstructor's folder (None: a temporary one)
    nice: int  # OS priority of its threads or process of its own (the window worker's)

    def reconstruct(self, frames: Sequence[Frame], intrinsics: Intrinsics
                    ) -> tuple[SfmResult, bool]:
        """The window's reconstruction (Sec. 3.1; how it was mapped in its ``mapping``) and
        whether it was made ahead (while the previous window refined)."""
        ...

    def begin_window(self) -> None:
        """A window begins (its own reconstruction follows)."""
        ...

    def warm_up(self) -> None:
        """Pay the source's one-time costs now (the window worker's warm-up)."""
        ...

    def admit(self, frame: Frame, intrinsics: Intrinsics) -> bool:
        """A keyframe the stream took into the window being filled; True when the source did
        its share of the window's SfM now, False when it does it all at the window's end."""
        ...

    def retain(self, names: Sequence[str]) -> None:
        """The frames the stream's future windows may still take; the others admitted are
        forgotten."""
        ...

    def prefetch(self, frames: Sequence[Frame], intrinsics: Intrinsics) -> bool:
        """Begin the SfM of a coming window now, in the background; False when nothing was
        begun (the source begins nothing ahead, or not now)."""
        ...

    def counters(self) -> dict[str, dict[str, int]]:
        """What /diagnostics counts: ``sfm_ahead`` (reconstructions begun ahead: started, used
        by their window, discarded) and ``sfm_streaming`` (windows continued and mapped afresh,
        keyframes admitted but not registered into the map yet, SfM processes that died and
        were replaced; {} for batch)."""
        ...

    @property
    def frames_extracted(self) -> int:
        """Frames whose features the window's reconstructions extracted."""
        ...

    def set_config(self, config: SfmConfig) -> None:
        """New options of the same ``sfm.mode``, from the next reconstruction on."""
        ...

    def cancel(self) -> None:
        """Interrupt the running reconstructions (from another thread)."""
        ...

    def close(self) -> None:
        """Stop and free what the source holds (threads, workspaces)."""
        ...


class BatchSfmSource:
    """``sfm.mode: batch``: the window's own reconstruction, or the one begun ahead of it
    (:class:`SfmSource`)."""

    mode = "batch"

    def __init__(self, config: SfmConfig, workspace: str | Path | None = None):
        self.config = config
        self.workspace = workspace
        self.nice = 0
        self.reconstructor = SfmReconstructor(config, workspace)
        self._prefetch: SfmPrefetch | None = None  # created at the first prefetch()
        # a window runs and its own SfM has not ended yet (set by begin_window, cleared once
        # its SfM ends; a window that stops before SfM runs none, so nothing waits on it)
        self._own_pending = False
        self._closed = False  # nothing begun ahead once closed (a new source took over)
        self._lock = threading.Lock()

    def set_config(self, config: SfmConfig) -> None:
        self.config = config
        self.reconstructor.config = config
        if self._prefetch is not None:
            self._prefetch.set_config(config)

    def begin_window(self) -> None:
        """A window begins: no SfM is begun ahead until its own has ended."""
        self._own_pending = True

    def warm_up(self) -> None:
        """Nothing to pay ahead."""

    def reconstruct(self, frames: Sequence[Frame], intrinsics: Intrinsics
                    ) -> tuple[SfmResult, bool]:
        try:
            sfm = (self._prefetch.take(frames, intrinsics) if self._prefetch is not None
                   else None)
            if sfm is not None:
                return sfm, True
            return self.reconstructor.reconstruct(frames, intrinsics), False
        finally:
            self._own_pending = False

    def admit(self, frame: Frame, intrinsics: Intrinsics) -> bool:
        """Nothing now (False): the window does it all after its last frame."""
        return False

    def retain(self, names: Sequence[str]) -> None:
        """Nothing admitted, nothing to forget."""

    def prefetch(self, frames: Sequence[Frame], intrinsics: Intrinsics) -> bool:
        """Begin the SfM of a coming window now, in the background; :meth:`reconstruct` of
        exactly these frames then takes it. False when one is still running, or while the
        current window has not finished its own SfM (module docstring)."""
        if self._own_pending or self._closed:
            return False
        with self._lock:
            if self._prefetch is None:
                self._prefetch = SfmPrefetch(self.config, self.nice)
        return self._prefetch.start(frames, intrinsics)

    def counters(self) -> dict[str, dict[str, int]]:
        ahead = self._prefetch.counters() if self._prefetch is not None else dict(NOTHING_AHEAD)
        return {"sfm_ahead": ahead, "sfm_streaming": {}}

    @property
    def frames_extracted(self) -> int:
        return self.reconstructor.frames_extracted

    def cancel(self) -> None:
        self.reconstructor.cancel()
        if self._prefetch is not None:
            self._prefetch.cancel()

    def close(self) -> None:
        self._closed = True
        self.reconstructor.close()
        if self._prefetch is not None:
            self._prefetch.close()


class StreamingSfmSource:
    """``sfm.mode: streaming``: the stream's carried map (:class:`StreamingSfm`), each keyframe
    admitted as the stream takes it (:class:`SfmSource`).

    While the focal length of assumed intrinsics is refined (``refine_intrinsics``, set window
    by window by :class:`~sfm_ttr_ros.core.sfm.self_calibration.SelfCalibration` till it
    settles), each window is mapped on its own by a batch :class:`SfmReconstructor` (the
    carried map holds one camera fixed) and nothing is admitted ahead; once it is off again a
    fresh map starts, its keyframes admitted with the focal length the windows are mapped
    with (the settled estimate), not the assumed one."""

    mode = "streaming"

    def __init__(self, config: SfmConfig, workspace: str | Path | None = None):
        self.config = config
        self.workspace = workspace  # the calibrating windows' (and a batch source's) folder
        self.streaming = StreamingSfmProcess(config)
        self.calibrating: SfmReconstructor | None = None  # while refine_intrinsics is on
        self._extracted_before = 0  # frames extracted by the calibrating reconstructors gone
        # the intrinsics the last window of assumed intrinsics was mapped with
        self._assumed_as: Intrinsics | None = None

    @property
    def nice(self) -> int:
        """The SfM process's OS priority (the window worker's), set before it starts."""
        return self.streaming.nice

    @nice.setter
    def nice(self, value: int) -> None:
        self.streaming.nice = value

    def warm_up(self) -> None:
        """Start the SfM process (its imports), unless the focal length is refined."""
        if self.calibrating is None:
            self.streaming.start()

    def set_config(self, config: SfmConfig) -> None:
        self.config = config
        if config.refine_intrinsics:
            if self.calibrating is None:
                self.calibrating = SfmReconstructor(config, self.workspace)
            self.calibrating.config = config
            return
        if self.calibrating is not None:  # the focal length settled: a fresh map with it
            self._extracted_before += self.calibrating.frames_extracted
            self.calibrating.close()
            self.calibrating = None
            self.streaming.afresh(config)
        self.streaming.set_config(config)

    def reconstruct(self, frames: Sequence[Frame], intrinsics: Intrinsics
                    ) -> tuple[SfmResult, bool]:
        if frames and all(f.assumed_intrinsics for f in frames):
            self._assumed_as = intrinsics
        if self.calibrating is not None:
            return self.calibrating.reconstruct(frames, intrinsics), False
        return self.streaming.reconstruct(frames, intrinsics), False

    def begin_window(self) -> None:
        """Nothing waits on a window's own SfM (nothing is begun ahead)."""

    def prefetch(self, frames: Sequence[Frame], intrinsics: Intrinsics) -> bool:
        """Nothing is begun ahead (False): the keyframes admitted leave only the mapping."""
        return False

    def admit(self, frame: Frame, intrinsics: Intrinsics) -> bool:
        """The keyframe's features, matches and registration into the carried map now (assumed
        intrinsics: with the focal length the windows are mapped with); nothing while the
        focal length is refined (False: the window maps it all)."""
        if self.calibrating is not None:
            return False
        self.streaming.admit(frame, self._as_mapped(frame, intrinsics))
        return True

    def _as_mapped(self, frame: Frame, intrinsics: Intrinsics) -> Intrinsics:
        """``intrinsics``, or for a frame of assumed ones of the last such window's image and
        principal point, the intrinsics that window was mapped with (its focal length)."""
        last = self._assumed_as
        same = last is not None and (last.width, last.height, last.cx, last.cy) == (
            intrinsics.width, intrinsics.height, intrinsics.cx, intrinsics.cy)
        return last if frame.assumed_intrinsics and same else intrinsics

    def retain(self, names: Sequence[str]) -> None:
        """The admitted frames outside ``names`` are forgotten (:meth:`StreamingSfm.retain`)."""
        self.streaming.retain(names)

    def counters(self) -> dict[str, dict[str, int]]:
        st = self.streaming.stats()
        return {"sfm_ahead": dict(NOTHING_AHEAD),
                "sfm_streaming": {**{k: st[k] for k in ("continued", "fresh",
                                                        "admitted_unmapped")},
                                  "process_restarts": self.streaming.restarts}}

    @property
    def frames_extracted(self) -> int:
        calibrating = self.calibrating.frames_extracted if self.calibrating is not None else 0
        return (self._extracted_before + calibrating
                + self.streaming.stats()["frames_extracted"])

    def cancel(self) -> None:
        """Interrupt a calibrating window's reconstruction; a window's mapping of the carried
        map runs to its end (never cancelled)."""
        if self.calibrating is not None:
            self.calibrating.cancel()

    def close(self) -> None:
        if self.calibrating is not None:
            self.calibrating.close()
        self.streaming.close()


#: the source of each sfm.mode
_SOURCES: dict[str, type[BatchSfmSource | StreamingSfmSource]] = {
    s.mode: s for s in (BatchSfmSource, StreamingSfmSource)}


def make_sfm_source(config: SfmConfig, workspace: str | Path | None = None) -> SfmSource:
    """The source ``sfm.mode`` says (``workspace``: the batch reconstructor's folder; a
    temporary one when None)."""
    return _SOURCES[config.mode](config, workspace)


def reconfigure_sfm_source(source: SfmSource, config: SfmConfig) -> SfmSource:
    """``source`` with the options ``config``, or, when ``config`` is of another ``sfm.mode``, a
    new source of that mode (``source`` closed; its workspace and ``nice`` carried over)."""
    if source.mode == config.mode:
        source.set_config(config)
        return source
    source.close()
    fresh = make_sfm_source(config, source.workspace)
    fresh.nice = source.nice
    return fresh
