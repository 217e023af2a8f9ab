"""Progress of a split: a tqdm bar on a terminal (sequences done of all, frames, failed, ETA),
one log line per finished sequence otherwise (logs, CI); the same counts either way."""

from __future__ import annotations

import sys
import time
from typing import Any


def _eta(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


class SplitProgress:
    """``total`` sequences of which ``reused`` are already done (read from an earlier run)."""

    def __init__(self, total: int, reused: int = 0, stream=None, enabled: bool = True,
                 label: str = "split") -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.total, self.done, self.label = total, reused, label
        self.computed = self.failed = self.frames = 0
        self.t0 = time.perf_counter()
        self.enabled = enabled
        self.tty = enabled and bool(getattr(self.stream, "isatty", lambda: False)())
        self.bar = None
        if self.tty:
            try:
                from tqdm import tqdm
            except ImportError:  # the [cluster] extra brings it; without it, log lines
                self.tty = False
        if self.tty:
            self.bar = tqdm(total=total, initial=reused, unit="seq", desc=label,
                            file=self.stream, dynamic_ncols=True)
        elif enabled and reused:
            self._line(f"{reused} of {total} sequences already done (resumed)")

    def _line(self, text: str) -> None:
        print(f"sfm-ttr {self.label}: {text}", file=self.stream, flush=True)

    def update(self, record: dict[str, Any]) -> None:
        """One sequence ended (its stored record)."""
        self.done += 1
        self.computed += 1
        frames = int((record.get("row") or {}).get("frames_total") or 0)
        self.frames += frames
        ok = record["status"] == "done"
        self.failed += int(not ok)
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.set_postfix(frames=self.frames, failed=self.failed, refresh=False)
            self.bar.update(1)
            if not ok:
                self.bar.write(f"{record['id']}: failed: {record['reason']}", file=self.stream)
            return
        elapsed = time.perf_counter() - self.t0
        left = self.total - self.done
        eta = f"; ETA {_eta(elapsed / self.computed * left)}" if left else ""
        retry = record.get("attempts", 1) - 1
        what = (f"done in {record['seconds']:.1f} s, {frames} frames" if ok
                else f"FAILED ({record['reason']})")
        self._line(f"[{self.done}/{self.total}] {record['id']}: {what}"
                   f"{f', {retry} retr' + ('y' if retry == 1 else 'ies') if retry else ''}; "
                   f"{self.frames} frames so far, {self.failed} failed{eta}")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
