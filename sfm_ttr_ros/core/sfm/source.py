"""Where a window's reconstruction comes from: its own SfM, or the one begun ahead of it.

:class:`SfmSource` holds the window worker's reconstructor and the reconstructions begun ahead
(:class:`~sfm_ttr_ros.core.sfm.prefetch.SfmPrefetch`) with their gate: no SfM is begun ahead
while the running window's own SfM has not ended. On a few cores two reconstructions at once
slowed the current window's (a GPU machine held to 2 cores: first weights 6.8 s after the
window's last frame instead of 4.2 s); the stream asks again at its next frame.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from pathlib import Path

from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.sfm.config import SfmConfig
from sfm_ttr_ros.core.sfm.prefetch import SfmPrefetch
from sfm_ttr_ros.core.sfm.reconstruction import SfmReconstructor
from sfm_ttr_ros.core.sfm.result import SfmResult


class SfmSource:
    """A stream's reconstructions: the window's own, or taken from those begun ahead."""

    def __init__(self, config: SfmConfig, workspace: str | Path | None = None):
        self.config = config
        self.reconstructor = SfmReconstructor(config, workspace)
        self._prefetch: SfmPrefetch | None = None  # created at the first prefetch()
        self.nice = 0  # OS priority of the SfM-ahead thread (the window worker's)
        # a window runs and its own SfM has not ended yet (set by begin_window, cleared once
        # its SfM ends; a window that stops before SfM runs none, so nothing waits on it)
        self._own_pending = False
        self._lock = threading.Lock()

    def set_config(self, config: SfmConfig) -> None:
        """New options, from the next reconstruction on (ahead ones included)."""
        self.config = config
        self.reconstructor.config = config
        if self._prefetch is not None:
            self._prefetch.set_config(config)

    def begin_window(self) -> None:
        """A window begins: no SfM is begun ahead until its own has ended."""
        self._own_pending = True

    def reconstruct(self, frames: Sequence[Frame], intrinsics: Intrinsics
                    ) -> tuple[SfmResult, bool]:
        """The window's reconstruction (Sec. 3.1) and whether it was made ahead (while the
        previous window refined)."""
        try:
            sfm = (self._prefetch.take(frames, intrinsics) if self._prefetch is not None
                   else None)
            if sfm is not None:
                return sfm, True
            return self.reconstructor.reconstruct(frames, intrinsics), False
        finally:
            self._own_pending = False

    def prefetch(self, frames: Sequence[Frame], intrinsics: Intrinsics) -> bool:
        """Begin the SfM of a coming window now, in the background; :meth:`reconstruct` of
        exactly these frames then takes it. False when one is still running, or while the
        current window has not finished its own SfM (module docstring)."""
        if self._own_pending:
            return False
        with self._lock:
            if self._prefetch is None:
                self._prefetch = SfmPrefetch(self.config, self.nice)
        return self._prefetch.start(frames, intrinsics)

    def counters(self) -> dict[str, int]:
        """SfM reconstructions begun ahead: started, used by their window, discarded."""
        if self._prefetch is None:
            return {"started": 0, "used": 0, "discarded": 0}
        return self._prefetch.counters()

    def cancel(self) -> None:
        """Interrupt the running reconstructions (from another thread)."""
        self.reconstructor.cancel()
        if self._prefetch is not None:
            self._prefetch.cancel()

    def close(self) -> None:
        self.reconstructor.close()
        if self._prefetch is not None:
            self._prefetch.close()
