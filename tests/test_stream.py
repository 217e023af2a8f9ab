"""WindowRunner: windows, keyframes, back-pressure and the accounting of every frame (no ROS).

Most tests drive the stream with a scripted stand-in for SfmTTR (fast, every outcome on demand);
the last ones run the real SfmTTR with a tiny network on synthetic street frames."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from conftest import tiny_model

from sfm_ttr_ros.core.checks.measures import CheckReport
from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.metric.scale import MetricStatus
from sfm_ttr_ros.core.outcomes import Dropped, Unrefined
from sfm_ttr_ros.core.pipeline import SfmTTR, TTRConfig, WindowResult
from sfm_ttr_ros.core.sfm.result import SfmResult
from sfm_ttr_ros.core.stream.frame_queue import RELEASED_IMAGE
from sfm_ttr_ros.core.stream.records import FrameOutput
from sfm_ttr_ros.core.stream.settings import StreamSettings
from sfm_ttr_ros.core.stream.window_runner import WindowRunner

W, H = 64, 32
INTR = Intrinsics(50.0, 50.0, 31.5, 15.5, W, H)


class ScriptedTTR:
    """Stand-in for SfmTTR: ``outcomes`` says what each window does (``"ok"``, ``"sfm"`` =
    SfM failed, ``"few"`` = too few points, ``"raise"``, ``"rejected"`` = refused by the
    held-out check, ``"remapped"`` = refined after a second run of the mapper); depth 2 =
    refined, 1 = not."""

    def __init__(self, outcomes=("ok",), delay: float = 0.0):
        self.outcomes = list(outcomes)
        self.config = TTRConfig()
        self.windows: list[list[str]] = []
        self.configs: list[TTRConfig] = []
        self.delay = delay
        self.cancelled = False
        self.prefetched: list[list[str]] = []  # windows whose SfM the stream asked ahead
        self.predictor = self.sfm = self  # the stand-in is its own predictor and SfM source
        self.metres_per_unit = None  # the outputs' metric factor (None: not metric)

    def set_config(self, config):
        self.config = config

    def prefetch(self, frames, intrinsics):  # as SfmPrefetch.start: the same frames once
        if self.prefetched and self.prefetched[-1] == [f.name for f in frames]:
            return False
        self.prefetched.append([f.name for f in frames])
        return True

    def admit(self, frame, intrinsics):  # as the batch source: the window does it all
        return False

    def retain(self, names):
        pass

    def counters(self):
        return {"sfm_ahead": {"started": len(self.prefetched), "used": 0, "discarded": 0},
                "sfm_streaming": {}}

    def metric_status(self):
        return MetricStatus("fixed", "metric", self.metres_per_unit, float("nan"), 0, 0, 0)

    def cancel(self):
        self.cancelled = True

    def predict(self, images):
        return [np.ones(im.shape[:2], np.float32) for im in images]

    def process_window(self, frames, intrinsics, refine=True, should_stop=None):
        self.windows.append([f.name for f in frames])
        self.configs.append(self.config)
        if self.delay:
            time.sleep(self.delay)
        outcome = self.outcomes[min(len(self.windows) - 1, len(self.outcomes) - 1)]
        if outcome == "raise":
            raise RuntimeError("boom")
        names = [f.name for f in frames]
        before = {n: np.ones((H, W), np.float32) for n in names}
        res = WindowResult(names, dict(before), before, refined=outcome == "ok")
        if outcome in ("ok", "remapped"):
            res.refined = True
            res.depths = {n: np.full((H, W), 2.0, np.float32) for n in names}
            res.sfm = SfmResult(True, "", len(names))
            if outcome == "remapped":  # the mapper's second run kept (sfm.mapping_attempts)
                res.sfm.attempts = [{"seed": 0, "reprojection_error": 1.1, "kept": False},
                                    {"seed": 1, "reprojection_error": 0.6, "kept": True}]
        elif outcome == "sfm":
            res.reason_key, res.reason = Unrefined.SFM_FAILED, "SfM failed: too little motion"
        elif outcome == "rejected":
            key = Unrefined.CHECK_UNSUPPORTED_CHANGE
            res.reason_key, res.reason = key, "rejected by check: 0.03 of the pixels moved"
            res.check = CheckReport(unsupported_change=0.03, reason_key=key)
        else:
            res.reason_key = Unrefined.TOO_FEW_POINTS
            res.reason = "too few supervision points: 3 selected of 10 (< 50)"
        return res


def frames(n: int, start: float = 0.0, size=(W, H), seed: int = 0) -> list[Frame]:
    rng = np.random.default_rng(seed)
    return [Frame(index=i, image=rng.integers(0, 255, (size[1], size[0], 3), np.uint8),
                  stamp=start + 0.1 * i) for i in range(n)]


def check_accounting(stream: WindowRunner, outs: list[FrameOutput], sent: int) -> dict:
    c = stream.counters()
    assert c["received"] == sent
    assert c["received"] == c["refined"] + c["unrefined"] + c["dropped"] + c["pending"]
    assert c["refined"] == sum(o.refined for o in outs)
    assert c["unrefined"] == sum(not o.refined for o in outs)
    names = [o.frame.name for o in outs]
    assert len(names) == len(set(names)), "a frame was published twice"
    assert set(c["unrefined_by_reason"]) <= set(Unrefined)
    assert set(c["dropped_by_reason"]) <= set(Dropped)
    return c


def run(stream, fs, intr=INTR):
    outs = []
    for f in fs:
        outs += stream.push(f, intr)
    return outs


def test_windows_stride_overlap_and_each_frame_published_once():
    ttr = ScriptedTTR()
    stream = WindowRunner(ttr, StreamSettings(window_size=4, window_stride=2))
    outs = run(stream, frames(9))
    # windows over 0-3, 2-5, 4-7; frame 8 waits for the next window
    assert ttr.windows == [[f"{i:010d}" for i in r] for r in (range(0, 4), range(2, 6),
                                                                 range(4, 8))]
    assert [o.frame.name for o in outs] == [f"{i:010d}" for i in range(8)]
    assert [o.window for o in outs] == [0, 0, 0, 0, 1, 1, 2, 2]
    assert all(o.refined and o.reason == "" and float(o.depth.mean()) == 2.0 for o in outs)
    c = check_accounting(stream, outs, 9)
    assert c["pending"] == 1 and c["windows_ok"] == 3
    # end of stream: a final partial window over the overlap + the last frame
    outs += stream.flush()
    assert ttr.windows[-1] == [f"{i:010d}" for i in (6, 7, 8)]
    c = check_accounting(stream, outs, 9)
    assert (c["refined"], c["pending"]) == (9, 0)
    assert len(stream.windows) == 4 and stream.last_window.new_frames == 1


def test_names_come_from_a_running_counter():
    stream = WindowRunner(ScriptedTTR(), StreamSettings(window_size=2, window_stride=2))
    fs = frames(4)
    for f in fs:
        f.name = "same"
    outs = run(stream, fs)
    assert [o.frame.name for o in outs] == [f"{i:010d}" for i in range(4)]
    assert [o.frame.index for o in outs] == [0, 1, 2, 3]  # the caller's index is kept


def scripted_run(outcomes, n: int):
    """``n`` frames through windows of 2 whose outcomes ``ScriptedTTR`` scripts: (stream,
    outputs, the windows reported to ``on_window``)."""
    seen_windows = []
    stream = WindowRunner(ScriptedTTR(outcomes=outcomes),
                             StreamSettings(window_size=2, window_stride=2),
                             on_window=seen_windows.append)
    return stream, run(stream, frames(n)), seen_windows


def test_failed_windows_publish_unrefined_with_reason():
    stream, outs, seen_windows = scripted_run(("sfm", "few", "raise", "ok"), 8)
    keys = [o.reason_key or "" for o in outs]
    assert keys == ["sfm_failed"] * 2 + ["too_few_points"] * 2 + ["window_error"] * 2 + [""] * 2
    assert outs[0].reason.startswith("SfM failed: too little motion")
    assert "boom" in outs[4].reason
    c = check_accounting(stream, outs, 8)
    assert c["unrefined_by_reason"] == {"sfm_failed": 2, "too_few_points": 2, "window_error": 2}
    assert (c["windows_ok"], c["windows_failed"]) == (1, 3)
    assert [w.refined for w in seen_windows] == [False, False, False, True]


def test_a_window_refused_by_its_check_is_counted_with_what_it_measured():
    stream, outs, seen_windows = scripted_run(("ok", "rejected", "ok"), 6)
    refused = Unrefined.CHECK_UNSUPPORTED_CHANGE
    assert [o.reason_key for o in outs] == [None, None, refused, refused, None, None]
    assert all(float(o.depth.mean()) == 1.0 for o in outs[2:4])  # the weights before it
    c = check_accounting(stream, outs, 6)
    assert c["unrefined_by_reason"] == {"check_unsupported_change": 2}
    assert (c["windows_ok"], c["windows_failed"], c["windows_rejected"]) == (2, 1, 1)
    assert seen_windows[1].unsupported_change == 0.03
    assert np.isnan(seen_windows[0].unsupported_change)


def test_windows_mapped_more_than_once_are_counted():
    stream, outs, seen_windows = scripted_run(("ok", "remapped", "sfm"), 6)
    c = check_accounting(stream, outs, 6)
    assert (c["windows_ok"], c["windows_failed"], c["windows_remapped"]) == (2, 1, 1)
    assert [w.mapping_attempts for w in seen_windows] == [0, 2, 0]


def test_overflow_drops_the_oldest_pending_frame():
    drops = []
    ttr = ScriptedTTR()
    stream = WindowRunner(ttr, StreamSettings(window_size=2, window_stride=1, max_pending=3,
                                                 overload_pending=0),
                             on_drop=lambda f, k, m: drops.append((f.name, k)))
    fs = frames(6)
    for f in fs:  # nobody processes: the queue overflows
        stream.submit(f, INTR)
    assert drops == [("0000000000", "overflow"), ("0000000001", "overflow"),
                     ("0000000002", "overflow")]
    outs = stream.process_available()
    assert [o.frame.name for o in outs] == ["0000000003", "0000000004", "0000000005"]
    c = check_accounting(stream, outs, 6)
    assert c["dropped_by_reason"] == {"overflow": 3} and c["pending"] == 0


@pytest.mark.parametrize("policy", ["newest", "all"])
def test_a_full_queue_under_newest_loses_no_frame_the_live_output_served(policy):
    """newest: served frames past max_pending give their image up and are counted stale when
    the worker reaches them; all: the oldest are dropped for overflow as before."""
    drops = []
    stream = WindowRunner(ScriptedTTR(), StreamSettings(
        window_size=2, window_stride=1, max_pending=3, overload_pending=0,
        keyframe_policy=policy), on_drop=lambda f, k, m: drops.append((f.name, k)))
    fs = frames(12)
    for f in fs:  # the live output serves each frame as it arrives; no worker runs meanwhile
        f.served_live = True
        stream.submit(f, INTR)
    held = sum(f.image is not RELEASED_IMAGE for f, _ in stream._queue)
    assert held == 3
    outs = stream.process_available()
    c = check_accounting(stream, outs, 12)
    if policy == "all":
        assert c["dropped_by_reason"] == {"overflow": 9} and len(drops) == 9
        assert [o.frame.name for o in outs] == [f"{i:010d}" for i in (9, 10, 11)]
        return
    assert drops == [] and c["dropped"] == 0 and c["backlog_released"] == 9
    # frames 0..9: the frames queued after each span a window (2 x 0.1 s); 10 and 11 refined
    assert c["unrefined_by_reason"] == {"stale": 10} and c["refined"] == 2
    assert all(o.live_only for o in outs if not o.refined)
    assert sorted(o.frame.name for o in outs) == [f"{i:010d}" for i in range(12)]


def test_overload_skips_refinement_until_the_queue_drains():
    ttr = ScriptedTTR()
    stream = WindowRunner(ttr, StreamSettings(window_size=2, window_stride=2,
                                                 overload_pending=2, max_pending=50,
                                                 keyframe_policy="all"))
    for f in frames(8):
        stream.submit(f, INTR)
    outs = stream.process_available()
    # window at frame 1: 6 frames queued > 2 → skipped; at frame 3: 4 > 2 → skipped;
    # at frame 5: 2 queued (not > 2) → refined; at frame 7 → refined
    assert [o.reason_key or "" for o in outs] == ["overload"] * 4 + [""] * 4
    assert len(ttr.windows) == 2
    c = check_accounting(stream, outs, 8)
    assert c["windows_skipped"] == 2 and c["unrefined_by_reason"] == {"overload": 4}


def overloaded_stream(ttr, republish: bool) -> WindowRunner:
    """Windows of 2, refinement skipped while more than 2 frames wait (backlog bound: 4)."""
    return WindowRunner(ttr, StreamSettings(window_size=2, window_stride=2,
                                               overload_pending=2, max_pending=50,
                                               republish_unrefined=republish,
                                               keyframe_policy="all"))


def test_frames_served_live_are_not_predicted_again_unless_republished():
    class CountingTTR(ScriptedTTR):
        predicted = 0

        def predict(self, images):
            self.predicted += len(images)
            return super().predict(images)

    for republish in (False, True):
        ttr = CountingTTR()
        stream = overloaded_stream(ttr, republish)
        fs = frames(8)
        for f in fs:
            stream.submit(f, INTR)
        for f in fs[:3]:  # the live output served these since (core/stream/live.py sets the flag);
            f.served_live = True  # after the submissions, so the backlog bound took nothing
        outs = stream.process_available()
        assert [o.reason_key or "" for o in outs] == ["overload"] * 4 + [""] * 4
        c = check_accounting(stream, outs, 8)  # counted as before, whatever is published
        assert c["unrefined_by_reason"] == {"overload": 4}
        live_only = [o.frame.index for o in outs if o.live_only]
        if republish:
            assert live_only == [] and ttr.predicted == 4 and c["live_only"] == 0
        else:  # frame 3 was not served live (e.g. skipped there): still predicted
            assert live_only == [0, 1, 2] and ttr.predicted == 1 and c["live_only"] == 3
            assert all(o.depth is None for o in outs[:3]) and outs[3].depth is not None
        assert all(o.depth is not None for o in outs[4:])  # refined frames always come out


def test_the_backlog_keeps_the_images_of_overload_pending_plus_window_size_frames():
    for republish in (False, True):
        ttr = ScriptedTTR()
        stream = overloaded_stream(ttr, republish)
        fs = frames(10)
        for f in fs:
            f.served_live = f.index != 1  # frame 1: the live output skipped it
            stream.submit(f, INTR)
        queued = [f for f, _ in stream._queue]
        held = [f.index for f in queued if f.image is not RELEASED_IMAGE]
        outs = stream.process_available()
        c = check_accounting(stream, outs, 10)
        if republish:  # every frame predicted again: nothing released
            assert held == list(range(10)) and c["backlog_released"] == 0
            continue
        # 2 + 2 = 4 images kept, frame 1 among them (it has no depth out yet): 6 released
        assert held == [1, 7, 8, 9] and c["backlog_released"] == 6
        # frame 2 (released) ends the window frame 1 had started: both overload; 7-8 refined
        assert [o.frame.index for o in outs] == list(range(9)) and c["pending"] == 1
        assert [o.reason_key or "" for o in outs] == ["overload"] * 7 + ["", ""]
        assert [o.frame.index for o in outs if o.live_only] == [0, 2, 3, 4, 5, 6]
        assert outs[1].depth is not None  # frame 1 was never served: predicted
        assert all(o.frame.stamp == fs[o.frame.index].stamp for o in outs)
        assert ttr.windows == [["0000000007", "0000000008"]]  # no window spans released frames
        assert c["live_only"] == 6


def test_keyframe_interval_and_motion():
    ttr = ScriptedTTR()
    stream = WindowRunner(ttr, StreamSettings(window_size=2, window_stride=1,
                                                 min_keyframe_interval_s=0.25))
    outs = run(stream, frames(7))  # stamps 0.0 .. 0.6: keyframes at 0.0, 0.3, 0.6
    kf = [o for o in outs if o.reason_key != "not_keyframe"]
    assert [o.frame.index for o in kf] == [0, 3, 6]
    assert all(o.reason == "not a keyframe" and not o.refined
               for o in outs if o.reason_key == "not_keyframe")
    check_accounting(stream, outs, 7)

    stream = WindowRunner(ScriptedTTR(), StreamSettings(window_size=2, window_stride=1,
                                                           min_keyframe_motion=5.0))
    base = frames(1)[0].image
    fs = [Frame(i, base.copy(), stamp=0.1 * i) for i in range(3)]  # static camera
    fs.append(Frame(3, (255 - base).copy(), stamp=0.3))  # a big change
    outs = run(stream, fs)
    assert [o.reason_key or "" for o in outs] == ["not_keyframe", "not_keyframe", "", ""]
    check_accounting(stream, outs, 4)


def test_resolution_change_flushes_pending_frames():
    ttr = ScriptedTTR()
    stream = WindowRunner(ttr, StreamSettings(window_size=3, window_stride=3))
    outs = run(stream, frames(2))
    assert outs == []
    big = Intrinsics(100.0, 100.0, 63.5, 31.5, 2 * W, 2 * H)
    outs += run(stream, frames(3, start=1.0, size=(2 * W, 2 * H)), big)
    assert [o.reason_key or "" for o in outs] == ["resolution_change"] * 2 + [""] * 3
    assert ttr.windows == [["0000000002", "0000000003", "0000000004"]]
    # intrinsics of another size than the image: published unrefined, kept out of windows
    outs += run(stream, frames(1, start=2.0), big)
    assert outs[-1].reason_key == "intrinsics_mismatch"
    # same size, other focal length: a new window too
    outs += run(stream, frames(1, start=3.0), INTR)
    outs += run(stream, frames(1, start=4.0), Intrinsics(60.0, 60.0, 31.5, 15.5, W, H))
    assert outs[-1].reason_key == "intrinsics_change"
    check_accounting(stream, outs, 8)


def test_the_first_received_intrinsics_replace_the_fallback_for_pending_frames():
    """Images that came before their camera's first CameraInfo (on the fallback fx, fy) stay in
    their window and take the received intrinsics; a later change still starts a new window."""
    ttr = ScriptedTTR()
    stream = WindowRunner(ttr, StreamSettings(window_size=3, window_stride=3))
    early = frames(2)
    for f in early:
        f.fallback_intrinsics = True
    fallback = Intrinsics(70.0, 70.0, 31.5, 15.5, W, H)
    outs = run(stream, early, fallback)
    outs += run(stream, frames(4, start=1.0), INTR)
    assert [o.reason_key or "" for o in outs] == [""] * 6
    assert ttr.windows[0] == ["0000000000", "0000000001", "0000000002"]
    assert stream._intr == INTR
    # once received intrinsics are in use, another camera is a change: a new window
    outs += run(stream, frames(1, start=2.0), INTR)
    outs += run(stream, frames(1, start=3.0), fallback)
    assert [o.reason_key or "" for o in outs[6:]] == ["intrinsics_change"]
    check_accounting(stream, outs, 8)


def test_duplicate_and_non_monotonic_stamps():
    ttr = ScriptedTTR()
    stream = WindowRunner(ttr, StreamSettings(window_size=4, window_stride=4))
    fs = frames(5)
    fs[2].stamp = fs[1].stamp  # duplicate: rejected
    fs[4].stamp = -1.0  # back in time: window reset
    outs = run(stream, fs)
    c = check_accounting(stream, outs, 5)
    assert c["dropped_by_reason"] == {"duplicate_stamp": 1}
    assert c["non_monotonic_stamps"] == 1
    assert [o.frame.index for o in outs] == [0, 1, 3]
    assert {o.reason_key or "" for o in outs} == {"stamp_jump_back"}
    assert ttr.windows == []  # no window ever had 4 keyframes in order
    assert c["pending"] == 1  # frame 4 starts the new window
    outs += stream.flush()
    assert outs[-1].reason_key == "end_of_stream"
    assert check_accounting(stream, outs, 5)["pending"] == 0


def test_reject_counts_frames_that_never_reach_the_stream():
    stream = WindowRunner(ScriptedTTR(), StreamSettings())
    stream.reject("bad_image", "truncated")
    c = check_accounting(stream, [], 1)
    assert c["dropped_by_reason"] == {"bad_image": 1}


def test_live_settings_and_config_take_effect_at_the_next_window():
    ttr = ScriptedTTR()
    box = {"steps": 7, "size": 2}

    def config():
        cfg = TTRConfig()
        cfg.refinement.steps = box["steps"]
        return cfg

    stream = WindowRunner(
        ttr, config_provider=config,
        settings_provider=lambda: StreamSettings(window_size=box["size"], window_stride=2))
    outs = run(stream, frames(2))
    box.update(steps=3, size=3)
    outs += run(stream, frames(3, start=1.0))
    assert [c.refinement.steps for c in ttr.configs] == [7, 3]
    assert [len(w) for w in ttr.windows] == [2, 3]
    assert [w.steps for w in stream.windows] == [7, 3]
    check_accounting(stream, outs, 5)


def test_a_camera_slower_than_idle_flush_s_is_not_taken_for_a_stopped_one():
    """Frames every 0.25 s with ``idle_flush_s`` 0.1: windows stay whole (the flush waits 3
    frame intervals); once the frames stop, the rest is flushed as a final window."""
    ttr = ScriptedTTR(delay=0.0)
    outs: list[FrameOutput] = []
    stream = WindowRunner(ttr, StreamSettings(window_size=4, window_stride=4,
                                                 idle_flush_s=0.1), on_output=outs.append)
    stop = threading.Event()
    t = threading.Thread(target=lambda: [stream.step(timeout=0.02) for _ in iter(stop.is_set,
                                                                             True)])
    t.start()
    try:
        for f in frames(6):
            stream.submit(f, INTR)
            time.sleep(0.25)
        deadline = time.monotonic() + 10
        while len(outs) < 6 and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        stop.set()
        t.join(5)
    assert [len(w) for w in ttr.windows] == [4, 2], ttr.windows
    assert stream._idle_after() == pytest.approx(0.75, rel=0.3)
    check_accounting(stream, outs, 6)


def test_idle_flush_and_worker_thread_cancel():
    ttr = ScriptedTTR(delay=0.0)
    outs: list[FrameOutput] = []
    stream = WindowRunner(ttr, StreamSettings(window_size=4, window_stride=2,
                                                 idle_flush_s=0.3), on_output=outs.append)
    stop = threading.Event()

    def worker():
        while not stop.is_set():
            stream.step(timeout=0.05)

    t = threading.Thread(target=worker)
    t.start()
    try:
        for f in frames(3):
            stream.submit(f, INTR)
        deadline = time.monotonic() + 10
        while len(outs) < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert [o.refined for o in outs] == [True] * 3  # a final partial window of 3
        assert ttr.windows == [["0000000000", "0000000001", "0000000002"]]
    finally:
        stream.cancel()
        stop.set()
        t.join(5)
    assert not t.is_alive()
    assert stream.step(timeout=1.0) == []  # cancelled: returns at once
    check_accounting(stream, outs, 3)


# -- the real SfmTTR with a tiny network ------------------------------------------------------
@pytest.fixture(scope="module")
def sequence():
    synthetic = pytest.importorskip("sfm_ttr_ros.data.synthetic")
    return synthetic.make_sequence(seed=0, domain="A", num_frames=8, width=320, height=96)


def small_config(steps: int = 5) -> TTRConfig:
    cfg = TTRConfig()
    cfg.refinement.steps = steps
    cfg.sfm.max_num_features = 2048
    cfg.min_supervision_points = 20
    return cfg


@pytest.mark.slow
def test_real_windows_on_a_synthetic_street(sequence):
    ttr = SfmTTR(tiny_model(), small_config())
    try:
        stream = WindowRunner(ttr, StreamSettings(window_size=5, window_stride=3))
        fs = [Frame(i, im, stamp=s) for i, (im, s) in
              enumerate(zip(sequence.images, sequence.stamps, strict=True))]
        outs = run(stream, fs, sequence.intrinsics)
        outs += stream.flush()
    finally:
        ttr.close()
    c = check_accounting(stream, outs, len(fs))
    assert c["pending"] == 0 and c["refined"] >= 5
    w = stream.windows[0]
    assert w.refined and w.registered >= 2 and w.points >= 20
    assert 0 < w.inlier_ratio <= 1 and w.scale > 0 and w.steps == w.steps_done == 5
    assert np.isfinite(w.loss_before) and np.isfinite(w.loss_after)
    assert w.cloud_xyz.shape == (w.points, 3) and w.cloud_frame is not None
    assert w.cloud_frame.name in w.names and {"sfm", "refine"} <= set(w.timings)
    assert w.cloud_frame.image is RELEASED_IMAGE  # the history keeps no pixels
    for o in outs:
        assert o.depth.shape == (96, 320) and o.depth.dtype == np.float32


@pytest.mark.slow
def test_static_camera_is_published_unrefined_with_the_sfm_reason(sequence):
    ttr = SfmTTR(tiny_model(), small_config())
    try:
        stream = WindowRunner(ttr, StreamSettings(window_size=4, window_stride=4))
        fs = [Frame(i, sequence.images[0].copy(), stamp=float(i)) for i in range(4)]
        outs = run(stream, fs, sequence.intrinsics)
    finally:
        ttr.close()
    c = check_accounting(stream, outs, 4)
    assert c["unrefined_by_reason"] == {"sfm_failed": 4}
    assert all(o.reason.startswith("SfM failed: ") and len(o.reason) > len("SfM failed: ")
               for o in outs)
    assert c["windows_failed"] == 1


def test_zero_steps_publishes_unrefined_as_disabled_without_running_sfm(sequence):
    ttr = SfmTTR(tiny_model(), small_config(steps=0))
    try:
        stream = WindowRunner(ttr, StreamSettings(window_size=4, window_stride=4))
        fs = [Frame(i, im, stamp=float(i)) for i, im in enumerate(sequence.images[:4])]
        outs = run(stream, fs, sequence.intrinsics)
    finally:
        ttr.close()
    c = check_accounting(stream, outs, 4)
    assert c["unrefined_by_reason"] == {"disabled": 4}
    assert c["windows_failed"] == 0 and c["windows_skipped"] == 0
    assert c["windows_disabled"] == 1
    assert stream.windows[0].result.sfm is None  # no time spent on SfM


def test_the_next_windows_sfm_begins_while_a_window_runs():
    """While window 0 refines, the frames of window 1 (its 5 overlap frames + 5 new ones) are
    all queued: their SfM is asked for ahead, once (keyframe_policy all: every frame a
    keyframe); with a keyframe floor, or under newest (a full next window queued means the
    worker is behind: those frames go stale), never."""
    ahead = [[f"{k:010d}" for k in range(5, 15)]]
    for policy, interval, want in (("all", 0.0, ahead), ("all", 0.05, []),
                                   ("newest", 0.0, [])):
        ttr = ScriptedTTR(delay=0.3)
        s = WindowRunner(ttr, StreamSettings(window_size=10, window_stride=5,
                                                min_keyframe_interval_s=interval,
                                                keyframe_policy=policy,
                                                overload_pending=0))
        worker = threading.Thread(target=lambda st=s: [st.step(timeout=0.05) for _ in range(60)])
        fs = frames(16)
        for k in range(10):
            s.submit(fs[k], INTR)
        worker.start()
        while not ttr.windows:
            time.sleep(0.01)
        for k in range(10, 16):
            s.submit(fs[k], INTR)
        worker.join()
        assert ttr.prefetched == want, (policy, interval)
        assert s.counters()["sfm_ahead"]["started"] == len(want)


def test_a_short_first_window_then_windows_of_window_size():
    """first_window_size 4: the first window closes after 4 keyframes (its weights reach the
    live output sooner), the next ones have window_size frames; every frame is accounted for."""
    ttr = ScriptedTTR()
    s = WindowRunner(ttr, StreamSettings(window_size=6, window_stride=6, first_window_size=4))
    outs = []
    for f in frames(16):
        outs += s.push(f, INTR)
    assert [len(w) for w in ttr.windows] == [4, 6, 6]
    assert ttr.windows[1][0] == f"{4:010d}"
    check_accounting(s, outs, 16)
    with pytest.raises(ValueError, match="first_window_size"):
        StreamSettings(window_size=6, first_window_size=7)
