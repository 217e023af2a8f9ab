"""The stream's frame and window accounting: every frame received is refined, unrefined with a
key of :class:`~sfm_ttr_ros.core.outcomes.Unrefined`, dropped with a key of
:class:`~sfm_ttr_ros.core.outcomes.Dropped`, or still pending, so at any time

    received == refined + sum(unrefined) + sum(dropped) + pending

(docs/node.md, "How frames flow"). Plain counters: the :class:`~.frame_queue.FrameQueue` that
owns the ledger is the one that locks them."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field

from sfm_ttr_ros.core.outcomes import CHECKS, Dropped, Unrefined
from sfm_ttr_ros.core.stream.records import FrameOutput, WindowStats


@dataclass
class Ledger:
    """The 13 counters of one stream (read by :meth:`counters`)."""

    received: int = 0
    refined: int = 0
    unrefined: Counter[str] = field(default_factory=Counter)  # by Unrefined key
    dropped: Counter[str] = field(default_factory=Counter)  # by Dropped key
    live_only: int = 0  # unrefined frames not predicted again: served live only
    released: int = 0  # queued frames whose image the backlog bound released
    non_monotonic: int = 0  # frames whose stamp went back
    windows_ok: int = 0
    windows_failed: int = 0
    windows_skipped: int = 0  # refinement skipped for overload
    windows_disabled: int = 0
    windows_rejected: int = 0  # refused by a window check, among the failed
    windows_remapped: int = 0  # whose mapper ran more than once (sfm.mapping_attempts)

    def drop(self, key: Dropped, n: int = 1) -> None:
        self.dropped[key] += n

    def account(self, outs: Iterable[FrameOutput]) -> None:
        """Frames that came out: refined, or unrefined under their key (and live-only)."""
        for o in outs:
            if o.refined:
                self.refined += 1
            else:
                self.unrefined[o.reason_key] += 1
                self.live_only += o.live_only

    def window(self, stats: WindowStats) -> None:
        """A window: skipped for overload, else ok, disabled or failed (rejected by a check
        among the failed), and remapped whatever its outcome."""
        if stats.reason_key == Unrefined.OVERLOAD:
            self.windows_skipped += 1
            return
        if stats.refined:
            self.windows_ok += 1
        elif stats.reason_key == Unrefined.DISABLED:
            self.windows_disabled += 1
        else:
            self.windows_failed += 1
            self.windows_rejected += stats.reason_key in CHECKS
        self.windows_remapped += stats.mapping_attempts > 1

    def balanced(self, pending: int) -> bool:
        """The accounting invariant (module docstring) with ``pending`` frames in flight."""
        return self.received == (self.refined + sum(self.unrefined.values())
                                 + sum(self.dropped.values()) + pending)

    def counters(self, pending: int, queued: int) -> dict[str, object]:
        """The counters as the stream reports them (``WindowRunner.counters``), with the
        ``pending`` frames (queued or in the worker's hands) and the ``queued`` ones."""
        return {
            "received": self.received,
            "refined": self.refined,
            "unrefined": sum(self.unrefined.values()),
            "unrefined_by_reason": dict(self.unrefined),
            "live_only": self.live_only,
            "backlog_released": self.released,
            "dropped": sum(self.dropped.values()),
            "dropped_by_reason": dict(self.dropped),
            "pending": pending,
            "queued": queued,
            "windows_ok": self.windows_ok,
            "windows_failed": self.windows_failed,
            "windows_skipped": self.windows_skipped,
            "windows_disabled": self.windows_disabled,
            "windows_rejected": self.windows_rejected,
            "windows_remapped": self.windows_remapped,
            "non_monotonic_stamps": self.non_monotonic,
        }
