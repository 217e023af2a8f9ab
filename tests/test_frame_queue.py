"""FrameQueue, the stream's one thread-safe part (naming, making room, the backlog bound,
pending counts, the next window's frames, idle timing), and the Ledger it locks (the counters
and the accounting invariant)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.outcomes import Dropped, Unrefined
from sfm_ttr_ros.core.pipeline import WindowResult
from sfm_ttr_ros.core.sfm.result import SfmResult
from sfm_ttr_ros.core.stream.frame_queue import IDLE_INTERVALS, RELEASED_IMAGE, FrameQueue
from sfm_ttr_ros.core.stream.ledger import Ledger
from sfm_ttr_ros.core.stream.records import FrameOutput, WindowStats, unrefined_result
from sfm_ttr_ros.core.stream.settings import StreamSettings

INTR = Intrinsics(50.0, 50.0, 3.5, 2.5, 8, 6)


def frames(n: int, served: bool = False) -> list[Frame]:
    fs = [Frame(i, np.full((6, 8, 3), i, np.uint8), stamp=0.1 * i, name="given") for i in range(n)]
    for f in fs:
        f.served_live = served
    return fs


def fill(q: FrameQueue, fs: list[Frame], settings: StreamSettings) -> list[Frame]:
    return [d for f in fs if (d := q.put(f, INTR, settings)) is not None]


def test_frames_are_named_in_arrival_order_and_taken_oldest_first():
    q = FrameQueue()
    fill(q, frames(3), StreamSettings())
    assert [f.name for f, _ in q] == ["0000000000", "0000000001", "0000000002"]
    frame, intr = q.take(0.0)
    assert frame.index == 0 and intr == INTR
    assert (q.queued(), q.pending()) == (2, 3)  # taken, not yet accounted: still pending
    assert q.newest_stamp() == pytest.approx(0.2) and q.behind(0.0) == pytest.approx(0.2)


def test_a_full_queue_drops_its_oldest_frame_under_all():
    q = FrameQueue()
    s = StreamSettings(max_pending=3, keyframe_policy="all", overload_pending=0)
    dropped = fill(q, frames(5, served=True), s)
    assert [f.index for f in dropped] == [0, 1]
    assert [f.index for f, _ in q] == [2, 3, 4]
    assert q.ledger.dropped == {Dropped.OVERFLOW: 2} and q.ledger.balanced(q.pending())


def test_a_full_queue_under_newest_releases_served_images_and_drops_none():
    q = FrameQueue()
    s = StreamSettings(max_pending=3, keyframe_policy="newest", overload_pending=0)
    fs = frames(6, served=True)
    fs[1].served_live = False  # the live output skipped it: it keeps its image
    assert fill(q, fs, s) == []
    held = [f.index for f, _ in q if f.image is not RELEASED_IMAGE]
    assert held == [1, 4, 5] and q.queued() == 6 and q.ledger.released == 3
    # frames the live output did not serve: the served ones give their images up first, then,
    # none left, the oldest queued frame is dropped after all
    assert [f.index for f in fill(q, frames(3), s)] == [0]
    assert q.ledger.dropped == {Dropped.OVERFLOW: 1} and q.ledger.released == 5


def test_the_backlog_bound_keeps_the_newest_images():
    q = FrameQueue()
    s = StreamSettings(window_size=2, window_stride=1, overload_pending=2, keyframe_policy="all")
    fill(q, frames(7, served=True), s)
    assert [f.index for f, _ in q if f.image is not RELEASED_IMAGE] == [3, 4, 5, 6]
    assert q.ledger.released == 3 and q.queued() == 7


def test_settled_and_dropped_frames_leave_the_pending_count_and_the_ledger_balances():
    q = FrameQueue()
    fill(q, frames(4), StreamSettings())
    q.reject(Dropped.BAD_IMAGE)
    a, b, c = (q.take(0.0)[0] for _ in range(3))
    q.settle([FrameOutput(a, np.ones((6, 8), np.float32), True),
              FrameOutput(b, None, False, Unrefined.NOT_KEYFRAME)])
    q.drop_taken([c], Dropped.PREDICTION_ERROR)
    c = q.counters()
    assert (c["received"], c["refined"], c["unrefined"], c["dropped"], c["pending"]) == \
        (5, 1, 1, 2, 1)
    assert c["live_only"] == 1 and c["dropped_by_reason"] == {"bad_image": 1,
                                                              "prediction_error": 1}
    assert q.ledger.balanced(q.pending()) and not q.ledger.balanced(0)


def test_cancel_wakes_a_waiting_take():
    q = FrameQueue()
    got = []
    t = threading.Thread(target=lambda: got.append(q.take(10.0)))
    t.start()
    time.sleep(0.05)
    q.cancel()
    t.join(2)
    assert not t.is_alive() and got == [None] and q.cancelled
    fill(q, frames(1), StreamSettings())
    assert q.take(0.0) is None  # cancelled for good


def test_the_next_window_is_its_overlap_plus_the_oldest_queued_frames():
    q = FrameQueue()
    s = StreamSettings()
    running = frames(4)
    for i, f in enumerate(running):
        f.name = f"r{i}"
    assert q.next_window(2, 2) is None  # no window running
    q.begin_window(running, INTR)
    assert q.running_names() == ["r0", "r1", "r2", "r3"]
    later = frames(6)[4:]
    fill(q, later[:1], s)
    assert q.next_window(2, 2) is None  # one of the two new frames queued so far
    fill(q, later[1:], s)
    window, intr = q.next_window(2, 2)
    assert [f.name for f in window] == ["r2", "r3", "0000000000", "0000000001"] and intr == INTR
    q.put(Frame(9, np.zeros((6, 8, 3), np.uint8), stamp=0.0), INTR, s)
    q.take(0.0)
    assert q.next_window(2, 2) is None  # stamps of the next window no longer rising
    q.end_window()
    assert q.running_names() == [] and q.next_window(2, 2) is None


def test_the_idle_wait_follows_a_slow_camera():
    q = FrameQueue()
    assert q.idle_after(2.0) == 2.0 and q.idle_after(0.0) == 0.0
    fill(q, frames(1), StreamSettings())
    assert q.idle_after(2.0) == IDLE_INTERVALS * 2.0  # one frame: its interval not known yet
    q._arrivals.extend([q._arrivals[-1] + 1.0, q._arrivals[-1] + 2.0])  # a 1 Hz camera
    assert q.idle_after(2.0) == pytest.approx(IDLE_INTERVALS * 1.0)
    assert q.idle_after(5.0) == 5.0
    q.restart_idle()
    assert 0.0 <= q.idle_for() < 1.0


def stats(res: WindowResult) -> WindowStats:
    return WindowStats.of(0, 2, res, steps=1, started_at=0.0)


def test_the_ledger_counts_each_window_under_one_outcome():
    ledger = Ledger()
    ok = WindowResult(["a", "b"], {}, {}, True, sfm=SfmResult(True, "", 2, attempts=[{}, {}]))
    for res in (ok, unrefined_result(["a"], Unrefined.OVERLOAD, "busy"),
                unrefined_result(["a"], Unrefined.DISABLED, "off"),
                unrefined_result(["a"], Unrefined.CHECK_PARALLAX, "flat"),
                unrefined_result(["a"], Unrefined.WINDOW_ERROR, "boom")):
        ledger.window(stats(res))
    c = ledger.counters(pending=0, queued=0)
    assert (c["windows_ok"], c["windows_skipped"], c["windows_disabled"], c["windows_failed"],
            c["windows_rejected"], c["windows_remapped"]) == (1, 1, 1, 2, 1, 1)
    assert list(c)[:4] == ["received", "refined", "unrefined", "unrefined_by_reason"]
