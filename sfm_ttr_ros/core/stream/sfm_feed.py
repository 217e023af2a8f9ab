"""What the stream hands the SfM source (:class:`~sfm_ttr_ros.core.sfm.source.SfmSource`)
before a window is due (:class:`SfmFeed`): the frames of the next window once they are all
queued, to begin its SfM ahead (the batch source begins it), and every keyframe as the window
buffer takes it, so that its features, matches and registration into the carried map are done
while frames arrive and the window only maps what is left (the streaming source takes it). The
source says what it does with each; the feed never asks which kind it is."""

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
        self._admitted: set[str] = set()  # keyframes the SfM source took ahead of the window

    def prefetch_next(self, s: StreamSettings) -> None:
        """While a window runs, once the frames of the window after it are all queued
        (:meth:`FrameQueue.next_window`; every frame a keyframe), ask the SfM source to begin
        their SfM in the background (:meth:`SfmSource.prefetch`: the batch source does, once the
        running window's own SfM has ended: asked again at every frame that arrives). Cheap."""
        if (not s.prefetch_sfm or s.keyframe_policy != "all"
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
        """The buffered keyframes handed to the SfM source (:meth:`SfmSource.admit`: the
        streaming source's front end and registration into the carried map), oldest first,
        while no frame waits in the queue; the first the source does not take (the batch source
        does it all at the window's end) ends it. A keyframe's front end costs more than a
        10-Hz camera's frame interval on 2 cores: admitted as it arrives, the worker fell behind
        the camera, the keyframe rule skipped its frames as stale and no window filled (one
        keyframe admitted in a 30-s feed). What is not admitted in idle time the window admits
        itself before it maps. A failure is logged: the window admits the frame again itself."""
        if self.ttr is None:
            return
        for frame in buffered:
            if self._queue.queued() > 0:
                return
            if frame.name in self._admitted:
                continue
            self._admitted.add(frame.name)
            if not self._admit(frame, intr):
                self._admitted.discard(frame.name)
                return

    def _admit(self, frame: Frame, intr: Intrinsics) -> bool:
        """One keyframe to the SfM source: whether it takes keyframes ahead of the window (a
        failure is logged and counts as taken: the window's own SfM admits it again)."""
        try:
            return self.ttr.sfm.admit(frame, intr)
        except Exception as exc:  # noqa: BLE001 - the window's own SfM admits it again
            self._warn("sfm_admit", f"keyframe {frame.name} not admitted to the streaming "
                       f"SfM now: {type(exc).__name__}: {exc}")
            return True

    def retain(self, names: Sequence[str]) -> None:
        """The keyframes admitted that no future window takes (the buffer let them go without a
        window of theirs: a flush, a stamp that went back, an overloaded window) are forgotten
        by the SfM source (the streaming source's carried map); ``names``: the buffer's
        keyframes."""
        self._admitted &= set(names)
        if self.ttr is not None:
            self.ttr.sfm.retain(names)

    def counters(self) -> dict[str, object]:
        """The SfM source's counters (:meth:`SfmSource.counters`): SfM begun ahead (started,
        used, discarded) and the streaming SfM's windows continued and mapped afresh with its
        front end's lag ({} under batch)."""
        if self.ttr is None:
            return {"sfm_ahead": {}, "sfm_streaming": {}}
        return self.ttr.sfm.counters()
