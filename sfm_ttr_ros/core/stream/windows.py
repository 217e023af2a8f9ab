"""Online SfM-TTR over a stream of frames: keyframes, sliding windows, back-pressure, accounting.

ROS-free: the ROS node feeds it from its subscription callbacks and publishes what comes out; the
benchmark feeds it from files. Same code path, no ROS transport.

Model of the stream
-------------------
* :meth:`StreamProcessor.submit` (thread-safe, cheap) puts a frame and its intrinsics in a
  bounded input queue. :meth:`StreamProcessor.step` (one worker thread) takes frames out and
  does the heavy work. :meth:`StreamProcessor.push` = submit + process everything queued, for
  synchronous callers (benchmark, tests).
* Frame names are assigned here from a running counter (``f"{seq:010d}"``), so they are unique
  per stream whatever the caller put in ``Frame.name`` (stamps are not unique enough, and SfM
  caches features by name). ``Frame.index``, ``stamp`` and ``header`` are left as given.
* Keyframes: a frame is a keyframe when at least ``min_keyframe_interval_s`` has passed since
  the last keyframe (stamps) and, when ``min_keyframe_motion`` > 0, the mean absolute grey-level
  difference (0-255) between 64-pixel-wide thumbnails of it and of the last keyframe is at least
  that much. Other frames are published at once, unrefined (``not_keyframe``), predicted with
  the latest weights - so outputs are not always in stamp order; each carries its own header.
* Windows: keyframes collect in a window buffer. When it holds ``window_size`` keyframes of
  which at least ``window_stride`` are new (not yet published), one SfM-TTR window runs over the
  last ``window_size`` of them. Its new frames are published (refined, or unrefined with the
  window's reason); the last ``window_size - window_stride`` stay as overlap for the next window
  and are NOT published again.
* Back-pressure: ``max_pending`` bounds the queued frames that hold an image; when it is full
  the OLDEST queued frame is dropped (counted under ``dropped["overflow"]`` and logged,
  throttled): the newest images matter most for a live robot. Under ``keyframe_policy`` newest
  a frame the live output served is not dropped: it gives its image up
  (:data:`RELEASED_IMAGE`) and stays queued, image-less, until the worker counts it stale - no
  frame is lost while the worker is a window behind (at most
  :data:`IMAGELESS_QUEUE_FACTOR` x ``max_pending`` queued frames in all).
* Overload: with ``keyframe_policy`` all, when a window is due while more than
  ``overload_pending`` frames wait in the queue (0 = never), refinement is skipped for that
  window: its new frames are published unrefined (``overload``) so the queue drains, and
  refinement resumes later. Under newest the keyframe rule skips stale frames instead
  (:mod:`.keyframes`, checked before anything else about a frame), so no window is skipped.
* Unrefined frames are predicted again with the latest weights for the windowed output -
  except, unless ``republish_unrefined``, those the live output already served
  (``Frame.served_live``): they come out with ``depth`` None (``FrameOutput.live_only``, counted
  under their reason and in ``live_only``), so an overloaded worker drains its queue at once
  instead of spending its time predicting frames again.
* Backlog bound: in that case (``republish_unrefined`` off, ``overload_pending`` > 0) the queue
  keeps the images of at most ``overload_pending + window_size`` frames: beyond that the OLDEST
  queued frames the live output has served give their image up (:data:`RELEASED_IMAGE`). Such a
  frame cannot join a window: when the worker reaches it, the window being filled is published
  unrefined (``overload``) and so is the frame (live-only), counted in ``backlog_released``.
  Under overload those frames' windows are skipped anyway; the queue's memory stays bounded
  while a window refines (~90 frames arrive meanwhile at 10 Hz, 1.4 MB each at 1242x375).
* Resolution / intrinsics change: every unpublished keyframe is published unrefined
  (``resolution_change`` / ``intrinsics_change``) and a new window starts with the new frame.
  Not when the first received intrinsics replace the fallback's (``Frame.fallback_intrinsics``)
  for an image of the same size: the pending frames take them (logged), since the fallback only
  stood in for the camera's CameraInfo.
  A frame whose intrinsics are for another image size is published unrefined
  (``intrinsics_mismatch``) and kept out of the windows.
* Stamps: a frame with the same stamp as the previous frame is rejected (a duplicated message):
  dropped and counted (``dropped["duplicate_stamp"]``). A stamp earlier than the previous one
  (a bag restarted, a clock reset) is counted (``non_monotonic_stamps``), logged, the unpublished
  keyframes are published unrefined (``stamp_jump_back``) and a new window starts with it.
* Idle flush: when no frame arrived for ``idle_flush_s`` (> 0), and for at least
  :data:`IDLE_INTERVALS` of the stream's median frame interval (so a camera slower than
  ``idle_flush_s`` is not taken for a stopped one; after the first frame IDLE_INTERVALS x
  ``idle_flush_s``), and frames are waiting in an incomplete window, :meth:`step` runs
  :meth:`flush` (end of a bag, a paused camera).
* :meth:`flush` (end of stream) runs a final partial window over the buffer when it holds at
  least 2 frames with something unpublished, else publishes the rest unrefined (``end_of_stream``).
  A node shutting down does NOT flush (it must exit fast): what is still pending then is only
  counted (``pending`` in :meth:`counters`).

Every frame given to :meth:`submit` / :meth:`reject` is accounted for exactly once: refined,
unrefined with a key of :class:`~sfm_ttr_ros.core.outcomes.Unrefined`, or dropped with a key
of :class:`~sfm_ttr_ros.core.outcomes.Dropped`; until then it is pending, so at any time
``received == refined + sum(unrefined) + sum(dropped) + pending``.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from sfm_ttr_ros.core.errors import InputError, check_choice
from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.metric.scale import in_metres
from sfm_ttr_ros.core.outcomes import CHECKS, Dropped, Unrefined
from sfm_ttr_ros.core.pipeline import SfmTTR, TTRConfig, WindowResult
from sfm_ttr_ros.core.sfm.reconstruction import SfmCancelled
from sfm_ttr_ros.core.stream.keyframes import KEYFRAME_POLICIES, KeyframeSelector
from sfm_ttr_ros.core.stream.throttle import Throttle

# the idle flush waits at least this many median frame intervals of the last
# IDLE_CADENCE_FRAMES arrivals (a 0.5 Hz camera with idle_flush_s 2 s: 6 s)
IDLE_INTERVALS = 3.0
IDLE_CADENCE_FRAMES = 10
#: Under keyframe_policy newest the queue may hold this many times ``max_pending`` frames, most
#: of them image-less (served live, waiting to be counted stale): a bound on memory all the same.
IMAGELESS_QUEUE_FACTOR = 10
#: The image of a frame whose pixels are no longer kept: a queued frame released by the backlog
#: bound (see the module docstring), a window's cloud frame in the history (:class:`WindowStats`).
RELEASED_IMAGE = np.zeros((0, 0, 3), np.uint8)
RELEASED_IMAGE.flags.writeable = False


@dataclass
class StreamSettings:
    """Options of the online windowing (the node's parameters of the same names)."""

    window_size: int = 10
    window_stride: int = 5
    # > 0: the stream's first window closes after this many keyframes instead of window_size,
    # so that the first refined weights reach the live output sooner (a short clip); 0 = off
    first_window_size: int = 0
    # which frames are keyframes (core/stream/keyframes.py): newest = windows of the newest
    # consecutive frames (stale frames skipped), all = every frame
    keyframe_policy: str = "newest"
    min_keyframe_interval_s: float = 0.0
    min_keyframe_motion: float = 0.0  # mean abs grey difference on thumbnails, 0 = off
    # input queue bound (frames holding an image); overflow drops the oldest queued frame
    max_pending: int = 100
    overload_pending: int = 30  # more queued frames than this at a window: skip refinement; 0 off
    idle_flush_s: float = 2.0  # > 0: flush an incomplete window after this long without input
    # Live serving (core/stream/refiner.py): bound of the live queue (oldest skipped when full) and
    # the nice value added to the background window worker, so live prediction gets the cores first.
    live_max_queue: int = 4
    worker_nice: int = 10
    # OpenMP threads of the window worker's torch ops (core/threads.py): 1 measured fastest on
    # 2 cores next to live serving; 0 = the runtime's default
    worker_threads: int = 1
    # > 0: while a window refines, its weights are served every this many steps
    # (core/stream/refiner.py)
    serve_every_steps: int = 0
    # False: a frame no window refines that the live output already served is not predicted
    # again for the windowed output (FrameOutput.depth None; counted under its reason as before)
    republish_unrefined: bool = False
    # While a window runs and the next window's frames are all queued, reconstruct them in the
    # background (core/sfm/prefetch.py): the next window starts with its SfM done. Only with
    # keyframe_policy all and every frame a keyframe (under newest a queued next window is one
    # the worker is behind on: its frames would be stale before their SfM is used).
    prefetch_sfm: bool = True

    @property
    def backlog_images(self) -> int:
        """Queued frames that keep their image under the backlog bound (module docstring);
        0 = no bound (unrefined frames are republished, or no overload rule)."""
        if self.republish_unrefined or self.overload_pending <= 0:
            return 0
        return self.overload_pending + self.window_size

    def __post_init__(self) -> None:
        if self.window_size < 2:
            raise InputError(f"window_size must be >= 2, got {self.window_size}")
        if self.first_window_size and not 2 <= self.first_window_size <= self.window_size:
            raise InputError(f"first_window_size must be 0 or in [2, window_size="
                             f"{self.window_size}], got {self.first_window_size}")
        if not 1 <= self.window_stride <= self.window_size:
            raise InputError(f"window_stride must be in [1, window_size={self.window_size}], "
                             f"got {self.window_stride}")
        check_choice("keyframe_policy", self.keyframe_policy, KEYFRAME_POLICIES)
        if self.max_pending < 1:
            raise InputError(f"max_pending must be >= 1, got {self.max_pending}")
        for name in ("min_keyframe_interval_s", "min_keyframe_motion", "idle_flush_s"):
            v = float(getattr(self, name))
            if not (np.isfinite(v) and v >= 0):
                raise InputError(f"{name} must be a finite number >= 0, got {v}")
        if self.live_max_queue < 1:
            raise InputError(f"live_max_queue must be >= 1, got {self.live_max_queue}")
        if self.worker_threads < 0:
            raise InputError(f"worker_threads must be >= 0, got {self.worker_threads}")
        if self.serve_every_steps < 0:
            raise InputError(f"serve_every_steps must be >= 0, got {self.serve_every_steps}")
        if not 0 <= self.worker_nice <= 19:
            raise InputError(f"worker_nice must lie in 0..19, got {self.worker_nice}")
        if self.overload_pending < 0:
            raise InputError(f"overload_pending must be >= 0, got {self.overload_pending}")


@dataclass
class WindowStats:
    """What one window did (for diagnostics); ``result`` is the full core result."""

    index: int
    names: list[str]
    new_frames: int
    refined: bool
    reason_key: Unrefined | None = None
    reason: str = ""
    registered: int = 0
    points: int = 0
    mapping_attempts: int = 0  # runs of the incremental mapper (sfm.mapping_attempts)
    reprojection_error: float = float("nan")  # mean, px, of the reconstruction kept
    inlier_ratio: float = float("nan")
    selected_points: int = 0
    scale: float = float("nan")
    loss_before: float = float("nan")
    loss_after: float = float("nan")
    steps: int = 0  # configured refinement steps for this window
    steps_done: int = 0
    # how the steps ran (RefinementResult.step_mode): "eager", "static" or "graph", with the
    # reason after a colon when it is not "graph" ("" = no step ran)
    step_mode: str = ""
    unsupported_change: float = float("nan")  # share of unsupported pixels moved
    # metres per network unit of the window's own estimate (NaN: none; metric_reason says why)
    metric_estimate: float = float("nan")
    metric_reason: str = ""
    timings: dict[str, float] = field(default_factory=dict)
    # time.monotonic() when the worker began the window and when its outputs were ready
    started_at: float = float("nan")
    finished_at: float = float("nan")
    cloud_frame: Frame | None = field(default=None, repr=False)  # header and stamp, no pixels
    cloud_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32),
                                  repr=False)
    cloud_error: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32), repr=False)
    result: WindowResult | None = field(default=None, repr=False)

    @property
    def ok(self) -> bool:
        return self.refined


@dataclass
class FrameOutput:
    """One frame out of the stream: its depth (network units, image size) and whether it was
    refined. ``depth`` is None for an unrefined frame the live output already served when
    ``StreamSettings.republish_unrefined`` is off (:attr:`live_only`): nothing to publish again."""

    frame: Frame
    depth: np.ndarray | None
    refined: bool
    reason_key: Unrefined | None = None
    reason: str = ""
    window: int | None = None  # index of the window that produced it
    # metres per network unit ``depth`` was multiplied by (core/metric/); None: network units
    metres_per_unit: float | None = None

    @property
    def live_only(self) -> bool:
        """Unrefined and not predicted again: its depth went out on the live output only."""
        return self.depth is None


@dataclass
class _Entry:
    frame: Frame
    published: bool = False


class StreamProcessor:
    """Sliding-window SfM-TTR over a stream (see the module docstring for the rules).

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
        self.on_output = on_output
        self.on_window = on_window
        self.on_drop = on_drop
        self.log = logger or logging.getLogger(__name__)
        self.windows: deque[WindowStats] = deque(maxlen=history)

        self._cv = threading.Condition()
        self._queue: deque[tuple[Frame, Intrinsics]] = deque()
        self._queued_images = 0  # queued frames that still hold their image
        self._seq = 0
        self._received = 0
        self._refined = 0
        self._unrefined_n: Counter[str] = Counter()
        self._dropped: Counter[str] = Counter()
        self._windows_ok = 0
        self._windows_failed = 0
        self._windows_skipped = 0
        self._windows_disabled = 0
        self._windows_rejected = 0  # refused by a window check, among the failed
        self._windows_remapped = 0  # whose mapper ran more than once (sfm.mapping_attempts)
        self._non_monotonic = 0
        self._live_only = 0  # unrefined frames not predicted again: served live only
        self._released = 0  # queued frames whose image the backlog bound released
        self._taken: set[int] = set()  # id() of frames out of the queue, not yet accounted
        self._cancelled = False
        self._last_input = time.monotonic()
        self._arrivals: deque[float] = deque(maxlen=IDLE_CADENCE_FRAMES + 1)  # monotonic s
        self._throttle = Throttle()

        # worker-side state (only touched by the thread that calls step / push / flush)
        self._buffer: list[_Entry] = []
        self._intr: Intrinsics | None = None
        self._intr_fallback = False  # self._intr are the fallback's (replaced by received ones)
        self._last_stamp: float | None = None
        self.keyframes = KeyframeSelector()  # which frames are keyframes (keyframes.py)
        self._window_index = 0
        # the window being processed (frames, intrinsics): what the next one overlaps
        self._running: tuple[list[Frame], Intrinsics] | None = None
        self._asked_ahead: tuple[str, ...] = ()  # the frames whose SfM was begun ahead last

    # -- input (any thread) ----------------------------------------------------------------------
    def submit(self, frame: Frame, intrinsics: Intrinsics) -> None:
        """Queue a frame (thread-safe, never blocks on heavy work)."""
        dropped = None
        with self._cv:
            self._received += 1
            frame.name = f"{self._seq:010d}"
            self._seq += 1
            dropped = self._make_room()
            self._queue.append((frame, intrinsics))
            self._queued_images += frame.image is not RELEASED_IMAGE
            self._release_backlog()
            self._last_input = time.monotonic()
            self._arrivals.append(self._last_input)
            self._cv.notify_all()
        self._prefetch_next()
        if dropped is not None:
            self._emit_drop(dropped, Dropped.OVERFLOW,
                            f"input queue full (max_pending={self.settings.max_pending}): dropped "
                            f"the oldest pending frame (stamp {dropped.stamp:.6f}); "
                            f"{self._dropped['overflow']} dropped so far")

    def _make_room(self) -> Frame | None:
        """Room for one more frame in a full queue (module docstring, back-pressure); called
        under ``self._cv``. Returns the frame dropped for overflow, if any."""
        s = self.settings
        bound = max(1, s.max_pending)
        if s.keyframe_policy != "all" and len(self._queue) < IMAGELESS_QUEUE_FACTOR * bound:
            if self._queued_images < bound or self._release_oldest_served(1):
                return None
        elif len(self._queue) < bound:
            return None
        dropped, _ = self._queue.popleft()
        self._queued_images -= dropped.image is not RELEASED_IMAGE
        self._dropped[Dropped.OVERFLOW] += 1
        return dropped

    def _release_backlog(self) -> None:
        """The backlog bound (module docstring); called under ``self._cv``."""
        keep = self.settings.backlog_images
        if keep and self._queued_images > keep:
            self._release_oldest_served(self._queued_images - keep)

    def _release_oldest_served(self, n: int) -> int:
        """The oldest ``n`` queued frames the live output served give their image up
        (:data:`RELEASED_IMAGE`); returns how many did. Called under ``self._cv``."""
        done = 0
        for i, (f, intr) in enumerate(self._queue):
            if done >= n:
                break
            if f.image is not RELEASED_IMAGE and f.served_live:
                self._queue[i] = (dataclasses.replace(f, image=RELEASED_IMAGE), intr)
                done += 1
        self._released += done
        self._queued_images -= done
        return done

    def reject(self, reason_key: Dropped, message: str, frame: Frame | None = None) -> None:
        """Count a received frame that is not processed at all (bad image, no intrinsics...)."""
        with self._cv:
            self._received += 1
            self._dropped[reason_key] += 1
        self._emit_drop(frame, reason_key, message)

    def cancel(self) -> None:
        """Stop: the running window ends at its next step, :meth:`step` returns at once."""
        with self._cv:
            self._cancelled = True
            self._cv.notify_all()
        self.ttr.cancel()

    @property
    def cancelled(self) -> bool:
        return self._cancelled

    # -- processing (one worker thread) ----------------------------------------------------------
    def push(self, frame: Frame, intrinsics: Intrinsics) -> list[FrameOutput]:
        """Synchronous use: submit one frame and process everything queued."""
        self.submit(frame, intrinsics)
        return self.process_available()

    def process_available(self) -> list[FrameOutput]:
        outs: list[FrameOutput] = []
        while not self._cancelled:
            got = self._take(timeout=0.0)
            if got is None:
                break
            outs += self._consume(*got)
        return outs

    def step(self, timeout: float | None = None) -> list[FrameOutput]:
        """Wait up to ``timeout`` s for a frame and process it; flush when idle (settings)."""
        got = self._take(timeout)
        if got is not None:
            return self._consume(*got)
        if not self._n_unpublished or self._cancelled:
            return []
        idle = self._idle_after()
        if idle > 0 and time.monotonic() - self._last_input >= idle:
            self.log.info(f"no input for {idle:.3g} s: flushing {self._n_unpublished} pending "
                          "frame(s) as a final window")
            self._last_input = time.monotonic()
            return self.flush()
        return []

    def flush(self, refine: bool = True) -> list[FrameOutput]:
        """End of stream: process the queue, then a final partial window (>= 2 frames) or the
        remaining frames unrefined. The stream can go on afterwards (new windows)."""
        outs = self.process_available()
        if self._n_unpublished and not self._cancelled:
            if refine and len(self._buffer) >= 2:
                outs += self._run_window(self._buffer)
            else:
                outs += self._flush_unrefined(Unrefined.END_OF_STREAM, "end of stream: a "
                                              "single frame cannot make a window")
        self._buffer = []
        self.keyframes.reset()
        return outs

    # -- introspection ---------------------------------------------------------------------------
    @property
    def _n_unpublished(self) -> int:
        return sum(not e.published for e in self._buffer)

    def pending(self) -> int:
        with self._cv:
            return len(self._queue) + len(self._taken)

    def queued(self) -> int:
        with self._cv:
            return len(self._queue)

    def counters(self) -> dict[str, object]:
        """Snapshot of the accounting (consistent under the lock)."""
        with self._cv:
            return {
                "received": self._received,
                "refined": self._refined,
                "unrefined": sum(self._unrefined_n.values()),
                "unrefined_by_reason": dict(self._unrefined_n),
                "live_only": self._live_only,
                "backlog_released": self._released,
                "dropped": sum(self._dropped.values()),
                "dropped_by_reason": dict(self._dropped),
                "pending": len(self._queue) + len(self._taken),
                "queued": len(self._queue),
                "windows_ok": self._windows_ok,
                "windows_failed": self._windows_failed,
                "windows_skipped": self._windows_skipped,
                "windows_disabled": self._windows_disabled,
                "windows_rejected": self._windows_rejected,
                "windows_remapped": self._windows_remapped,
                "non_monotonic_stamps": self._non_monotonic,
                "sfm_ahead": self.ttr.sfm.counters() if self.ttr is not None else {},
            }

    @property
    def last_window(self) -> WindowStats | None:
        return self.windows[-1] if self.windows else None

    @property
    def running_names(self) -> list[str]:
        """The frames of the window being processed (oldest first); [] between windows."""
        with self._cv:
            return [f.name for f in self._running[0]] if self._running is not None else []

    @property
    def windows_started(self) -> int:
        """Windows begun so far: during a window, its index + 1."""
        return self._window_index

    # -- internals -------------------------------------------------------------------------------
    def _idle_after(self) -> float:
        """Seconds without input before the idle flush: ``idle_flush_s``, or
        :data:`IDLE_INTERVALS` median frame intervals of the last arrivals when longer (after
        a single frame, whose camera's interval is not known yet, IDLE_INTERVALS x
        ``idle_flush_s``)."""
        idle = self.settings.idle_flush_s
        with self._cv:
            arrivals = list(self._arrivals)
        if idle <= 0 or not arrivals:
            return idle
        interval = float(np.median(np.diff(arrivals))) if len(arrivals) >= 2 else idle
        return max(idle, IDLE_INTERVALS * interval)

    def _take(self, timeout: float | None) -> tuple[Frame, Intrinsics] | None:
        with self._cv:
            if not self._queue and not self._cancelled and timeout != 0.0:
                self._cv.wait(timeout)
            if not self._queue or self._cancelled:
                return None
            frame, intr = self._queue.popleft()
            self._queued_images -= frame.image is not RELEASED_IMAGE
            self._taken.add(id(frame))
            return frame, intr

    def _refresh_settings(self) -> None:
        if self.settings_provider is not None:
            try:
                self.settings = self.settings_provider()
            except Exception as exc:  # keep the last good settings
                self._warn("settings", f"stream settings not updated: {exc}")

    def _consume(self, frame: Frame, intr: Intrinsics) -> list[FrameOutput]:
        self._refresh_settings()
        s = self.settings
        outs: list[FrameOutput] = []
        if self._last_stamp is not None and frame.stamp == self._last_stamp:
            with self._cv:
                self._dropped[Dropped.DUPLICATE_STAMP] += 1
                self._taken.discard(id(frame))
            self._emit_drop(frame, Dropped.DUPLICATE_STAMP,
                            f"frame with the same stamp as the previous one ({frame.stamp:.9f}) "
                            "rejected")
            return outs
        if self._last_stamp is not None and frame.stamp < self._last_stamp:
            with self._cv:
                self._non_monotonic += 1
            self.log.warning(f"stamp went back from {self._last_stamp:.6f} to {frame.stamp:.6f} "
                             f"s: {self._n_unpublished} pending frame(s) published unrefined and "
                             "a new window started")
            outs += self._flush_unrefined(Unrefined.STAMP_JUMP_BACK,
                                          "stamp went back: window reset")
            self.keyframes.reset()
        self._last_stamp = frame.stamp

        if self.keyframes.is_stale(frame, s.keyframe_policy, s.min_keyframe_interval_s,
                                   s.window_size, self._newest_stamp(),
                                   released=frame.image is RELEASED_IMAGE):
            why = ("stale: the frames queued after it span the next window "
                   f"(keyframe_policy {s.keyframe_policy})")
            outs += self._flush_unrefined(Unrefined.STALE, why)
            outs += self._unrefined([frame], Unrefined.STALE, why)
            return outs
        if frame.image is RELEASED_IMAGE:  # the backlog bound took its image: no window
            reason = ("overload: image released by the backlog bound (overload_pending + "
                      "window_size images kept); served live")
            self._warn("overload", reason)
            outs += self._flush_unrefined(Unrefined.OVERLOAD, reason)
            self.keyframes.reset()
            outs += self._unrefined([frame], Unrefined.OVERLOAD, reason)
            return outs

        if frame.size != (intr.width, intr.height):
            outs += self._unrefined([frame], Unrefined.INTRINSICS_MISMATCH,
                                    f"intrinsics are for {intr.width}x{intr.height}, the image is "
                                    f"{frame.size[0]}x{frame.size[1]}")
            return outs
        if self._intr is not None and intr != self._intr:
            size_changed = (intr.width, intr.height) != (self._intr.width, self._intr.height)
            if self._intr_fallback and not frame.fallback_intrinsics and not size_changed:
                self.log.info(f"intrinsics received: {intr} replace the fallback {self._intr} "
                              f"for the {self._n_unpublished} pending frame(s)")
            else:
                outs += self._intrinsics_changed(intr, size_changed)
        self._intr, self._intr_fallback = intr, frame.fallback_intrinsics

        if not self.keyframes.is_keyframe(frame, s.min_keyframe_interval_s,
                                          s.min_keyframe_motion):
            outs += self._unrefined([frame], Unrefined.NOT_KEYFRAME, "not a keyframe")
            return outs
        self._buffer.append(_Entry(frame))
        n_new = self._n_unpublished
        size = s.first_window_size if s.first_window_size and not self._window_index \
            else s.window_size
        if len(self._buffer) >= size and n_new >= min(s.window_stride, size):
            outs += self._run_window(self._buffer[-max(size, n_new):])
            keep = s.window_size - s.window_stride
            self._buffer = self._buffer[len(self._buffer) - keep:] if keep > 0 else []
        return outs

    def _intrinsics_changed(self, intr: Intrinsics, size_changed: bool) -> list[FrameOutput]:
        """The camera changed: the pending frames are published unrefined, a new window starts."""
        key = Unrefined.RESOLUTION_CHANGE if size_changed else Unrefined.INTRINSICS_CHANGE
        what = (f"image size changed from {self._intr.width}x{self._intr.height} to "
                f"{intr.width}x{intr.height}" if size_changed else
                f"intrinsics changed from {self._intr} to {intr}")
        self.log.warning(f"{what}: {self._n_unpublished} pending frame(s) published "
                         "unrefined and a new window started")
        outs = self._flush_unrefined(key, what)
        self.keyframes.reset()
        return outs

    def behind_s(self) -> float:
        """How far the worker is behind the camera: the newest queued frame's stamp minus the
        stamp of the last frame it took (0 when nothing waits)."""
        newest = self._newest_stamp()
        if newest is None or self._last_stamp is None:
            return 0.0
        return max(0.0, newest - self._last_stamp)

    def _newest_stamp(self) -> float | None:
        """The stamp of the newest frame queued (None: the queue is empty)."""
        with self._cv:
            return self._queue[-1][0].stamp if self._queue else None

    def _prefetch_next(self) -> None:
        """While a window runs: once the frames of the window after it are all queued (its
        overlap with the running window plus ``window_stride`` new ones, every frame a
        keyframe, same intrinsics and image size, stamps rising), begin their SfM in the
        background (:meth:`SfmSource.prefetch`, which waits until the running window's own SfM
        has ended: asked again at every frame that arrives). Called by :meth:`submit`; cheap
        when there is nothing to do."""
        s = self.settings
        if (not s.prefetch_sfm or s.keyframe_policy != "all" or s.min_keyframe_interval_s > 0
                or s.min_keyframe_motion > 0):
            return
        with self._cv:
            if self._running is None or len(self._queue) < s.window_stride:
                return
            running, intr = self._running
            queued = list(itertools.islice(self._queue, s.window_stride))
        keep = s.window_size - s.window_stride
        frames = (running[len(running) - keep:] if keep > 0 else []) + [f for f, _ in queued]
        names = tuple(f.name for f in frames)
        if names == self._asked_ahead:  # begun already: every later frame finds the same ones
            return
        if (len(frames) < 2 or any(i != intr for _, i in queued)
                or any(f.image is RELEASED_IMAGE or f.size != (intr.width, intr.height)
                       for f in frames)
                or any(b.stamp <= a.stamp for a, b in itertools.pairwise(frames))):
            return
        try:
            if self.ttr.sfm.prefetch(frames, intr):
                self._asked_ahead = names
        except Exception as exc:  # noqa: BLE001 - ahead of time only: the window does it itself
            self._warn("prefetch", f"SfM ahead of the next window not begun: {exc}")

    def _overloaded(self) -> int:
        """Frames queued beyond ``overload_pending`` when a window is due (0: not overloaded).
        Only with ``keyframe_policy`` all: under newest the stale frames are skipped instead,
        and a due window covers the latest seconds already."""
        limit = self.settings.overload_pending
        if self.settings.keyframe_policy != "all":
            return 0
        q = self.queued()
        return q if limit > 0 and q > limit else 0

    def _run_window(self, entries: Sequence[_Entry]) -> list[FrameOutput]:
        """One window over ``entries``; publishes its unpublished frames."""
        if self.config_provider is not None:
            try:
                self.ttr.set_config(self.config_provider())
            except Exception as exc:  # keep the last good config
                self._warn("config", f"SfM-TTR options not updated: {exc}")
        frames = [e.frame for e in entries]
        new = [e.frame for e in entries if not e.published]
        index = self._window_index
        self._window_index += 1
        stats = WindowStats(index, [f.name for f in frames], len(new), refined=False,
                            steps=self.ttr.config.refinement.steps,
                            started_at=time.monotonic())
        queued = self._overloaded()
        if queued:
            stats.reason_key = Unrefined.OVERLOAD
            stats.reason = (f"overload: {queued} frames queued > overload_pending="
                            f"{self.settings.overload_pending}: refinement skipped")
            self._warn("overload", stats.reason)
            self.windows.append(stats)  # before any output: a consumer sees the window first
            outs = self._unrefined(new, Unrefined.OVERLOAD, stats.reason, window=index)
            with self._cv:
                self._windows_skipped += 1
            self._finish_window(entries, stats)
            return outs

        with self._cv:
            self._running = (frames, self._intr)
        try:
            res = self.ttr.process_window(frames, self._intr,
                                          should_stop=lambda: self._cancelled)
        except SfmCancelled:
            res = None
            stats.reason_key, stats.reason = Unrefined.CANCELLED, "SfM cancelled"
        except Exception as exc:  # never let one window kill the stream
            res = None
            stats.reason_key = Unrefined.WINDOW_ERROR
            stats.reason = f"window failed: {type(exc).__name__}: {exc}"
            self.log.error(stats.reason)
        finally:
            with self._cv:
                self._running = None
        if self._cancelled:  # shutting down: publish nothing more
            return []
        if res is None:
            self.windows.append(stats)
            outs = self._unrefined(new, stats.reason_key, stats.reason, window=index)
        else:
            self._fill_stats(stats, res)
            cloud_frame = next((f for f in frames if f.name == res.cloud_frame), None)
            # its header and stamp, not its pixels: the history holds 100 windows (a 1242x375
            # image each grew a 30-min soak's RSS by ~140 MB until the history was full)
            stats.cloud_frame = (None if cloud_frame is None
                                 else dataclasses.replace(cloud_frame, image=RELEASED_IMAGE))
            self.windows.append(stats)
            k = None if self.ttr is None else self.ttr.metric_status().metres_per_unit
            outs = [FrameOutput(f, in_metres(res.depths[f.name], k), res.refined,
                                None if res.refined else stats.reason_key,
                                "" if res.refined else stats.reason, window=index,
                                metres_per_unit=k) for f in new]
            self._account(outs)
        with self._cv:
            if stats.refined:
                self._windows_ok += 1
            elif stats.reason_key == Unrefined.DISABLED:
                self._windows_disabled += 1
            else:
                self._windows_failed += 1
                self._windows_rejected += stats.reason_key in CHECKS
            self._windows_remapped += stats.mapping_attempts > 1
        if not stats.refined and stats.reason_key != Unrefined.DISABLED:
            self._warn(f"window:{stats.reason_key}",
                       f"window {index} not refined ({stats.reason}): {len(new)} frame(s) "
                       "published unrefined")
        self._finish_window(entries, stats)
        return outs

    def _finish_window(self, entries: Sequence[_Entry], stats: WindowStats) -> None:
        """Mark the window's frames published and report it (``stats`` is already in
        :attr:`windows`: it goes there before the window's first output is published)."""
        stats.finished_at = time.monotonic()
        if stats.reason_key != Unrefined.OVERLOAD:  # the windows' pace (diagnostics)
            self.keyframes.window_done(stats.finished_at - stats.started_at)
        for e in entries:
            e.published = True
        if self.on_window is not None:
            self.on_window(stats)

    @staticmethod
    def _fill_stats(stats: WindowStats, res: WindowResult) -> None:
        stats.refined = res.refined
        if not res.refined:
            stats.reason_key, stats.reason = res.reason_key, res.reason
        if res.sfm is not None:
            stats.registered, stats.points = res.sfm.num_registered, res.sfm.num_points
            stats.mapping_attempts = len(res.sfm.attempts)
            stats.reprojection_error = res.sfm.reprojection_error
        if res.alignment is not None and res.alignment.ransac_inliers.size:
            stats.inlier_ratio = float(np.mean(res.alignment.ransac_inliers))
            stats.selected_points = int(res.alignment.selected.sum())
        stats.scale, stats.loss_before, stats.loss_after = res.scale, res.loss_before, \
            res.loss_after
        stats.steps_done = res.refinement.steps_done if res.refinement is not None else 0
        if res.refinement is not None and res.refinement.steps_done:
            r = res.refinement
            stats.step_mode = f"{r.step_mode}: {r.step_mode_reason}" if r.step_mode_reason \
                else r.step_mode
        if res.check is not None:
            stats.unsupported_change = res.check.unsupported_change
        if res.metric is not None:
            stats.metric_estimate, stats.metric_reason = res.metric.k, res.metric.reason
        stats.timings = dict(res.timings)
        # The history keeps the SfM/alignment summary but not the per-frame depth maps: a deque of
        # 100 windows x 10 full-size maps each would grow memory for the whole first 100 windows.
        stats.result = dataclasses.replace(res, depths={}, depths_before={},
                                           depths_candidate={})
        if res.cloud_frame:
            stats.cloud_xyz, stats.cloud_error = res.cloud_xyz, res.cloud_error

    def _flush_unrefined(self, key: Unrefined, reason: str) -> list[FrameOutput]:
        new = [e.frame for e in self._buffer if not e.published]
        self._buffer = []
        return self._unrefined(new, key, reason) if new else []

    def _unrefined(self, frames: Sequence[Frame], key: Unrefined, reason: str,
                   window: int | None = None) -> list[FrameOutput]:
        """Publish ``frames`` unrefined, predicted with the latest weights - except the frames
        the live output already served, unless ``republish_unrefined``: those come out with
        ``depth`` None (:attr:`FrameOutput.live_only`), counted under ``key`` all the same.
        Under overload this is most frames, and predicting them again took ~40 % of the
        worker's time that windows then lacked (BENCHMARKS.md "Live latency and the live share")."""
        if not frames:
            return []
        again = self.settings.republish_unrefined
        todo = [f for f in frames
                if f.image is not RELEASED_IMAGE and (again or not f.served_live)]
        depths: dict[int, np.ndarray] = {}
        if todo:
            try:
                depths = dict(zip(map(id, todo),
                                  self.ttr.predictor.predict([f.image for f in todo]),
                                  strict=True))
            except Exception as exc:
                msg = f"prediction failed ({type(exc).__name__}: {exc}): frame(s) dropped"
                self.log.error(msg)
                with self._cv:
                    self._dropped[Dropped.PREDICTION_ERROR] += len(todo)
                    self._taken.difference_update(map(id, todo))
                for f in todo:
                    self._emit_drop(f, Dropped.PREDICTION_ERROR, msg)
                failed = set(map(id, todo))
                frames = [f for f in frames if id(f) not in failed]
        k = None if self.ttr is None else self.ttr.metric_status().metres_per_unit
        outs = [FrameOutput(f, in_metres(depths.get(id(f)), k), False, key, reason, window,
                            metres_per_unit=k) for f in frames]
        self._account(outs)
        return outs

    def _account(self, outs: list[FrameOutput]) -> None:
        with self._cv:
            for o in outs:
                if o.refined:
                    self._refined += 1
                else:
                    self._unrefined_n[o.reason_key] += 1
                    self._live_only += o.live_only
                self._taken.discard(id(o.frame))
        for o in outs:
            if self.on_output is not None:
                self.on_output(o)

    def _emit_drop(self, frame: Frame | None, key: Dropped, message: str) -> None:
        self._warn(f"drop:{key}", message)
        if self.on_drop is not None:
            self.on_drop(frame, key, message)

    def _warn(self, key: str, message: str) -> None:
        """Log a warning at most once per :data:`~sfm_ttr_ros.core.stream.throttle.WARN_PERIOD_S`
        per key."""
        if self._throttle.due(key):
            self.log.warning(message)
