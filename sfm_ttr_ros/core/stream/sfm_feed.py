"""What the stream hands the SfM stage before a window is due (:class:`SfmFeed`): under
``sfm.mode`` batch the frames of the next window once they are all queued, to begin its SfM
ahead; under ``sfm.mode`` streaming every keyframe as the window buffer takes it, so that its
features, matches and registration into the carried map are done while frames arrive and the
window only maps what is left (:class:`~sfm_ttr_ros.core.sfm.source.SfmSource`)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.stream.frame_queue import FrameQueue
from sfm_ttr_ros.core.stream.settings import StreamSettings


class SfmFeed:
    """The stream's side of the SfM source (``ttr.sfm``); ``warn(key, message)`` logs a
    throttled warning. :meth:`prefetch_next` runs on the submitting thread, the rest on the
    window worker."""

    def __init__(self, ttr, queue: FrameQueue, warn: Callable[[str, str], None]):
        self.ttr = ttr
        self._queue = queue
        self._warn = warn
        self._asked_ahead: tuple[str, ...] = ()  # the frames whose SfM was begun ahead last
        self._admitted: set[str] = set()  # keyframes handed to the streaming SfM

    @property
    def streaming(self) -> bool:
        """``sfm.mode`` streaming (read at each call: the config may change per window)."""
        return self.ttr is not None and self.ttr.config.sfm.mode == "streaming"

    def prefetch_next(self, s: StreamSettings) -> None:
        """Batch SfM: while a window runs, once the frames of the window after it are all
        queued (:meth:`FrameQueue.next_window`; every frame a keyframe), begin their SfM in the
        background (:meth:`SfmSource.prefetch`, which waits for the running window's own SfM:
        asked again at every frame that arrives). Cheap."""
        if (self.streaming or not s.prefetch_sfm or s.keyframe_policy != "all"
                or s.min_keyframe_interval_s > 0 or s.min_keyframe_motion > 0):
            return
        ahead = self._queue.next_window(s.window_stride, s.window_size - s.window_stride)
        if ahead is None or tuple(f.name for f in ahead[0]) == self._asked_ahead:
            return  # nothing to begin, or begun already (every later frame finds the same ones)
        frames, intr = ahead
        try:
            if self.ttr.sfm.prefetch(frames, intr):
                self._asked_ahead = tuple(f.name for f in frames)
        except Exception as exc:  # noqa: BLE001 - ahead of time only: the window does it itself
            self._warn("prefetch", f"SfM ahead of the next window not begun: {exc}")

    def admit_while_idle(self, buffered: Sequence[Frame], intr: Intrinsics) -> None:
        """Streaming SfM: the buffered keyframes' front end and registration into the carried
        map (:meth:`SfmSource.admit`), oldest first, while no frame waits in the queue. A
        keyframe's front end costs more than a 10-Hz camera's frame interval on 2 cores:
        admitted as it arrives, the worker fell behind the camera, the keyframe rule skipped its
        frames as stale and no window filled (one keyframe admitted in a 30-s feed). What is
        not admitted in idle time the window admits itself before it maps. A failure is logged:
        the window admits the frame again itself."""
        if not self.streaming:
            return
        for frame in buffered:
            if self._queue.queued() > 0:
                return
            if frame.name in self._admitted:
                continue
            self._admitted.add(frame.name)
            try:
                self.ttr.sfm.admit(frame, intr)
            except Exception as exc:  # noqa: BLE001 - the window's own SfM admits it again
                self._warn("sfm_admit", f"keyframe {frame.name} not admitted to the streaming "
                           f"SfM now: {type(exc).__name__}: {exc}")

    def retain(self, names: Sequence[str]) -> None:
        """Streaming SfM: the keyframes admitted that no future window takes (the buffer let
        them go without a window of theirs: a flush, a stamp that went back, an overloaded
        window) are forgotten by the carried map; ``names``: the buffer's keyframes."""
        self._admitted &= set(names)
        if self.streaming:
            self.ttr.sfm.retain(names)

    def counters(self) -> dict[str, object]:
        """SfM begun ahead (started, used, discarded) and the streaming SfM's windows continued
        and mapped afresh with its front end's lag ({} under batch)."""
        if self.ttr is None:
            return {"sfm_ahead": {}, "sfm_streaming": {}}
        return {"sfm_ahead": self.ttr.sfm.counters(),
                "sfm_streaming": self.ttr.sfm.streaming_counters() if self.streaming else {}}
