"""Keyframes at the rate the windows can afford (sfm_ttr_ros.core.stream.keyframes): the auto
interval from the windows' pace, its floor and widest cap, stale frames skipped behind, the
newest-frames policy, and a slow camera left alone."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from test_stream import ScriptedTTR, check_accounting

from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.stream.keyframes import HEADROOM, KeyframeSelector
from sfm_ttr_ros.core.stream.windows import StreamProcessor, StreamSettings

RNG = np.random.default_rng(0)
IMAGE = RNG.integers(0, 255, (24, 32, 3), np.uint8)


def frame(stamp: float) -> Frame:
    return Frame(index=0, image=IMAGE, stamp=stamp)


def verdict(sel: KeyframeSelector, f: Frame, policy="auto", newest=None, **kw) -> str:
    """What the stream asks of the rule per frame: "stale", "keyframe" or "other"."""
    args = dict(floor_s=0.0, widest_s=1.0, min_motion=0.0, window_size=15, stride=15)
    args.update(kw)
    if sel.is_stale(f, policy, args["floor_s"], args["widest_s"], args["window_size"],
                    args["stride"], newest):
        return "stale"
    return "keyframe" if sel.is_keyframe(f, args["min_motion"]) else "other"


def judge(sel: KeyframeSelector, stamps, policy="auto", newest=None, **kw):
    return [verdict(sel, frame(s), policy, newest, **kw) == "keyframe" for s in stamps]


def test_auto_keyframes_every_frame_until_a_window_has_run_then_at_its_pace():
    sel = KeyframeSelector()
    assert all(judge(sel, [0.1 * i for i in range(15)]))  # the first window: consecutive
    assert sel.reason == "every_frame"
    sel.window_done(6.0)  # 15 new keyframes took 6 s: keyframes 1.2 x 6 / 15 = 0.48 s apart
    kept = judge(sel, [1.5 + 0.1 * i for i in range(30)])
    assert sel.interval_s == pytest.approx(HEADROOM * 6.0 / 15) and sel.reason == "window_time"
    assert sum(kept) == 6  # 3 s of 10 Hz frames, one every 0.5 s


def test_the_widest_interval_caps_auto_and_a_floor_is_kept():
    sel = KeyframeSelector()
    sel.window_done(60.0)  # the windows would need keyframes 4.8 s apart
    judge(sel, [0.0], widest_s=1.0)
    assert sel.interval_s == 1.0 and sel.reason == "widest" and sel.needed_s > 4
    judge(sel, [0.1], widest_s=1.0, floor_s=2.0)  # the user's floor wins over the widest
    assert sel.interval_s == 2.0
    sel = KeyframeSelector()
    judge(sel, [0.0], floor_s=0.3)
    assert sel.interval_s == 0.3 and sel.reason == "min_interval"


def test_a_camera_slower_than_the_windows_keeps_every_frame():
    """At 1 Hz with windows taking 6 s per 15 frames (0.48 s per keyframe) nothing changes."""
    sel = KeyframeSelector()
    sel.window_done(6.0)
    assert all(judge(sel, [float(i) for i in range(20)]))


def test_a_frame_behind_a_window_of_newer_frames_is_stale():
    sel = KeyframeSelector()
    judge(sel, [0.0, 0.1, 0.2])  # the stream's cadence: 10 Hz
    # newest policy: frames 1.5 s (15 frames) older than the newest queued one are stale
    assert verdict(sel, frame(0.3), "newest", newest=2.0) == "stale" and sel.stale == 1
    assert verdict(sel, frame(0.6), "newest", newest=2.0) == "keyframe"
    # auto after a slow window: its windows span 15 x 0.48 s = 7.2 s, older frames are stale
    sel.window_done(6.0)
    assert verdict(sel, frame(0.7), "auto", newest=8.0) == "stale"
    assert verdict(sel, frame(1.0), "auto", newest=8.0) != "stale"
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
    s = StreamProcessor(ttr, StreamSettings(window_size=4, window_stride=4,
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
