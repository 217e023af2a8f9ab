"""The stream's input queue: the one object the camera's threads and the window worker share.

Frames go in from any thread (:meth:`FrameQueue.put`, cheap, never blocked by heavy work) and
come out to the one worker (:meth:`FrameQueue.take`). The queue makes room when it is full and
bounds the images it keeps while the worker is behind (back-pressure: docs/node.md, "How frames
flow", rules 1 and 5), names each frame from a running counter (``f"{seq:010d}"``: unique per
stream, whatever the caller put in ``Frame.name``; stamps are not unique enough and SfM caches
features by name), counts the frames pending (queued, or taken and not yet accounted for), keeps
the arrival times the idle flush reads, and holds the stream's :class:`~.ledger.Ledger` under
its lock, so that a snapshot of the counters always balances."""

from __future__ import annotations

import dataclasses
import itertools
import threading
import time
from collections import deque
from collections.abc import Iterable, Iterator
from contextlib import contextmanager

import numpy as np

from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.outcomes import Dropped
from sfm_ttr_ros.core.stream.ledger import Ledger
from sfm_ttr_ros.core.stream.records import FrameOutput
from sfm_ttr_ros.core.stream.settings import StreamSettings

# the idle flush waits at least this many median frame intervals of the last
# IDLE_CADENCE_FRAMES arrivals (a 0.5 Hz camera with idle_flush_s 2 s: 6 s)
IDLE_INTERVALS = 3.0
IDLE_CADENCE_FRAMES = 10
#: Under keyframe_policy newest the queue may hold this many times ``max_pending`` frames, most
#: of them image-less (served live, waiting to be counted stale): a bound on memory all the same.
IMAGELESS_QUEUE_FACTOR = 10
#: The image of a frame whose pixels are no longer kept: a queued frame released by the backlog
#: bound, a window's cloud frame in the history (:class:`~.records.WindowStats`).
RELEASED_IMAGE = np.zeros((0, 0, 3), np.uint8)
RELEASED_IMAGE.flags.writeable = False

#: A queued frame and its intrinsics (None: a frame passed on without any, published unrefined).
Queued = tuple[Frame, Intrinsics | None]


class FrameQueue:
    """The bounded input queue of one stream, thread-safe (module docstring)."""

    def __init__(self) -> None:
        self._cv = threading.Condition()  # re-entrant: locked() may call the other methods
        self._frames: deque[Queued] = deque()
        self._images = 0  # queued frames that still hold their image
        self._seq = 0
        self._taken: dict[int, Frame] = {}  # frames out of the queue, not yet accounted (by id)
        self._cancelled = False
        self._last_input = time.monotonic()
        self._arrivals: deque[float] = deque(maxlen=IDLE_CADENCE_FRAMES + 1)  # monotonic s
        # the window the worker is running (frames, intrinsics): what the next one overlaps
        self._running: tuple[list[Frame], Intrinsics] | None = None
        self.ledger = Ledger()

    # -- in (any thread) -------------------------------------------------------------------------
    def put(self, frame: Frame, intrinsics: Intrinsics | None,
            settings: StreamSettings) -> Frame | None:
        """Name ``frame`` and queue it, making room first; returns the frame dropped for
        overflow, if any (counted, not yet reported). ``intrinsics`` None: the frame has none
        (the worker publishes it unrefined)."""
        with self._cv:
            self.ledger.received += 1
            frame.name = f"{self._seq:010d}"
            self._seq += 1
            dropped = self._make_room(settings)
            self._frames.append((frame, intrinsics))
            self._images += frame.image is not RELEASED_IMAGE
            keep = settings.backlog_images
            if keep and self._images > keep:  # the backlog bound
                self._release_oldest_served(self._images - keep)
            self._last_input = time.monotonic()
            self._arrivals.append(self._last_input)
            self._cv.notify_all()
        return dropped

    def reject(self, key: Dropped) -> None:
        """A frame received and dropped before it reached the queue."""
        with self._cv:
            self.ledger.received += 1
            self.ledger.drop(key)

    def _make_room(self, settings: StreamSettings) -> Frame | None:
        """Room for one more frame in a full queue (back-pressure): under ``keyframe_policy``
        newest the oldest frame the live output served gives its image up, else (or when none
        can) the oldest frame is dropped. Called under the lock."""
        bound = max(1, settings.max_pending)
        if settings.keyframe_policy != "all" and \
                len(self._frames) < IMAGELESS_QUEUE_FACTOR * bound:
            if self._images < bound or self._release_oldest_served(1):
                return None
        elif len(self._frames) < bound:
            return None
        dropped, _ = self._frames.popleft()
        self._images -= dropped.image is not RELEASED_IMAGE
        self.ledger.drop(Dropped.OVERFLOW)
        return dropped

    def _release_oldest_served(self, n: int) -> int:
        """The oldest ``n`` queued frames the live output served give their image up
        (:data:`RELEASED_IMAGE`); returns how many did. Called under the lock."""
        done = 0
        for i, (f, intr) in enumerate(self._frames):
            if done >= n:
                break
            if f.image is not RELEASED_IMAGE and f.served_live:
                self._frames[i] = (dataclasses.replace(f, image=RELEASED_IMAGE), intr)
                done += 1
        self.ledger.released += done
        self._images -= done
        return done

    def cancel(self) -> None:
        """Stop: :meth:`take` returns None at once, now and from now on."""
        with self._cv:
            self._cancelled = True
            self._cv.notify_all()

    @property
    def cancelled(self) -> bool:
        return self._cancelled

    # -- out (the worker) ------------------------------------------------------------------------
    def take(self, timeout: float | None) -> Queued | None:
        """The oldest queued frame, waiting up to ``timeout`` s for one (0: no wait); it stays
        pending until :meth:`settle` or :meth:`drop_taken`."""
        with self._cv:
            if not self._frames and not self._cancelled and timeout != 0.0:
                self._cv.wait(timeout)
            if not self._frames or self._cancelled:
                return None
            frame, intr = self._frames.popleft()
            self._images -= frame.image is not RELEASED_IMAGE
            self._taken[id(frame)] = frame
            return frame, intr

    def settle(self, outs: Iterable[FrameOutput]) -> None:
        """Frames taken that came out (refined or unrefined): counted, no longer pending."""
        outs = list(outs)
        with self._cv:
            self.ledger.account(outs)
            for o in outs:
                self._taken.pop(id(o.frame), None)

    def drop_taken(self, frames: Iterable[Frame], key: Dropped) -> None:
        """Frames taken that are dropped with ``key``: counted, no longer pending."""
        frames = list(frames)
        with self._cv:
            self.ledger.drop(key, len(frames))
            for f in frames:
                self._taken.pop(id(f), None)

    def taken(self) -> list[Frame]:
        """The frames out of the queue not yet accounted for (in the worker's hands), in the
        order they were taken."""
        with self._cv:
            return list(self._taken.values())

    @contextmanager
    def locked(self) -> Iterator[Ledger]:
        """The ledger, under the lock (a counter only the worker moves, or a snapshot)."""
        with self._cv:
            yield self.ledger

    # -- the window in the worker's hands ----------------------------------------------------------
    def begin_window(self, frames: list[Frame], intrinsics: Intrinsics) -> None:
        with self._cv:
            self._running = (frames, intrinsics)

    def end_window(self) -> None:
        with self._cv:
            self._running = None

    def running_names(self) -> list[str]:
        """The frames of the window being processed (oldest first); [] between windows."""
        with self._cv:
            return [f.name for f in self._running[0]] if self._running is not None else []

    def next_window(self, stride: int, overlap: int) -> tuple[list[Frame], Intrinsics] | None:
        """While a window runs, the frames of the window after it when they are all queued: the
        running window's last ``overlap`` frames and the ``stride`` oldest queued ones, with its
        intrinsics and image size, every image kept, stamps rising (None otherwise)."""
        with self._cv:
            if self._running is None or len(self._frames) < stride:
                return None
            running, intr = self._running
            queued = list(itertools.islice(self._frames, stride))
        frames = (running[len(running) - overlap:] if overlap > 0 else []) + [f for f, _ in queued]
        if (len(frames) < 2 or any(i != intr for _, i in queued)
                or any(f.image is RELEASED_IMAGE or f.size != (intr.width, intr.height)
                       for f in frames)
                or any(b.stamp <= a.stamp for a, b in itertools.pairwise(frames))):
            return None
        return frames, intr

    # -- counts and timing -----------------------------------------------------------------------
    def pending(self) -> int:
        """Frames received and not accounted for yet: queued, or taken by the worker."""
        with self._cv:
            return len(self._frames) + len(self._taken)

    def queued(self) -> int:
        with self._cv:
            return len(self._frames)

    def counters(self) -> dict[str, object]:
        """The ledger's counters with the frames pending and queued, one consistent snapshot."""
        with self._cv:
            return self.ledger.counters(self.pending(), self.queued())

    def behind(self, last_stamp: float | None) -> float:
        """How far the worker is behind the camera: the newest queued frame's stamp minus
        ``last_stamp``, that of the last frame it took (0 when nothing waits)."""
        newest = self.newest_stamp()
        if newest is None or last_stamp is None:
            return 0.0
        return max(0.0, newest - last_stamp)

    def newest_stamp(self) -> float | None:
        """The stamp of the newest frame queued (None: the queue is empty)."""
        with self._cv:
            return self._frames[-1][0].stamp if self._frames else None

    def __iter__(self) -> Iterator[Queued]:
        """The queued frames, oldest first, as they are now."""
        with self._cv:
            return iter(list(self._frames))

    def idle_after(self, idle_flush_s: float) -> float:
        """Seconds without input before the idle flush: ``idle_flush_s``, or
        :data:`IDLE_INTERVALS` median frame intervals of the last arrivals when longer (after
        a single frame, whose camera's interval is not known yet, IDLE_INTERVALS x
        ``idle_flush_s``)."""
        with self._cv:
            arrivals = list(self._arrivals)
        if idle_flush_s <= 0 or not arrivals:
            return idle_flush_s
        interval = float(np.median(np.diff(arrivals))) if len(arrivals) >= 2 else idle_flush_s
        return max(idle_flush_s, IDLE_INTERVALS * interval)

    def idle_for(self) -> float:
        """Seconds since the last frame was queued (or since :meth:`restart_idle`)."""
        return time.monotonic() - self._last_input

    def restart_idle(self) -> None:
        """The idle flush ran: the next one waits a full idle period again."""
        self._last_input = time.monotonic()
