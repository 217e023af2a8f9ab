"""The window runner: online SfM-TTR over a stream of frames (:class:`WindowRunner`).

ROS-free: the ROS node feeds it from its subscription callbacks and publishes what comes out; the
benchmark feeds it from files. Same code path, no ROS transport. The rules it applies to every
frame (queue and back-pressure, stamps, keyframes, windows, overload, idle flush, the end of the
stream) and the accounting of every frame are written once, in docs/node.md, "How frames flow".

:meth:`WindowRunner.submit` (any thread, cheap) queues a frame; :meth:`WindowRunner.step`
(one worker thread) takes frames out and does the heavy work; :meth:`WindowRunner.push` =
submit + process everything queued, for synchronous callers (benchmark, tests). The parts:
:mod:`.settings`, :mod:`.records` (what comes out), :mod:`.frame_queue` (the only part two
threads share), :mod:`.ledger` (the counters), :mod:`.admission` (the per-frame rules),
:mod:`.keyframes`, :mod:`.window_buffer`, :mod:`.frame_outlet` (outputs, counted), :mod:`.sfm_feed`
(the next window's SfM begun ahead, or each keyframe admitted to the streaming SfM as the
buffer takes it), :mod:`.path` (the camera's path, extended as each window finishes); this
module schedules the windows and skips them under overload.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections import deque
from collections.abc import Callable, Sequence

from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.outcomes import Dropped, Unrefined
from sfm_ttr_ros.core.pipeline import SfmTTR, TTRConfig, WindowResult
from sfm_ttr_ros.core.sfm.reconstruction import SfmCancelled
from sfm_ttr_ros.core.stream.admission import (
    Verdict,
    image_rule,
    intrinsics_rule,
    stale_verdict,
    stamp_rule,
)
from sfm_ttr_ros.core.stream.frame_outlet import FrameOutlet
from sfm_ttr_ros.core.stream.frame_queue import RELEASED_IMAGE, FrameQueue
from sfm_ttr_ros.core.stream.keyframes import KeyframeSelector
from sfm_ttr_ros.core.stream.path import StreamPath
from sfm_ttr_ros.core.stream.records import FrameOutput, WindowStats, unrefined_result
from sfm_ttr_ros.core.stream.settings import StreamSettings
from sfm_ttr_ros.core.stream.sfm_feed import SfmFeed
from sfm_ttr_ros.core.stream.window_buffer import Entry, WindowBuffer

# the names the node, the benchmark and the parameter schema import from here
__all__ = ["FrameOutput", "WindowRunner", "StreamSettings", "WindowStats"]


class WindowRunner:
    """Sliding-window SfM-TTR over a stream (docs/node.md, "How frames flow", for the rules).

    ``config_provider`` (optional) is called at the start of every window and its TTRConfig
    handed to ``ttr.set_config`` (live parameters take effect at the next window);
    ``settings_provider`` likewise for :class:`StreamSettings`, read at every frame.
    Sinks: ``on_output(FrameOutput)``, ``on_window(WindowStats)`` (after the window's outputs),
    ``on_drop(frame_or_None, reason_key, message)``. ``logger``: anything with ``info``,
    ``warning`` and ``error`` taking one string (a logging.Logger, an rclpy logger).
    """

    def __init__(
        self,
        ttr: SfmTTR,
        settings: StreamSettings | None = None,
        *,
        config_provider: Callable[[], TTRConfig] | None = None,
        settings_provider: Callable[[], StreamSettings] | None = None,
        on_output: Callable[[FrameOutput], None] | None = None,
        on_window: Callable[[WindowStats], None] | None = None,
        on_drop: Callable[[Frame | None, str, str], None] | None = None,
        logger=None,
        history: int = 100,
    ):
        self.ttr = ttr
        self.settings = settings or StreamSettings()
        self.config_provider = config_provider
        self.settings_provider = settings_provider
        self.on_window = on_window
        self.log = logger or logging.getLogger(__name__)
        self.windows: deque[WindowStats] = deque(maxlen=history)
        self._queue = FrameQueue()
        self._out = FrameOutlet(ttr, self._queue, lambda: self.settings.republish_unrefined,
                                   on_output, on_drop, self.log)

        # worker-side state (only touched by the thread that calls step / push / flush)
        self._buffer = WindowBuffer()  # the keyframes of the window being filled
        self._intr: Intrinsics | None = None
        self._intr_fallback = False  # self._intr are the fallback's (replaced by received ones)
        self._last_stamp: float | None = None
        self.keyframes = KeyframeSelector()  # which frames are keyframes (keyframes.py)
        self._window_index = 0
        self.path = StreamPath()  # the camera's path (~/odom), in the depth's metres
        # the next window's SfM begun ahead (batch), each keyframe admitted (streaming)
        self._sfm = SfmFeed(ttr, self._queue, self._out.warn)

    # -- input (any thread) ----------------------------------------------------------------------
    def submit(self, frame: Frame, intrinsics: Intrinsics | None) -> None:
        """Queue a frame (thread-safe, never blocks on heavy work); ``intrinsics`` None: a
        frame that has none (held too long for them), published unrefined as it comes out."""
        dropped = self._queue.put(frame, intrinsics, self.settings)
        self._sfm.prefetch_next(self.settings)
        if dropped is not None:
            self._out.overflow(dropped, self.settings.max_pending)

    def reject(self, reason_key: Dropped, message: str, frame: Frame | None = None) -> None:
        """Count a received frame that is not processed at all (bad image, no intrinsics...)."""
        self._queue.reject(reason_key)
        self._out.drop(frame, reason_key, message)

    def recover(self, reason: str) -> list[FrameOutput]:
        """After a fault that escaped :meth:`step` (the caller contained it): the window state
        reset (no window running, an empty buffer, the keyframes anew) and the frames in the
        worker's hands published unrefined under ``WORKER_FAULT``: the next frames flow."""
        self._queue.end_window()
        self._buffer = WindowBuffer()
        self.keyframes.reset()
        outs = self._out.release_taken(Unrefined.WORKER_FAULT, reason)
        self._sfm.retain([])
        return outs

    def cancel(self) -> None:
        """Stop: the running window ends at its next step, :meth:`step` returns at once."""
        self._queue.cancel()
        self.ttr.cancel()

    @property
    def cancelled(self) -> bool:
        return self._queue.cancelled

    # -- processing (one worker thread) ----------------------------------------------------------
    def push(self, frame: Frame, intrinsics: Intrinsics) -> list[FrameOutput]:
        """Synchronous use: submit one frame and process everything queued."""
        self.submit(frame, intrinsics)
        return self.process_available()

    def process_available(self) -> list[FrameOutput]:
        outs: list[FrameOutput] = []
        while not self._queue.cancelled:
            got = self._queue.take(timeout=0.0)
            if got is None:
                break
            outs += self._consume(*got)
        return outs

    def step(self, timeout: float | None = None) -> list[FrameOutput]:
        """Wait up to ``timeout`` s for a frame and process it; flush when idle (settings)."""
        got = self._queue.take(timeout)
        if got is not None:
            return self._consume(*got)
        if not self._buffer.unpublished or self._queue.cancelled:
            return []
        idle = self._idle_after()
        if idle > 0 and self._queue.idle_for() >= idle:
            self.log.info(f"no input for {idle:.3g} s: flushing {self._buffer.unpublished} "
                          "pending frame(s) as a final window")
            self._queue.restart_idle()
            return self.flush()
        return []

    def flush(self, refine: bool = True) -> list[FrameOutput]:
        """End of stream: process the queue, then a final partial window (>= 2 frames) or the
        remaining frames unrefined. The stream can go on afterwards (new windows)."""
        outs = self.process_available()
        if self._buffer.unpublished and not self._queue.cancelled:
            if refine and len(self._buffer) >= 2:
                outs += self._run_window(self._buffer.entries)
            else:
                outs += self._out.unrefined(self._buffer.take_unpublished(),
                                            Unrefined.END_OF_STREAM,
                                            "end of stream: a single frame cannot make a window")
        self._buffer = WindowBuffer()
        self._sfm.retain([])
        self.keyframes.reset()
        return outs

    # -- introspection ---------------------------------------------------------------------------
    def pending(self) -> int:
        return self._queue.pending()

    def queued(self) -> int:
        return self._queue.queued()

    def counters(self) -> dict[str, object]:
        """Snapshot of the accounting (:meth:`FrameQueue.counters`) and of the SfM begun ahead."""
        return self._queue.counters() | self._sfm.counters()

    @property
    def last_window(self) -> WindowStats | None:
        return self.windows[-1] if self.windows else None

    @property
    def running_names(self) -> list[str]:
        """The frames of the window being processed (oldest first); [] between windows."""
        return self._queue.running_names()

    @property
    def windows_started(self) -> int:
        """Windows begun so far: during a window, its index + 1."""
        return self._window_index

    def behind_s(self) -> float:
        """How far the worker is behind the camera: the newest queued frame's stamp minus the
        stamp of the last frame it took (0 when nothing waits)."""
        return self._queue.behind(self._last_stamp)

    # -- one frame -------------------------------------------------------------------------------
    def _idle_after(self) -> float:
        return self._queue.idle_after(self.settings.idle_flush_s)

    def _refresh_settings(self) -> None:
        if self.settings_provider is not None:
            try:
                self.settings = self.settings_provider()
            except Exception as exc:  # keep the last good settings
                self._out.warn("settings", f"stream settings not updated: {exc}")

    def _refresh_config(self) -> None:
        if self.config_provider is not None:
            try:
                self.ttr.set_config(self.config_provider())
            except Exception as exc:  # keep the last good config
                self._out.warn("config", f"SfM-TTR options not updated: {exc}")

    def _consume(self, frame: Frame, intr: Intrinsics | None) -> list[FrameOutput]:
        """One frame taken from the queue: the admission rules in their order, then the
        keyframe rule, then the window when one is due."""
        if intr is None:  # held for intrinsics that never came
            return self._out.unrefined([frame], Unrefined.NO_INTRINSICS,
                                       "no intrinsics within the idle period")
        self._refresh_settings()
        s = self.settings
        verdict = stamp_rule(frame.stamp, self._last_stamp, self._buffer.unpublished)
        outs = self._apply(frame, verdict) if verdict is not None else []
        if verdict is not None and verdict.final:
            return outs
        self._last_stamp = frame.stamp
        released = frame.image is RELEASED_IMAGE
        if self.keyframes.is_stale(frame, s.keyframe_policy, s.min_keyframe_interval_s,
                                   s.window_size, self._queue.newest_stamp(), released=released):
            return outs + self._apply(frame, stale_verdict(s.keyframe_policy))
        verdict = image_rule(frame, intr, released) or intrinsics_rule(
            intr, self._intr, self._intr_fallback, frame.fallback_intrinsics,
            self._buffer.unpublished)
        if verdict is not None:
            outs += self._apply(frame, verdict)
            if verdict.final:
                return outs
        self._intr, self._intr_fallback = intr, frame.fallback_intrinsics
        if not self.keyframes.is_keyframe(frame, s.min_keyframe_interval_s,
                                          s.min_keyframe_motion):
            return outs + self._out.unrefined([frame], Unrefined.NOT_KEYFRAME, "not a keyframe")
        self._buffer.add(frame)
        self._sfm.admit_while_idle([e.frame for e in self._buffer.entries], intr)
        return outs + self._window_if_due()

    def _apply(self, frame: Frame, v: Verdict) -> list[FrameOutput]:
        """An admission verdict (:class:`~.admission.Verdict`): a stamp that went back
        counted, the window being filled emptied (``flush``), the keyframes started anew
        (``reset``), the rest published."""
        if v.flush == Unrefined.STAMP_JUMP_BACK:
            with self._queue.locked() as ledger:
                ledger.non_monotonic += 1
        flushed = self._buffer.take_unpublished() if v.flush is not None else []
        if v.reset:
            self.keyframes.reset()
        if flushed:
            self._sfm.retain([])
        return self._out.verdict(frame, v, flushed)

    # -- windows ---------------------------------------------------------------------------------
    def _window_if_due(self) -> list[FrameOutput]:
        """The window over the buffered keyframes when one is due (:meth:`WindowBuffer.due`);
        the buffer then keeps the next window's overlap."""
        entries = self._buffer.due(self.settings, first=not self._window_index)
        if not entries:
            return []
        outs = self._run_window(entries)
        self._buffer.slide(self.settings)
        self._sfm.retain([e.frame.name for e in self._buffer.entries])
        return outs

    def _overloaded(self) -> int:
        """Frames queued beyond ``overload_pending`` when a window is due (0: not overloaded).
        Only under ``keyframe_policy`` all: under newest the stale frames are skipped instead."""
        s, q = self.settings, self.queued()
        return q if s.keyframe_policy == "all" and 0 < s.overload_pending < q else 0

    def _run_window(self, entries: Sequence[Entry]) -> list[FrameOutput]:
        """One window over ``entries``, its refinement skipped under overload: recorded in
        :attr:`windows` before its first output, its unpublished frames published, counted."""
        self._refresh_config()
        frames = [e.frame for e in entries]
        new = [e.frame for e in entries if not e.published]
        index = self._window_index
        self._window_index += 1
        steps, started = self.ttr.config.refinement.steps, time.monotonic()
        queued = self._overloaded()
        if queued:
            res, ran = self._skipped(frames, queued), False
        else:
            res, ran = self._process(frames)
            if self._queue.cancelled:  # shutting down: publish nothing more
                return []
        cloud = next((f for f in frames if f.name == res.cloud_frame), None)
        # its header and stamp, not its pixels: the history holds 100 windows (a 1242x375
        # image each grew a 30-min soak's RSS by ~140 MB until the history was full)
        stats = WindowStats.of(index, len(new), res, steps=steps, started_at=started,
                               cloud_frame=None if cloud is None
                               else dataclasses.replace(cloud, image=RELEASED_IMAGE))
        self.windows.append(stats)
        outs = self._out.window(new, res, stats, ran)
        stats.path_poses = self.path.window(frames, res, self.ttr.metres_per_unit)
        with self._queue.locked() as ledger:
            ledger.window(stats)
        if not stats.refined and stats.reason_key not in (Unrefined.DISABLED, Unrefined.OVERLOAD):
            self._out.warn(f"window:{stats.reason_key}", f"window {index} not refined "
                           f"({stats.reason}): {len(new)} frame(s) published unrefined")
        stats.finished_at = time.monotonic()
        if stats.reason_key != Unrefined.OVERLOAD:  # the windows' pace (diagnostics)
            self.keyframes.window_done(stats.finished_at - stats.started_at)
        WindowBuffer.mark_published(entries)
        if self.on_window is not None:
            self.on_window(stats)
        return outs

    def _skipped(self, frames: list[Frame], queued: int) -> WindowResult:
        """Overload: the window's refinement skipped (its new frames go out unrefined)."""
        reason = (f"overload: {queued} frames queued > overload_pending="
                  f"{self.settings.overload_pending}: refinement skipped")
        self._out.warn("overload", reason)
        return unrefined_result([f.name for f in frames], Unrefined.OVERLOAD, reason)

    def _process(self, frames: list[Frame]) -> tuple[WindowResult, bool]:
        """The core's window over ``frames``: (its result, True), or (an unrefined result
        saying why, False) when it raised: cancelled, or failed (one window never ends the
        stream)."""
        names = [f.name for f in frames]
        self._queue.begin_window(frames, self._intr)
        try:
            return self.ttr.process_window(frames, self._intr,
                                           should_stop=lambda: self._queue.cancelled), True
        except SfmCancelled:
            return unrefined_result(names, Unrefined.CANCELLED, "SfM cancelled"), False
        except Exception as exc:
            reason = f"window failed: {type(exc).__name__}: {exc}"
            self.log.error(reason)
            return unrefined_result(names, Unrefined.WINDOW_ERROR, reason), False
        finally:
            self._queue.end_window()
