"""The options of the online windowing (``StreamSettings``) and their validation.

What each option does to a frame is in docs/node.md, "How frames flow"."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sfm_ttr_ros.core.errors import InputError, check_choice
from sfm_ttr_ros.core.stream.keyframes import KEYFRAME_POLICIES


@dataclass
class StreamSettings:
    """Options of the online windowing (the node's parameters of the same names)."""

    window_size: int = 15
    # new keyframes between windows; 0 = window_size (windows side by side), so that a
    # window_size given alone never conflicts with a stride meant for another size
    window_stride: int = 0
    # > 0: the stream's first window closes after this many keyframes instead of window_size,
    # so that the first refined weights reach the live output sooner (a short clip); 0 = off
    first_window_size: int = 0
    # which frames are keyframes (core/stream/keyframes.py): newest = windows of the newest
    # consecutive frames (stale frames skipped), all = every frame
    keyframe_policy: str = "newest"
    min_keyframe_interval_s: float = 0.0
    min_keyframe_motion: float = 0.0  # mean abs grey difference on thumbnails, 0 = off
    # input queue bound (frames holding an image); overflow drops the oldest queued frame
    max_pending: int = 200
    overload_pending: int = 50  # more queued frames than this at a window: skip refinement; 0 off
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
    serve_every_steps: int = 10
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
        """Queued frames that keep their image under the backlog bound (docs/node.md, "How
        frames flow", rule 5); 0 = no bound (unrefined frames are republished, or no overload
        rule)."""
        if self.republish_unrefined or self.overload_pending <= 0:
            return 0
        return self.overload_pending + self.window_size

    def __post_init__(self) -> None:
        if self.window_size < 2:
            raise InputError(f"window_size must be >= 2, got {self.window_size}")
        if self.first_window_size and not 2 <= self.first_window_size <= self.window_size:
            raise InputError(f"first_window_size must be 0 or in [2, window_size="
                             f"{self.window_size}], got {self.first_window_size}")
        if self.window_stride == 0:
            self.window_stride = self.window_size
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
