"""One log line per key per period: the throttle shared by the stream, the live server and the
node (a flood of bad frames gives one warning every few seconds, with the running count)."""

from __future__ import annotations

import time

WARN_PERIOD_S = 5.0


class Throttle:
    """``due(key)`` is True at most once per ``period`` seconds for each key."""

    def __init__(self, period: float = WARN_PERIOD_S) -> None:
        self.period = float(period)
        self._last: dict[str, float] = {}

    def due(self, key: str, period: float | None = None) -> bool:
        now = time.monotonic()
        if now - self._last.get(key, -1e9) < (self.period if period is None else period):
            return False
        self._last[key] = now
        return True
