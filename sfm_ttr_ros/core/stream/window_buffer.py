"""The keyframes collected for the windows (docs/node.md, "How frames flow", rule 4): which of
them are published, when a window is due and over which of them, the overlap kept for the next
window. The window worker's own state (no lock)."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from sfm_ttr_ros.core.frames import Frame
from sfm_ttr_ros.core.stream.settings import StreamSettings


@dataclass
class Entry:
    """A keyframe in the buffer; ``published`` once a window (or a flush) put it out."""

    frame: Frame
    published: bool = False


class WindowBuffer:
    """The keyframes of the window being filled, the overlap with the last window first."""

    def __init__(self) -> None:
        self.entries: list[Entry] = []

    def __len__(self) -> int:
        return len(self.entries)

    @property
    def unpublished(self) -> int:
        return sum(not e.published for e in self.entries)

    def add(self, frame: Frame) -> None:
        self.entries.append(Entry(frame))

    def due(self, settings: StreamSettings, first: bool) -> list[Entry]:
        """The window due now ([] when none): once ``window_size`` keyframes (for the stream's
        ``first`` window ``first_window_size`` when set) of which at least ``window_stride``
        are new are buffered, the last ``window_size`` of them (more when more are new)."""
        s = settings
        new = self.unpublished
        size = s.first_window_size if s.first_window_size and first else s.window_size
        if len(self.entries) < size or new < min(s.window_stride, size):
            return []
        return self.entries[-max(size, new):]

    def slide(self, settings: StreamSettings) -> None:
        """After a window: the last ``window_size - window_stride`` keyframes stay as the next
        window's overlap (published already: not published again)."""
        keep = settings.window_size - settings.window_stride
        self.entries = self.entries[len(self.entries) - keep:] if keep > 0 else []

    def take_unpublished(self) -> list[Frame]:
        """The keyframes not published yet; the buffer emptied (a new window starts)."""
        new = [e.frame for e in self.entries if not e.published]
        self.entries = []
        return new

    @staticmethod
    def mark_published(entries: Iterable[Entry]) -> None:
        for e in entries:
            e.published = True
