"""Which frames the windows take: the newest ones, when the camera is faster than the windows.

A window of ``window_size`` keyframes takes the worker T seconds (SfM, refinement,
predictions) and ``window_stride`` new keyframes from the stream: with a frame every Δ seconds
the worker keeps up with every frame when stride·Δ ≥ T (2 CPU cores, KITTI-size frames: T ≈
10–18 s against 1.5 s of frames at 10 Hz). ``keyframe_policy``:

* ``newest`` (the default): windows of consecutive frames taken from the NEWEST frames. A
  queued frame is **stale** when the frames queued after it already span the next window,
  (newest stamp − its stamp) ≥ window_size·max(min_keyframe_interval_s, frame interval), or
  when the queue, full, took its image (core/stream/frame_queue.py, back-pressure): it is
  skipped, and the keyframes collected before it leave the window being filled, so that every
  window covers the latest seconds of the stream and the worker is never more than a window
  behind. A camera the windows keep up with loses no frame: at 1 Hz nothing changes;
* ``all``: every frame a keyframe; a camera faster than the windows fills the queue, and the
  overload rule then skips whole windows (the paper's windows, and the benchmark's).

Both keep ``min_keyframe_interval_s`` (a floor between keyframes, stamps) and
``min_keyframe_motion`` (that much grey-level change from the last keyframe). Thinning the
stream to the windows' pace instead (keyframes stride·Δ ≥ T apart) was measured and lost:
keyframes further apart register fewer frames and refine worse (docs/decisions.md, "Keyframes").
Each frame the rule passes on says why: ``not_keyframe`` (floor or motion) or ``stale``.
"""

from __future__ import annotations

import math
from collections import deque

import cv2
import numpy as np

from sfm_ttr_ros.core.frames import Frame

#: Keyframe policies (``keyframe_policy``).
KEYFRAME_POLICIES = ("newest", "all")
#: Windows whose duration gives the windows' pace (their median; diagnostics).
WINDOW_HISTORY = 5
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


def keyframe_interval(floor_s: float) -> tuple[float, str]:
    """(the floor between keyframes, what sets it: ``every_frame`` or ``min_interval``) for
    ``min_keyframe_interval_s`` (diagnostics)."""
    return max(floor_s, 0.0), ("min_interval" if floor_s > 0 else "every_frame")


class KeyframeSelector:
    """The keyframe rule of one stream (module docstring); the worker thread's state."""

    def __init__(self) -> None:
        self._stamp: float | None = None  # the last keyframe's
        self._thumb: np.ndarray | None = None
        self._window_seconds: deque[float] = deque(maxlen=WINDOW_HISTORY)
        self._stamps: deque[float] = deque(maxlen=CADENCE_FRAMES + 1)
        self.stale = 0  # frames skipped behind so far

    def reset(self) -> None:
        """A new window starts from scratch (camera change, stamps back, flush)."""
        self._stamp = self._thumb = None

    def window_done(self, seconds: float) -> None:
        """A window the worker processed took ``seconds`` (not one skipped for overload)."""
        if math.isfinite(seconds) and seconds > 0:
            self._window_seconds.append(float(seconds))

    def needed_s(self, stride: int) -> float:
        """The frame interval at which the windows would keep up with every frame: the median
        time of the last windows over ``stride`` (0 before the first window)."""
        if not self._window_seconds:
            return 0.0
        return float(np.median(self._window_seconds)) / max(1, stride)

    def frame_interval(self) -> float:
        """The stream's frame interval: median stamp difference of its last frames (0 with
        fewer than two)."""
        s = list(self._stamps)
        return float(np.median(np.diff(s))) if len(s) >= 2 else 0.0

    def is_stale(self, frame: Frame, policy: str, floor_s: float, window_size: int,
                 newest_stamp: float | None, released: bool = False) -> bool:
        """Whether ``frame`` (the next one the worker takes) is stale (module docstring);
        ``newest_stamp``: the stamp of the newest frame queued after it (None: none);
        ``released``: the queue took its image while the worker was behind (stale under
        newest whatever the stamps). Called for every frame taken, before
        :meth:`is_keyframe`: it also keeps the stream's cadence."""
        self._stamps.append(frame.stamp)
        if policy == "all":
            return False
        span = window_size * max(floor_s, self.frame_interval())
        behind = newest_stamp is not None and span > 0 and newest_stamp - frame.stamp >= span
        if released or behind:
            self.stale += 1
            self.reset()
            return True
        return False

    def is_keyframe(self, frame: Frame, floor_s: float, min_motion: float) -> bool:
        """Whether a frame that is not stale is a keyframe: ``floor_s`` seconds after the last
        keyframe and, with ``min_motion`` > 0, that much grey-level change from it."""
        if self._stamp is not None and floor_s > 0 and \
                frame.stamp - self._stamp < floor_s - 1e-9:
            return False
        thumb = thumbnail(frame.image) if min_motion > 0 else None
        if (self._stamp is not None and thumb is not None and self._thumb is not None
                and self._thumb.shape == thumb.shape
                and float(np.mean(np.abs(thumb - self._thumb))) < min_motion):
            return False
        self._stamp, self._thumb = frame.stamp, thumb
        return True
