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

The stream (:class:`~sfm_ttr_ros.core.stream.StreamProcessor`) begins it from whichever thread
sees the next window's frames queued (the worker at a window's start, or the input callback
while a window runs); the thread lowers its own OS priority to the worker's
(:func:`~sfm_ttr_ros.core.live.lower_thread_priority`), so live serving keeps the cores first.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Sequence

from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.live import lower_thread_priority
from sfm_ttr_ros.core.sfm import SfmCancelled, SfmConfig, SfmReconstructor, SfmResult

log = logging.getLogger(__name__)


class SfmPrefetch:
    """One reconstruction ahead, in a background thread (see the module docstring)."""

    def __init__(self, config: SfmConfig | None = None, nice: int = 0) -> None:
        self.reconstructor = SfmReconstructor(config)
        self.nice = nice
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._key: tuple[tuple[str, ...], Intrinsics] | None = None
        self._result: SfmResult | None = None
        self._error: BaseException | None = None
        self.started = 0  # reconstructions begun ahead
        self.used = 0  # ... handed to their window
        self.discarded = 0  # ... whose window did not come as predicted

    @property
    def busy(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def set_config(self, config: SfmConfig) -> None:
        """Options for the next reconstruction begun ahead."""
        self.reconstructor.config = config

    def start(self, frames: Sequence[Frame], intrinsics: Intrinsics) -> bool:
        """Begin reconstructing ``frames`` now (any thread); False (nothing begun) while one
        is running or already done for the same frames."""
        key = (tuple(f.name for f in frames), intrinsics)
        with self._lock:
            if self.busy or key == self._key:
                return False
            if self._key is not None:  # a finished one nobody took
                self.discarded += 1
            self._key, self._result, self._error = key, None, None
            self._thread = threading.Thread(target=self._run, args=(list(frames), intrinsics),
                                            name="sfm-prefetch", daemon=True)
            self.started += 1
            self._thread.start()
        return True

    def _run(self, frames: list[Frame], intrinsics: Intrinsics) -> None:
        lower_thread_priority(self.nice)
        try:
            self._result = self.reconstructor.reconstruct(frames, intrinsics)
        except BaseException as exc:  # noqa: BLE001 - handed to take(), which decides
            self._error = exc

    def take(self, frames: Sequence[Frame], intrinsics: Intrinsics) -> SfmResult | None:
        """The reconstruction of exactly ``frames`` with ``intrinsics`` if one was begun
        (waits for it to end), else None. A cancelled or failed run gives None (the window then
        reconstructs itself, and reports a real failure as usual)."""
        key = (tuple(f.name for f in frames), intrinsics)
        with self._lock:
            if self._key != key:
                return None
            thread = self._thread
        if thread is not None:
            thread.join()
        with self._lock:
            result, error = self._result, self._error
            self._key, self._result, self._error, self._thread = None, None, None, None
            if error is not None:
                self.discarded += 1
            else:
                self.used += 1
        if error is not None:
            if not isinstance(error, SfmCancelled):
                log.warning("SfM begun ahead failed (%s: %s): the window reconstructs again",
                            type(error).__name__, error)
            return None
        return result

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
