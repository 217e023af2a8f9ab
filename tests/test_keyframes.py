"""Which frames the windows take (sfm_ttr_ros.core.stream.keyframes): stale frames skipped
behind the newest, the floor and the motion floor, a slow camera left alone, the windows' pace
reported."""

from __future__ import annotations

import threading
import time

import numpy as np
from test_stream import ScriptedTTR, check_accounting

from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.stream.keyframes import KeyframeSelector, keyframe_interval
from sfm_ttr_ros.core.stream.settings import StreamSettings
from sfm_ttr_ros.core.stream.window_runner import WindowRunner

RNG = np.random.default_rng(0)
IMAGE = RNG.integers(0, 255, (24, 32, 3), np.uint8)


def frame(stamp: float) -> Frame:
    return Frame(index=0, image=IMAGE, stamp=stamp)


def verdict(sel: KeyframeSelector, f: Frame, policy="newest", newest=None, floor_s=0.0,
            min_motion=0.0, window_size=15) -> str:
    """What the stream asks of the rule per frame: "stale", "keyframe" or "other"."""
    if sel.is_stale(f, policy, floor_s, window_size, newest):
        return "stale"
    return "keyframe" if sel.is_keyframe(f, floor_s, min_motion) else "other"


def judge(sel: KeyframeSelector, stamps, policy="newest", newest=None, **kw):
    return [verdict(sel, frame(s), policy, newest, **kw) == "keyframe" for s in stamps]


def test_every_frame_is_a_keyframe_unless_a_floor_says_otherwise():
    sel = KeyframeSelector()
    assert all(judge(sel, [0.1 * i for i in range(15)]))
    assert keyframe_interval(0.0) == (0.0, "every_frame")
    kept = judge(sel, [1.5 + 0.1 * i for i in range(30)], floor_s=0.45)
    assert keyframe_interval(0.45) == (0.45, "min_interval")
    assert sum(kept) == 6  # 3 s of 10 Hz frames, one every 0.5 s


def test_the_windows_pace_is_reported():
    sel = KeyframeSelector()
    assert sel.needed_s(15) == 0.0  # no window yet
    for t in (6.0, 9.0, 30.0):
        sel.window_done(t)
    sel.window_done(float("nan"))  # not a time: ignored
    assert sel.needed_s(15) == 9.0 / 15  # the median window over the stride


def test_a_camera_slower_than_the_windows_keeps_every_frame():
    """At 1 Hz with windows of 15 frames taking 6 s the worker is never a window behind."""
    sel = KeyframeSelector()
    sel.window_done(6.0)
    stamps = [float(i) for i in range(40)]
    # the newest frame queued when each is taken: at most 6 frames behind
    assert all(verdict(sel, frame(s), newest=s + 6.0) == "keyframe" for s in stamps)
    assert sel.stale == 0


def test_a_frame_behind_a_window_of_newer_frames_is_stale():
    sel = KeyframeSelector()
    judge(sel, [0.0, 0.1, 0.2])  # the stream's cadence: 10 Hz
    # newest policy: frames 1.5 s (15 frames) older than the newest queued one are stale
    assert verdict(sel, frame(0.3), "newest", newest=2.0) == "stale" and sel.stale == 1
    assert verdict(sel, frame(0.6), "newest", newest=2.0) == "keyframe"
    # a floor widens the span: 15 x 0.5 s = 7.5 s
    assert verdict(sel, frame(0.7), newest=8.3, floor_s=0.5) == "stale"
    assert verdict(sel, frame(1.0), newest=8.3, floor_s=0.5) != "stale"
    # all: never stale (overload is its rule)
    assert verdict(sel, frame(0.9), "all", newest=99.0) != "stale"


def test_the_motion_floor_needs_that_much_change_from_the_last_keyframe():
    sel = KeyframeSelector()
    still = Frame(index=0, image=IMAGE, stamp=0.0)
    assert verdict(sel, still, min_motion=5.0) == "keyframe"
    same = Frame(index=1, image=IMAGE.copy(), stamp=0.1)
    assert verdict(sel, same, min_motion=5.0) == "other"
    moved = Frame(index=2, image=255 - IMAGE, stamp=0.2)
    assert verdict(sel, moved, min_motion=5.0) == "keyframe"


def test_a_stream_behind_drops_its_partial_window_and_counts_every_frame():
    """A worker whose windows take long, frames arriving meanwhile: stale frames and the
    keyframes collected before them pass unrefined as ``stale``, the windows are built from
    the newest frames (none skipped for overload), and every frame is accounted for."""
    ttr = ScriptedTTR(delay=0.4)
    s = WindowRunner(ttr, StreamSettings(window_size=4, window_stride=4,
                                            keyframe_policy="newest", overload_pending=2,
                                            max_pending=500))
    frames = [Frame(index=i, image=IMAGE, stamp=0.1 * i) for i in range(60)]
    outs, stop = [], threading.Event()

    def work():
        while not stop.is_set():
            outs.extend(s.step(timeout=0.02))

    worker = threading.Thread(target=work)
    worker.start()
    for f in frames:
        s.submit(f, Intrinsics(30.0, 30.0, 15.5, 11.5, 32, 24))
        time.sleep(0.02)
    time.sleep(1.0)
    outs += s.flush()
    stop.set()
    worker.join()
    c = check_accounting(s, outs, 60)
    assert c["unrefined_by_reason"].get("stale", 0) > 10
    # the queue outgrew overload_pending, but under newest/auto no window is skipped for it
    assert "overload" not in c["unrefined_by_reason"] and c["windows_skipped"] == 0
    newest_first = [int(w[0]) for w in ttr.windows]
    assert all(b - a > 4 for a, b in zip(newest_first, newest_first[1:], strict=False))
