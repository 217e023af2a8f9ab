"""WindowBuffer: when a window is due over which keyframes, the overlap it keeps, and the
keyframes a flush takes out."""

from __future__ import annotations

import numpy as np

from sfm_ttr_ros.core.frames import Frame
from sfm_ttr_ros.core.stream.settings import StreamSettings
from sfm_ttr_ros.core.stream.window_buffer import WindowBuffer


def add(buffer: WindowBuffer, indices) -> None:
    for i in indices:
        buffer.add(Frame(i, np.zeros((2, 2, 3), np.uint8)))


def indices(entries) -> list[int]:
    return [e.frame.index for e in entries]


def test_windows_are_due_every_stride_with_the_overlap_kept_published():
    s = StreamSettings(window_size=4, window_stride=2)
    b = WindowBuffer()
    add(b, range(3))
    assert b.due(s, first=True) == []
    add(b, [3])
    window = b.due(s, first=True)
    assert indices(window) == [0, 1, 2, 3]
    WindowBuffer.mark_published(window)
    b.slide(s)
    assert indices(b.entries) == [2, 3] and b.unpublished == 0
    add(b, [4])
    assert b.due(s, first=False) == []  # one new keyframe of the two a window needs
    add(b, [5])
    assert indices(b.due(s, first=False)) == [2, 3, 4, 5]


def test_a_short_first_window_then_full_ones():
    s = StreamSettings(window_size=6, window_stride=6, first_window_size=3)
    b = WindowBuffer()
    add(b, range(3))
    assert indices(b.due(s, first=True)) == [0, 1, 2]
    assert b.due(s, first=False) == []


def test_more_new_keyframes_than_a_window_all_go_in_it():
    s = StreamSettings(window_size=2, window_stride=1)
    b = WindowBuffer()
    add(b, range(3))  # e.g. the first window's size was raised while frames waited
    assert indices(b.due(s, first=False)) == [0, 1, 2]


def test_a_flush_takes_the_unpublished_keyframes_and_empties_the_buffer():
    b = WindowBuffer()
    add(b, range(3))
    WindowBuffer.mark_published(b.entries[:1])
    assert [f.index for f in b.take_unpublished()] == [1, 2]
    assert len(b) == 0 and b.take_unpublished() == []
