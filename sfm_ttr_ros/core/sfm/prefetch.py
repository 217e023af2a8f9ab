"""The next window's SfM while the current window refines: stage 1 of the method off the
critical path.

A window's time from its last frame to its refined weights is SfM (Sec. 3.1) + alignment +
refinement; in a stream the next window's frames are usually all queued before the current
window has finished refining, and SfM does not depend on the network's weights. So
:class:`SfmPrefetch` reconstructs those frames in a thread of its own, with a reconstructor of
its own (own workspace and feature cache), while the window worker refines: on 2 CPU cores the
worker refines on one OpenMP thread (``worker_threads``) and the live server takes part of the
other, so SfM uses what is left; on a GPU machine SfM on the CPU and refinement on the GPU
overlap entirely. When the next window begins, :meth:`SfmPrefetch.take` hands over the
reconstruction of exactly those frames (waiting for it if it is still running); anything else
(other frames, other intrinsics, a failure) is discarded and the window reconstructs as usual.

The stream (:class:`~sfm_ttr_ros.core.stream.window_runner.WindowRunner`) begins it from its input
callback, at the first frame that finds the next window's frames all queued once the running
window's own SfM has ended (:meth:`~sfm_ttr_ros.core.sfm.source.SfmSource.prefetch`); the thread
lowers its own OS priority to the worker's
(:func:`~sfm_ttr_ros.core.threads.lower_thread_priority`), so live serving keeps the cores
first.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Sequence

from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.sfm.reconstruction import SfmCancelled, SfmConfig, SfmReconstructor, SfmResult
from sfm_ttr_ros.core.threads import lower_thread_priority

log = logging.getLogger(__name__)


#: Finished reconstructions kept for their window (the next one, and the one after it when a
#: window's frames were all queued before the previous one took its own).
KEEP_DONE = 2

_Key = tuple[tuple[str, ...], Intrinsics]


class SfmPrefetch:
    """Reconstructions ahead of their window, one at a time in a background thread (see the
    module docstring); finished ones wait for :meth:`take` (the :data:`KEEP_DONE` newest)."""

    def __init__(self, config: SfmConfig | None = None, nice: int = 0) -> None:
        self.reconstructor = SfmReconstructor(config)
        self.nice = nice
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._running: _Key | None = None
        self._done: dict[_Key, tuple[SfmResult | None, BaseException | None]] = {}
        self.started = 0  # reconstructions begun ahead
        self.used = 0  # ... handed to their window
        self.discarded = 0  # ... whose window did not come as predicted, or that failed

    @staticmethod
    def _key(frames: Sequence[Frame], intrinsics: Intrinsics) -> _Key:
        return tuple(f.name for f in frames), intrinsics

    @property
    def busy(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def set_config(self, config: SfmConfig) -> None:
        """Options for the next reconstruction begun ahead."""
        self.reconstructor.config = config

    def start(self, frames: Sequence[Frame], intrinsics: Intrinsics) -> bool:
        """Begin reconstructing ``frames`` now (any thread); False (nothing begun) while one
        is running, or when these frames are running or done already."""
        key = self._key(frames, intrinsics)
        with self._lock:
            if self.busy or key == self._running or key in self._done:
                return False
            self._running = key
            self._thread = threading.Thread(target=self._run, args=(key, list(frames),
                                                                      intrinsics),
                                            name="sfm-prefetch", daemon=True)
            self.started += 1
            self._thread.start()
        return True

    def _run(self, key: _Key, frames: list[Frame], intrinsics: Intrinsics) -> None:
        lower_thread_priority(self.nice)
        result, error = None, None
        try:
            result = self.reconstructor.reconstruct(frames, intrinsics)
        except BaseException as exc:  # noqa: BLE001 - handed to take(), which decides
            error = exc
        with self._lock:
            self._done[key] = (result, error)
            self._running = None
            while len(self._done) > KEEP_DONE:  # the oldest: its window has gone by
                del self._done[next(iter(self._done))]
                self.discarded += 1

    def take(self, frames: Sequence[Frame], intrinsics: Intrinsics) -> SfmResult | None:
        """The reconstruction of exactly ``frames`` with ``intrinsics`` if one was begun
        (waits for it to end), else None. A cancelled or failed run gives None (the window then
        reconstructs itself, and reports a real failure as usual)."""
        key = self._key(frames, intrinsics)
        with self._lock:
            thread = self._thread if key == self._running else None
            if thread is None and key not in self._done:
                return None
        if thread is not None:
            thread.join()
        with self._lock:
            result, error = self._done.pop(key, (None, None))
            if error is not None or result is None:
                self.discarded += 1
            else:
                self.used += 1
        if error is not None and not isinstance(error, SfmCancelled):
            log.warning("SfM begun ahead failed (%s: %s): the window reconstructs again",
                        type(error).__name__, error)
        return result if error is None else None

    def cancel(self) -> None:
        """Stop a running reconstruction (thread-safe)."""
        self.reconstructor.cancel()

    def close(self, timeout: float | None = None) -> None:
        """Cancel, wait for the thread (``timeout``), remove the workspace."""
        self.cancel()
        if self._thread is not None:
            self._thread.join(timeout)
        self.reconstructor.close()

    def counters(self) -> dict[str, int]:
        return {"started": self.started, "used": self.used, "discarded": self.discarded}
