"""Where a window's reconstruction comes from: its own SfM, the one begun ahead of it, or the
stream's carried map (``sfm.mode``).

Batch (``sfm.mode: batch``): :class:`SfmSource` holds the window worker's reconstructor and the
reconstructions begun ahead (:class:`~sfm_ttr_ros.core.sfm.prefetch.SfmPrefetch`) with their
gate: no SfM is begun ahead while the running window's own SfM has not ended. On a few cores two
reconstructions at once slowed the current window's (a GPU machine held to 2 cores: first
weights 6.8 s after the window's last frame instead of 4.2 s); the stream asks again at its next
frame.

Streaming (``sfm.mode: streaming``): it holds a
:class:`~sfm_ttr_ros.core.sfm.streaming_map.StreamingSfm` instead. The stream admits each
keyframe as it takes it (:meth:`SfmSource.admit`: features, matches, registration into the
map), so a window's :meth:`SfmSource.reconstruct` only maps what is left and collects; a fresh
mapping replaces the continuation when it fits badly (:attr:`SfmSource.last_mapping` says which
and why). Nothing is begun ahead (nothing is left to begin).
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
from sfm_ttr_ros.core.sfm.streaming_map import StreamingSfm, StreamingSfmConfig


class SfmSource:
    """A stream's reconstructions: the window's own, or taken from those begun ahead."""

    def __init__(self, config: SfmConfig, workspace: str | Path | None = None):
        self.config = config
        self.reconstructor = SfmReconstructor(config, workspace)
        # the stream's carried map under sfm.mode streaming (None: batch)
        self.streaming = (StreamingSfm(StreamingSfmConfig(sfm=config))
                          if config.mode == "streaming" else None)
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
        if (config.mode == "streaming") != (self.streaming is not None):  # the mode changed
            if self.streaming is not None:
                self.streaming.close()
            self.streaming = (StreamingSfm(StreamingSfmConfig(sfm=config))
                              if config.mode == "streaming" else None)
        elif self.streaming is not None:
            self.streaming.set_config(config)
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
            if self.streaming is not None:
                return self.streaming.reconstruct(frames, intrinsics), False
            sfm = (self._prefetch.take(frames, intrinsics) if self._prefetch is not None
                   else None)
            if sfm is not None:
                return sfm, True
            return self.reconstructor.reconstruct(frames, intrinsics), False
        finally:
            self._own_pending = False

    def admit(self, frame: Frame, intrinsics: Intrinsics) -> bool:
        """A keyframe the stream took into the window being filled: in streaming mode its
        features, matches and registration into the carried map now (True); batch: nothing
        (False; the window does it all after its last frame)."""
        if self.streaming is None:
            return False
        self.streaming.admit(frame, intrinsics)
        return True

    def retain(self, names: Sequence[str]) -> None:
        """The frames the stream's future windows may still take (streaming mode: the others
        admitted are forgotten, :meth:`StreamingSfm.retain`)."""
        if self.streaming is not None:
            self.streaming.retain(names)

    @property
    def last_mapping(self) -> tuple[str, str]:
        """How the last window was mapped: ("continued" | "fresh", the reason a fresh mapping
        replaced the continuation); ("", "") in batch mode."""
        return self.streaming.last_mapping if self.streaming is not None else ("", "")

    def streaming_counters(self) -> dict[str, int]:
        """Streaming mode's windows continued and mapped afresh, and the keyframes admitted but
        not registered into the map yet ({} in batch mode)."""
        st = self.streaming
        if st is None:
            return {}
        return {"continued": st.continuations, "fresh": st.fresh_mappings,
                "admitted_unmapped": st.unmapped()}

    @property
    def frames_extracted(self) -> int:
        """Frames whose features were extracted, by the batch reconstructor and the streaming
        front end."""
        extracted = self.reconstructor.frames_extracted
        if self.streaming is not None:
            extracted += self.streaming.frontend.frames_extracted
        return extracted

    def prefetch(self, frames: Sequence[Frame], intrinsics: Intrinsics) -> bool:
        """Begin the SfM of a coming window now, in the background; :meth:`reconstruct` of
        exactly these frames then takes it. False when one is still running, or while the
        current window has not finished its own SfM (module docstring)."""
        if self._own_pending or self.streaming is not None:
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
        if self.streaming is not None:
            self.streaming.close()
        if self._prefetch is not None:
            self._prefetch.close()
