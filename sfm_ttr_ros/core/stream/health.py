"""Is the node alive and fed? The worker's ERROR and the input's silence of its
``/diagnostics`` statuses and the rates among their values, ROS-free (docs/node.md
"Diagnostics").

The levels follow diagnostic_msgs/DiagnosticStatus and the diagnostic_aggregator's reading of
them (REP 107's diagnostics, ROS 2 ``diagnostic_updater``): ERROR when the node cannot do its
job, the window worker thread has died (no window will run again; ``worker_alive``); a WARN
when no input image arrived for ``diagnostics.stale_after_s`` seconds, counted from the node's
start before the first image (so a wrong remap or an unmatched QoS is a WARN, not OK; 0 =
never). STALE is not the node's to say: the aggregator reserves it for a status no longer
received.

Rates (:class:`RateMeter`) are events per second over the last :data:`RATE_INTERVAL_S`
seconds (the time since the node started while that is shorter), on the steady clock: what
arrived and left the node on the wall clock, whatever clock stamps the messages (a bag replayed
at twice its speed reads twice the camera's rate; a paused bag goes silent).
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable

RATE_INTERVAL_S = 5.0  # the recent interval the rates are taken over
#: the node's outputs whose rates are reported: ~/depth (live), ~/depth_refined (windows)
RATED_OUTPUTS = ("depth", "depth_refined")


class RateMeter:
    """Events per second over the last ``interval_s`` seconds (thread-safe); ``clock``: seconds
    on a steady clock (``time.monotonic``)."""

    def __init__(self, interval_s: float = RATE_INTERVAL_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.interval_s = float(interval_s)
        self._clock = clock
        self._start = clock()
        self._times: collections.deque[float] = collections.deque()
        self._lock = threading.Lock()
        self.count = 0
        self.last: float | None = None  # the clock at the last event (None before the first)

    def tick(self) -> None:
        """One event now."""
        now = self._clock()
        with self._lock:
            self._times.append(now)
            self.count += 1
            self.last = now
            self._forget(now)

    def _forget(self, now: float) -> None:
        while self._times and self._times[0] <= now - self.interval_s:
            self._times.popleft()

    def hz(self) -> float:
        """Events per second over the recent interval (0 before any time has passed)."""
        now = self._clock()
        with self._lock:
            self._forget(now)
            span = min(self.interval_s, now - self._start)
            return len(self._times) / span if span > 0 else 0.0

    def silent_s(self) -> float:
        """Seconds since the last event, or since the meter started before the first."""
        now = self._clock()
        with self._lock:
            return now - (self._start if self.last is None else self.last)


class Health:
    """The node's liveness: its input and output rates, whether the window worker lives, how
    long the input has been silent. ``worker_alive`` and ``stale_after_s`` are read at each
    status (the parameter is live); ``input_topic`` names the input in the messages."""

    def __init__(self, worker_alive: Callable[[], bool], stale_after_s: Callable[[], float],
                 input_topic: str = "image", clock: Callable[[], float] = time.monotonic,
                 interval_s: float = RATE_INTERVAL_S) -> None:
        self._worker_alive = worker_alive
        self._stale_after_s = stale_after_s
        self.input_topic = input_topic
        self.images = RateMeter(interval_s, clock)
        self.outputs = {name: RateMeter(interval_s, clock) for name in RATED_OUTPUTS}

    def image_received(self) -> None:
        """An image message arrived (read or not)."""
        self.images.tick()

    def published(self, output: str) -> None:
        """A frame left on ``output`` (one of :data:`RATED_OUTPUTS`)."""
        self.outputs[output].tick()

    def rate_values(self) -> dict[str, object]:
        """``rate.image_hz`` and ``rate.<output>_hz``."""
        out: dict[str, object] = {"rate.image_hz": self.images.hz()}
        out.update({f"rate.{name}_hz": meter.hz() for name, meter in self.outputs.items()})
        return out

    def input_values(self) -> dict[str, object]:
        """``input.silent_s``: seconds since the last image (since start-up before one)."""
        return {"input.silent_s": self.images.silent_s()}

    def worker_values(self) -> dict[str, object]:
        """``worker_alive``."""
        return {"worker_alive": bool(self._worker_alive())}

    def worker_problem(self) -> str | None:
        """Why the node cannot do its job (an ERROR): the worker has died; else None."""
        if not self._worker_alive():
            return "window worker has died: no window will run (restart the node)"
        return None

    def input_problem(self) -> str | None:
        """Why the input looks cut off (a WARN): silent longer than ``stale_after_s``; else
        None."""
        limit = float(self._stale_after_s())
        silent = self.images.silent_s()
        if limit > 0 and silent > limit:
            since = "the last image" if self.images.count else "start-up, none yet"
            return (f"no image on {self.input_topic} for {silent:.1f} s (since {since}; "
                    f"diagnostics.stale_after_s {limit:g})")
        return None
