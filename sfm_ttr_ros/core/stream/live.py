"""Live depth at camera rate: every frame predicted on arrival by the serving network.

The paper leaves "online and real-time refinement" open; here the two jobs are split. The
windowed SfM-TTR (:class:`~sfm_ttr_ros.core.stream.window_runner.WindowRunner`) reconstructs and
refines in the background and publishes each keyframe again once its window is done;
:class:`LiveServer` answers every frame at once from a
:class:`~sfm_ttr_ros.core.stream.serving.ServingModel` that holds the newest accepted weights.

Threads: :meth:`LiveServer.submit` (any thread, cheap) queues a frame; one serving thread takes
frames oldest first, predicts, and hands ``(frame, depth, version)`` to ``on_depth``. The queue
is bounded (``max_queue``): when it is full the OLDEST waiting frame is skipped and counted
(``skipped["overflow"]``), so a slow machine serves the newest images. A prediction that raises
skips that frame (``skipped["prediction_error"]``, logged, throttled) and the server goes on.

Hand-over: with ``live_depths`` (:class:`~sfm_ttr_ros.core.prediction.LiveDepths`) each served
frame's network depth (before any metres factor) is recorded with the generation of the weights
that made it, after it was published (the frame's latency does not include it), so that the
window that takes the frame need not predict it again with the same weights.

Accounting, as for the windowed stream: ``received == published + sum(skipped) + pending``.
Timing, over the last :data:`LATENCY_WINDOW` published frames: the latency from a frame's
arrival to its published depth (p50, p95, max) and the time ``on_depth`` took to publish it, so
/diagnostics tells a late ``~/depth`` made in the node from one delayed on the way out.

Scheduling on few cores: torch's intra-op thread count is one number per process, so the two
roles cannot be given different torch thread counts. What can be separated is the OS priority:
:func:`~sfm_ttr_ros.core.threads.lower_thread_priority` raises the calling thread's nice value
(Linux: per thread; threads it starts later, e.g. its OpenMP team and pycolmap's workers, inherit
it), so a background refinement worker yields the cores to the serving thread whenever a frame
arrives.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from sfm_ttr_ros.core.frames import Frame
from sfm_ttr_ros.core.outcomes import LiveSkipped
from sfm_ttr_ros.core.prediction import LiveDepths
from sfm_ttr_ros.core.stream.serving import Served, ServingModel
from sfm_ttr_ros.core.stream.throttle import Throttle

#: How long :meth:`LiveServer.start` (and the window worker's start) waits for a warm-up, s.
WARM_UP_WAIT_S = 120.0
#: How many of the newest published frames the latency figures cover.
LATENCY_WINDOW = 100
#: The keys of :func:`latency_figures` (also /diagnostics' ``live.<key>``).
LATENCY_KEYS = ("latency_p50_s", "latency_p95_s", "latency_max_s", "publish_max_s")


@dataclass
class LiveOutput:
    """One served frame: depth at the image's size, the weights' version and their age."""

    frame: Frame
    depth: np.ndarray
    version: int
    weights_age_s: float
    arrival: float  # time.monotonic() when submitted
    served: float  # time.monotonic() when the depth was ready
    metres_per_unit: float | None = None  # the factor ``depth`` is in metres by; None: not

    @property
    def latency_s(self) -> float:
        return self.served - self.arrival


class LiveServer:
    """Serve each submitted frame from ``serving`` on a thread of its own."""

    def __init__(self, serving: ServingModel, on_depth: Callable[[LiveOutput], None],
                 max_queue: int = 4, logger: logging.Logger | None = None,
                 live_depths: LiveDepths | None = None) -> None:
        if max_queue < 1:
            raise ValueError(f"max_queue must be >= 1, got {max_queue}")
        self.serving = serving
        self.on_depth = on_depth
        self.live_depths = live_depths  # the served depths handed to the windows (optional)
        self.max_queue = int(max_queue)
        self.log = logger or logging.getLogger(__name__)
        self._queue: deque[tuple[Frame, float]] = deque()
        self._cv = threading.Condition()
        self._stop = False
        self._busy = 0
        self.received = 0
        self.published = 0
        self.skipped: Counter[str] = Counter()
        self._throttle = Throttle()
        self._thread: threading.Thread | None = None
        self._latency: deque[float] = deque(maxlen=LATENCY_WINDOW)  # arrival -> published, s
        self._publish_s: deque[float] = deque(maxlen=LATENCY_WINDOW)  # on_depth's own time

    # -- input ----------------------------------------------------------------------------
    def submit(self, frame: Frame, arrival: float | None = None) -> None:
        """Queue a frame (thread-safe). ``arrival``: its monotonic arrival time (now)."""
        t = time.monotonic() if arrival is None else arrival
        with self._cv:
            self.received += 1
            if self._stop:
                self.skipped[LiveSkipped.STOPPED] += 1
                return
            if len(self._queue) >= self.max_queue:
                self._queue.popleft()
                self.skipped[LiveSkipped.OVERFLOW] += 1
                self._warn("overflow", f"live queue full ({self.max_queue}): oldest frame "
                                       f"skipped ({self.skipped[LiveSkipped.OVERFLOW]} so far)")
            self._queue.append((frame, t))
            self._cv.notify()

    # -- serving --------------------------------------------------------------------------
    def start(self, warm_up: Callable[[], object] | None = None) -> None:
        """Start the serving thread. ``warm_up`` (e.g. :meth:`ServingModel.warm_up`) runs first
        IN that thread, and this returns once it is done (at most :data:`WARM_UP_WAIT_S`): on
        CUDA each thread makes its own cuDNN / cuBLAS handles at its first prediction, which a
        live frame should not wait for. A warm-up that fails is logged; serving starts anyway."""
        ready = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(warm_up, ready),
                                        name="live-server", daemon=True)
        self._thread.start()
        if not ready.wait(WARM_UP_WAIT_S):
            self.log.warning(f"live serving: warm-up still running after {WARM_UP_WAIT_S:.0f} s; "
                             f"serving starts behind it")

    def stop(self, timeout: float = 3.0) -> None:
        """Stop serving; frames still queued are counted as skipped (``stopped``)."""
        with self._cv:
            self._stop = True
            if self._queue:
                self.skipped[LiveSkipped.STOPPED] += len(self._queue)
            self._queue.clear()
            self._cv.notify_all()
        if self._thread is not None:
            self._thread.join(timeout)

    def drain(self, timeout: float = 10.0) -> bool:
        """Wait until every queued frame is served (True) or ``timeout`` passes (False)."""
        end = time.monotonic() + timeout
        with self._cv:
            while self._queue or self._busy:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._cv.wait(left)
        return True

    def serve_one(self, frame: Frame, arrival: float) -> LiveOutput | None:
        """Predict one frame now (the serving thread's body; also for synchronous callers)."""
        try:
            served = self.serving.serve(frame.image)
        except Exception as exc:  # noqa: BLE001 - one bad frame must not stop serving
            return self._skip(LiveSkipped.PREDICTION_ERROR, frame, exc)
        out = LiveOutput(frame, served.depth, served.version, self.serving.age_s, arrival,
                         time.monotonic(), served.metres_per_unit)
        try:
            self.on_depth(out)
        except Exception as exc:  # noqa: BLE001 - a failing publisher must not stop serving
            return self._skip(LiveSkipped.PUBLISH_ERROR, frame, exc)
        frame.served_live = True
        done = time.monotonic()
        with self._cv:
            self.published += 1
            self._latency.append(done - arrival)
            self._publish_s.append(done - out.served)
        self._hand_over(frame, served)
        return out

    def _hand_over(self, frame: Frame, served: Served) -> None:
        """Record the served depth for the window that will take the frame; a failure costs
        only the window's own prediction of it (logged, throttled)."""
        if self.live_depths is None:
            return
        try:
            self.live_depths.record(frame.image, served.generation, served.raw)
        except Exception as exc:  # noqa: BLE001 - the hand-over must not stop serving
            self._warn("hand_over", f"frame {frame.name}: live depth not handed over to its "
                                    f"window: {type(exc).__name__}: {exc}")

    def _skip(self, key: LiveSkipped, frame: Frame, exc: Exception) -> None:
        """Count ``frame`` as skipped for ``key`` and log why (throttled)."""
        with self._cv:
            self.skipped[key] += 1
        self._warn(key, f"frame {frame.name}: {key.description}: "
                        f"{type(exc).__name__}: {exc}")

    def _run(self, warm_up: Callable[[], object] | None = None,
             ready: threading.Event | None = None) -> None:
        try:
            if warm_up is not None:
                warm_up()
        except Exception as exc:  # noqa: BLE001 - a failed warm-up only costs the first frame
            self.log.warning(f"live serving: warm-up failed ({type(exc).__name__}: {exc}); "
                             f"the first frame pays the one-time costs")
        finally:
            if ready is not None:
                ready.set()
        while True:
            with self._cv:
                while not self._queue and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return
                frame, arrival = self._queue.popleft()
                self._busy += 1
            try:
                self.serve_one(frame, arrival)
            finally:
                with self._cv:
                    self._busy -= 1
                    self._cv.notify_all()

    # -- accounting -----------------------------------------------------------------------
    @property
    def pending(self) -> int:
        with self._cv:
            return len(self._queue) + self._busy

    def counters(self) -> dict[str, object]:
        with self._cv:
            return {"received": self.received, "published": self.published,
                    "skipped": dict(self.skipped), "pending": len(self._queue) + self._busy,
                    "version": self.serving.version, "weights_age_s": self.serving.age_s,
                    **latency_figures(self._latency, self._publish_s)}

    def _warn(self, key: str, message: str) -> None:
        if self._throttle.due(key):
            self.log.warning(message)


def latency_figures(latency, publish_s) -> dict[str, float]:
    """p50 / p95 / max of arrival-to-published latency and the max publish time, in s (NaN
    before the first published frame)."""
    lat = np.asarray(latency, dtype=float)
    if lat.size == 0:
        return dict.fromkeys(LATENCY_KEYS, float("nan"))
    p50, p95 = np.percentile(lat, [50, 95])
    return dict(zip(LATENCY_KEYS, (float(p50), float(p95), float(lat.max()),
                                   float(max(publish_s))), strict=True))
