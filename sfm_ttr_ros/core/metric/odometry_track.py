"""Travelled distance from an odometry source, against SfM's camera path.

An odometry source (wheel odometry, a VIO, GNSS/INS like KITTI's OXTS, a pose file) gives the
camera's (or the robot's) position in metres at its own stamps. :class:`OdometryTrack` keeps the
last of them; for a window, the path length through the positions at its registered frames'
stamps (linear interpolation) over the SfM camera centres' path length is metres per SfM unit:

    m = Σ_j |p(t_{j+1}) − p(t_j)| / Σ_j |C_{j+1} − C_j|.

A path that runs along the robot's body frame and not its camera's differs by the lever arm
under rotation; over a window's second of driving that is well under a per cent.

A stamp more than :data:`JUMP_BACK_S` before the last one is a restart (a bag replayed again,
``ros2 bag play --loop``, a driver restarted): the track starts again from it (``resets``)
instead of refusing every later message; a stamp at or slightly before the last one is out of
order and refused. The stamp of the last position kept (:attr:`OdometryTrack.last_stamp`),
against the images', says when the source went silent: in the data's time, so that a paused
or sim-time bag and a benchmark that feeds every position at once read alike.
"""

from __future__ import annotations

import bisect
import threading
from collections import deque
from collections.abc import Sequence

import numpy as np

#: Positions kept (at 100 Hz: 50 s).
TRACK_LENGTH = 5000
#: A stamp this far (s) before the last one restarts the track; nearer, it is out of order.
JUMP_BACK_S = 1.0


class OdometryTrack:
    """Positions by stamp, added from any thread (the node's odometry callback)."""

    def __init__(self, length: int = TRACK_LENGTH):
        self._lock = threading.Lock()
        self._stamps: deque[float] = deque(maxlen=length)
        self._positions: deque[np.ndarray] = deque(maxlen=length)
        self.received = 0
        self.rejected = 0
        self.resets = 0  # restarts: a stamp more than JUMP_BACK_S back

    def add(self, stamp: float, position: Sequence[float]) -> bool:
        """Keep a position (metres) at ``stamp`` (seconds); a stamp more than
        :data:`JUMP_BACK_S` back restarts the track from it (counted in ``resets``); one
        slightly out of order or non-finite is rejected and counted (False)."""
        p = np.asarray(position, np.float64).reshape(-1)[:3]
        with self._lock:
            self.received += 1
            if p.shape != (3,) or not np.isfinite(p).all() or not np.isfinite(stamp):
                self.rejected += 1
                return False
            if self._stamps and stamp < self._stamps[-1] - JUMP_BACK_S:
                self._stamps.clear()
                self._positions.clear()
                self.resets += 1
            elif self._stamps and stamp <= self._stamps[-1]:
                self.rejected += 1
                return False
            self._stamps.append(float(stamp))
            self._positions.append(p)
        return True

    @property
    def last_stamp(self) -> float | None:
        """The stamp of the last position kept (s; None before any)."""
        with self._lock:
            return self._stamps[-1] if self._stamps else None

    def __len__(self) -> int:
        with self._lock:
            return len(self._stamps)

    def positions_at(self, stamps: Sequence[float]) -> np.ndarray | None:
        """Positions at ``stamps`` (linear interpolation), None when one lies outside the
        track's span."""
        with self._lock:
            ts, ps = list(self._stamps), list(self._positions)
        if len(ts) < 2:
            return None
        out = []
        for t in stamps:
            i = bisect.bisect_left(ts, t)
            if i < len(ts) and ts[i] == t:
                out.append(ps[i])
                continue
            if i == 0 or i == len(ts):
                return None
            a = (t - ts[i - 1]) / (ts[i] - ts[i - 1])
            out.append((1 - a) * ps[i - 1] + a * ps[i])
        return np.stack(out)


def path_length(points: np.ndarray) -> float:
    """Σ |P_{j+1} − P_j| of an N x 3 path."""
    p = np.asarray(points, np.float64)
    if p.shape[0] < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())
