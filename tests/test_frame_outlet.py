"""FrameOutlet: what leaves the stream, counted before it reaches the sink (unrefined frames
predicted again or live-only, prediction failures dropped, verdicts, a window's frames)."""

from __future__ import annotations

import dataclasses

import numpy as np

from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.metric.scale import MetricStatus
from sfm_ttr_ros.core.outcomes import Dropped, Unrefined
from sfm_ttr_ros.core.pipeline import WindowResult
from sfm_ttr_ros.core.stream.admission import Verdict
from sfm_ttr_ros.core.stream.frame_outlet import FrameOutlet
from sfm_ttr_ros.core.stream.frame_queue import RELEASED_IMAGE, FrameQueue
from sfm_ttr_ros.core.stream.records import WindowStats
from sfm_ttr_ros.core.stream.settings import StreamSettings

INTR = Intrinsics(50.0, 50.0, 3.5, 2.5, 8, 6)


class Net:
    metres_per_unit = None

    def __init__(self, fail: bool = False):
        self.fail = fail
        self.predicted: list[int] = []
        self.predictor = self  # the stand-in is its own predictor (SfmTTR.predictor)

    def metric_status(self):
        return MetricStatus("fixed", "metric", self.metres_per_unit, float("nan"), 0, 0, 0)

    def predict(self, images):
        if self.fail:
            raise RuntimeError("no memory")
        self.predicted += [int(im[0, 0, 0]) for im in images]
        return [np.full(im.shape[:2], 3.0, np.float32) for im in images]


class Log:
    def __init__(self):
        self.lines: list[tuple[str, str]] = []

    def __getattr__(self, level):
        return lambda message: self.lines.append((level, message))


def setup(net: Net, republish: bool = False, n: int = 3):
    """A publisher over a queue from which ``n`` frames (served live) were taken."""
    q = FrameQueue()
    outs, drops, log = [], [], Log()
    pub = FrameOutlet(net, q, lambda: republish, outs.append,
                         lambda f, k, m: drops.append((f.index, k)), log)
    for i in range(n):
        f = Frame(i, np.full((6, 8, 3), i, np.uint8), stamp=float(i))
        f.served_live = True
        q.put(f, INTR, StreamSettings())
    taken = [q.take(0.0)[0] for _ in range(n)]
    return pub, q, taken, outs, drops, log


def test_frames_served_live_are_not_predicted_again_unless_republished():
    net = Net()
    pub, q, fs, outs, _, _ = setup(net)
    fs[1].served_live = False
    got = pub.unrefined(fs, Unrefined.NOT_KEYFRAME, "not a keyframe")
    assert got == outs and [o.live_only for o in got] == [True, False, True]
    assert net.predicted == [1] and q.pending() == 0
    assert q.counters()["live_only"] == 2 and q.ledger.balanced(q.pending())
    net = Net()
    pub, q, fs, outs, _, _ = setup(net, republish=True)
    fs[2] = dataclasses.replace(fs[2], image=RELEASED_IMAGE)  # no pixels left to predict
    assert [o.live_only for o in pub.unrefined(fs, Unrefined.OVERLOAD, "busy")] == \
        [False, False, True]
    assert net.predicted == [0, 1]


def test_a_failed_prediction_drops_the_frames_it_was_for():
    pub, q, fs, outs, drops, log = setup(Net(fail=True))
    fs[0].served_live = False
    got = pub.unrefined(fs, Unrefined.STALE, "stale")
    assert [o.frame.index for o in got] == [1, 2] and drops == [(0, "prediction_error")]
    c = q.counters()
    assert c["dropped_by_reason"] == {"prediction_error": 1} and c["unrefined"] == 2
    assert q.ledger.balanced(q.pending()) and log.lines[-1][0] == "error"


def test_a_verdict_publishes_the_flushed_keyframes_then_the_frame_then_logs():
    pub, q, fs, outs, drops, log = setup(Net())
    published_when_logged = []
    pub.log = type("Log", (), {"warning": lambda self, m: published_when_logged.append(
        (m, len(outs), q.pending()))})()
    v = Verdict("reset", flush=Unrefined.STAMP_JUMP_BACK, unrefined=Unrefined.STALE,
                warning="went back")
    got = pub.verdict(fs[2], v, fs[:2])
    assert [(o.frame.index, o.reason_key) for o in got] == \
        [(0, "stamp_jump_back"), (1, "stamp_jump_back"), (2, "stale")]
    assert published_when_logged == [("went back", 3, 0)]  # every frame out before the line
    pub, q, fs, outs, drops, log = setup(Net(), n=1)
    assert pub.verdict(fs[0], Verdict("twice", drop=Dropped.DUPLICATE_STAMP), []) == []
    assert drops == [(0, "duplicate_stamp")] and q.pending() == 0 and outs == []
    assert log.lines == [("warning", "twice")]
    pub, q, fs, outs, drops, log = setup(Net(), n=1)
    assert pub.verdict(fs[0], Verdict(info="took the received K"), []) == []
    assert log.lines == [("info", "took the received K")] and q.pending() == 1


def test_warnings_are_throttled_per_key_and_an_overflow_says_how_many():
    pub, q, fs, outs, drops, log = setup(Net(), n=0)
    for _ in range(3):
        pub.warn("a", "first")
    pub.warn("b", "second")
    assert log.lines == [("warning", "first"), ("warning", "second")]
    q.ledger.drop(Dropped.OVERFLOW, 4)
    pub.overflow(Frame(7, np.zeros((6, 8, 3), np.uint8), stamp=2.5), max_pending=3)
    assert drops == [(7, "overflow")]
    assert log.lines[-1][1] == ("input queue full (max_pending=3): dropped the oldest pending "
                                "frame (stamp 2.500000); 4 dropped so far")


def test_a_window_that_ran_publishes_its_own_depths_in_metres():
    net = Net()
    net.metres_per_unit = 2.0
    pub, q, fs, outs, _, _ = setup(net, n=2)
    depths = {f.name: np.full((6, 8), 1.5, np.float32) for f in fs}
    res = WindowResult([f.name for f in fs], depths, dict(depths), True)
    stats = WindowStats.of(4, 2, res, steps=1, started_at=0.0)
    got = pub.window(fs, res, stats, ran=True)
    assert [(o.refined, o.window, o.metres_per_unit) for o in got] == [(True, 4, 2.0)] * 2
    assert all(float(o.depth.mean()) == 3.0 for o in got) and net.predicted == []
