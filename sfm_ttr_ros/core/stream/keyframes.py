"""Which frames become keyframes: at the rate the windows can afford.

A window of ``window_size`` keyframes takes the worker T seconds (SfM, refinement,
predictions) and takes ``window_stride`` new keyframes from the stream. With keyframes every Δ
seconds the worker keeps up when stride·Δ ≥ T, so ``keyframe_policy``:

* ``all``: every frame is a keyframe (as far as ``min_keyframe_interval_s`` and
  ``min_keyframe_motion`` allow). A camera faster than the windows fills the queue, and the
  overload rule then skips whole windows;
* ``auto`` (the default): keyframes at least Δ = max(min_keyframe_interval_s,
  HEADROOM·median(T of the last WINDOW_HISTORY windows)/window_stride) apart, Δ at most
  ``max_keyframe_interval_s`` (the widest spacing SfM and the photometric loss are trusted
  with); before the first window has run, Δ = min_keyframe_interval_s (the first window's frames
  are consecutive, so the first weights come soon). A stream slower than 1/Δ keeps every frame: at
  1 Hz nothing changes;
* ``newest``: no thinning; windows of consecutive frames taken from the NEWEST frames.

Under ``auto`` and ``newest`` a queued frame is **stale** when the frames queued after it
already span the next window, (newest stamp − its stamp) ≥ window_size·max(Δ, frame interval):
it is not a keyframe, and the keyframes collected before it are dropped from the window being
filled, so that every window covers the most recent span of the stream instead of one from
seconds ago, and the worker is never behind by more than a window. Each non-keyframe says why:
``not_keyframe`` (thinned) or ``stale`` (skipped behind).
"""

from __future__ import annotations

import math
from collections import deque

import cv2
import numpy as np

from sfm_ttr_ros.core.frames import Frame

#: Keyframe policies (``keyframe_policy``).
KEYFRAME_POLICIES = ("auto", "all", "newest")
#: Windows whose duration sets the auto interval (their median).
WINDOW_HISTORY = 5
#: The auto interval's margin over the windows' pace: keyframes a little slower than the worker
#: takes them, so the queue stays short.
HEADROOM = 1.2
#: Frames whose stamps give the stream's frame interval (their median difference).
CADENCE_FRAMES = 10
THUMB_WIDTH = 64


def thumbnail(image: np.ndarray) -> np.ndarray:
    """A 64-pixel-wide grey thumbnail (the motion floor's measure)."""
    h, w = image.shape[:2]
    tw = min(THUMB_WIDTH, w)
    th = max(1, round(h * tw / w))
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    return cv2.resize(grey, (tw, th), interpolation=cv2.INTER_AREA).astype(np.float32)


class KeyframeSelector:
    """The keyframe rule of one stream (module docstring); the worker thread's state."""

    def __init__(self) -> None:
        self._stamp: float | None = None  # the last keyframe's
        self._thumb: np.ndarray | None = None
        self._window_seconds: deque[float] = deque(maxlen=WINDOW_HISTORY)
        self._stamps: deque[float] = deque(maxlen=CADENCE_FRAMES + 1)
        self.interval_s = 0.0  # Δ now
        self.needed_s = 0.0  # the interval the windows' pace asks for (before the widest cap)
        self.reason = "every_frame"  # what sets Δ: every_frame, min_interval, window_time, widest
        self.stale = 0  # frames skipped behind so far

    def reset(self) -> None:
        """A new window starts from scratch (camera change, stamps back, flush)."""
        self._stamp = self._thumb = None

    def window_done(self, seconds: float) -> None:
        """A window the worker processed took ``seconds`` (not one skipped for overload)."""
        if math.isfinite(seconds) and seconds > 0:
            self._window_seconds.append(float(seconds))

    def frame_interval(self) -> float:
        """The stream's frame interval: median stamp difference of its last frames (0 with
        fewer than two)."""
        s = list(self._stamps)
        return float(np.median(np.diff(s))) if len(s) >= 2 else 0.0

    def update_interval(self, policy: str, floor_s: float, widest_s: float, stride: int) -> float:
        """Δ for ``policy`` from the windows' pace (module docstring); sets ``reason``."""
        self.needed_s = (HEADROOM * float(np.median(self._window_seconds)) / max(1, stride)
                         if policy == "auto" and self._window_seconds else 0.0)
        interval, self.reason = max(floor_s, 0.0), "min_interval" if floor_s > 0 else \
            "every_frame"
        if self.needed_s > interval:
            interval, self.reason = self.needed_s, "window_time"
        if policy == "auto" and interval > widest_s > 0:
            interval, self.reason = max(widest_s, floor_s), "widest"
        self.interval_s = interval
        return interval

    def is_stale(self, frame: Frame, policy: str, floor_s: float, widest_s: float,
                 window_size: int, stride: int, newest_stamp: float | None) -> bool:
        """Whether ``frame`` (the next one the worker takes) is stale (module docstring);
        ``newest_stamp``: the stamp of the newest frame queued after it (None: none). Called
        for every frame taken, before :meth:`is_keyframe`: it also keeps the stream's cadence
        and Δ up to date."""
        self._stamps.append(frame.stamp)
        interval = self.update_interval(policy, floor_s, widest_s, stride)
        if policy != "all" and newest_stamp is not None:
            span = window_size * max(interval, self.frame_interval())
            if span > 0 and newest_stamp - frame.stamp >= span:
                self.stale += 1
                self.reset()
                return True
        return False

    def is_keyframe(self, frame: Frame, min_motion: float) -> bool:
        """Whether a frame that is not stale is a keyframe: Δ (:meth:`update_interval`, set
        by :meth:`is_stale`) after the last keyframe and, with ``min_motion`` > 0, that much
        grey-level change from it."""
        interval = self.interval_s
        if self._stamp is not None and interval > 0 and \
                frame.stamp - self._stamp < interval - 1e-9:
            return False
        thumb = thumbnail(frame.image) if min_motion > 0 else None
        if (self._stamp is not None and thumb is not None and self._thumb is not None
                and self._thumb.shape == thumb.shape
                and float(np.mean(np.abs(thumb - self._thumb))) < min_motion):
            return False
        self._stamp, self._thumb = frame.stamp, thumb
        return True
