"""The metric scale's anchor (core/metric/anchor.py, scale.py): confirmed by agreement between
windows, recovered from a wrong first estimate, re-anchored by windows that agree with each
other and not with it, a disagreeing window refined in the stream's metres, the state stale
when the source stops, odometry that survives a restart, ``fixed`` on the cloud too."""

from __future__ import annotations

import numpy as np
import pytest
from test_metric import street

from sfm_ttr_ros.core.alignment.cloud import window_cloud
from sfm_ttr_ros.core.alignment.scale import AlignmentResult
from sfm_ttr_ros.core.metric.metric_config import MetricConfig
from sfm_ttr_ros.core.metric.odometry_track import OdometryTrack
from sfm_ttr_ros.core.metric.scale import MetricScale, WindowMetric, estimate


class Network:
    """A network's units under refinement: ``u`` true metres per unit of its weights. A window
    whose estimate is off by ``e`` (1 = right) measures k = u·e; refined on targets
    target_m·D_sfm it then predicts in units of m / (target_m·e) metres (SfM unit: 1 m·e/m)."""

    def __init__(self, u: float, policy: str = "continue") -> None:
        self.u, self.policy = u, policy

    def window(self, scale: MetricScale, cfg: MetricConfig, e: float) -> tuple[str, WindowMetric]:
        w = WindowMetric("camera_height", metres_per_sfm_unit=e, metres_per_net_unit=self.u * e,
                         metres_per_net_unit_after=1.0, supervision_metres_per_sfm_unit=e)
        why = scale.judge(cfg, w, self.policy)
        if not why:
            scale.accept(cfg, w, self.policy)
            if self.policy == "continue":
                self.u = w.metres_per_sfm_unit / (w.supervision_metres_per_sfm_unit * e)
        return why, w


def test_a_wrong_first_estimate_is_recovered_within_three_windows():
    cfg = MetricConfig(source="camera_height")
    scale, net, odom = MetricScale(), Network(0.6), OdometryTrack()
    assert scale.status(cfg, odom).state == "waiting"
    states = []
    for e in (1.5, 1.0, 1.0):  # the first ground plane reads 50 % too far
        assert net.window(scale, cfg, e)[0] == ""
        states.append(scale.status(cfg, odom).state)
    assert states == ["confirming", "confirming", "metric"]
    assert net.u == pytest.approx(1.0)  # the network predicts true metres
    assert "confirmed by 2" in scale.status(cfg, odom).reason
    for e in (1.0, 1.03):
        assert net.window(scale, cfg, e)[0] == ""
    assert net.u == pytest.approx(1 / 1.03)


def test_a_disagreeing_window_does_not_move_the_learnt_metres():
    """Once confirmed, a window 40 % off (within max_jump) is refined toward the anchor's metres:
    its targets use ref·ŝ, not its own m, and the anchor stays."""
    cfg = MetricConfig(source="camera_height")
    scale, net = MetricScale(), Network(0.6)
    for e in (1.0, 1.0):
        net.window(scale, cfg, e)
    why, w = net.window(scale, cfg, 1.4)
    assert why == "" and w.verdict == "disagrees" and "anchor" in w.reason
    # ref (1) · ŝ (m / k = 1): the stream's metres
    assert w.supervision_metres_per_sfm_unit == pytest.approx(1.0)
    assert net.u == pytest.approx(1.0) and scale.factor(cfg) == 1.0
    # under reset the anchor is the start-up weights' k
    scale, net = MetricScale(), Network(0.6, "reset")
    for e in (1.0, 1.02, 1.4):
        why, w = net.window(scale, cfg, e)
    shat = w.metres_per_sfm_unit / w.metres_per_net_unit
    assert w.verdict == "disagrees"
    assert w.supervision_metres_per_sfm_unit == pytest.approx(0.606 * shat, rel=1e-3)
    assert scale.reference(cfg, "reset") == pytest.approx(0.606)


@pytest.mark.parametrize("off", [1.3, 2.5])
def test_windows_that_agree_with_each_other_and_not_the_anchor_re_anchor_it(off):
    """Two wrong windows confirmed an anchor; the right windows after them disagree (refined
    in the anchor's metres, or refused beyond max_jump) until three agree: re-anchored."""
    cfg = MetricConfig(source="camera_height")
    scale, net, odom = MetricScale(), Network(0.6), OdometryTrack()
    for _ in range(2):
        net.window(scale, cfg, off)
    assert scale.status(cfg, odom).state == "metric" and net.u == pytest.approx(1 / off)
    verdicts = [net.window(scale, cfg, 1.0) for _ in range(3)]
    assert [w.verdict for _, w in verdicts] == ["disagrees", "disagrees", "re-anchors"]
    assert all(bool(why) == (off > cfg.max_jump) for why, _ in verdicts[:2])
    assert net.u == pytest.approx(1.0)
    s = scale.status(cfg, odom)
    assert (s.state, s.re_anchors) == ("metric", 1) and "re-anchored" in s.reason
    assert net.window(scale, cfg, 1.0)[1].verdict == "agrees"


def test_the_state_goes_stale_when_the_source_stops():
    cfg = MetricConfig(source="camera_height", stale_windows=2)
    scale, net, odom = MetricScale(), Network(1.0), OdometryTrack()
    for _ in range(2):
        net.window(scale, cfg, 1.0)
    for _ in range(2):  # no ground plane in view
        scale.judge(cfg, WindowMetric("camera_height", reason="no ground plane"), "continue")
    s = scale.status(cfg, odom)
    assert (s.state, s.metres_per_unit) == ("stale", 1.0) and "2 windows" in s.reason
    net.window(scale, cfg, 1.0)
    assert scale.status(cfg, odom).state == "metric"

    # odometry silent in the data's time: its last stamp behind the images' newest
    track = OdometryTrack()
    cfg = MetricConfig(source="odometry", odometry_timeout_s=2.0)
    scale = MetricScale()
    track.add(0.0, [0, 0, 0])
    for _ in range(2):
        Network(1.0).window(scale, cfg, 1.0)
    scale.note_images([0.5, 1.0])
    assert scale.status(cfg, track).state == "metric"
    scale.note_images([2.0, 2.5, float("nan")])
    s = scale.status(cfg, track)
    assert s.state == "stale" and "no odometry for 2.5 s of images" in s.reason
    track.add(2.5, [0, 0, 1])  # it speaks again
    assert scale.status(cfg, track).state == "metric"


def test_a_bag_played_twice_keeps_odometry_metres():
    """A restart (stamps back to the bag's start) restarts the track instead of refusing every
    later message; windows of both plays get the same metres."""
    sfm, reg = street(units=0.5)  # 0.6 m a frame: 1.2 SfM units
    cfg = MetricConfig(source="odometry")
    track = OdometryTrack()
    ms = []
    for _ in range(2):  # the bag, then its loop: the same stamps and positions again
        for i in range(40):
            assert track.add(100.0 + 0.05 * i, [0.0, 0.0, 0.3 * i])
        w = estimate(cfg, sfm, reg, [100.0 + 0.1 * i for i in range(10)], 1.0, track)
        ms.append(w.metres_per_sfm_unit)
    assert ms == pytest.approx([0.5, 0.5])
    assert (track.resets, track.rejected) == (1, 0)
    assert not track.add(101.5, [0, 0, 0]) and track.rejected == 1  # slightly back: out of order


def test_the_cloud_is_in_the_depth_outputs_units():
    """``fixed``: ~/points carries metric.factor like the depth images; an affine fit none."""
    sfm, reg = street(units=0.5)
    fit = AlignmentResult(2.0, np.zeros(0, bool), np.zeros(0, bool))
    _, plain, _ = window_cloud(sfm, reg, fit)
    _, fixed, _ = window_cloud(sfm, reg, fit,
                               MetricScale().factor(MetricConfig(source="fixed", factor=0.25)))
    assert np.allclose(fixed, 0.25 * plain) and np.allclose(plain, 2.0 * sfm.points_in_frame(
        reg[-1]), rtol=1e-5)


def test_the_pipeline_supervises_a_disagreeing_window_in_the_streams_metres():
    """SfmTTR's metric stage: a window that agrees with the anchor is supervised in its own
    metres (targets m·D_sfm); one that disagrees (k 1.4x the anchor's, within max_jump) in the
    stream's (ref·ŝ: here ŝ itself, the network having learnt metres), not moving them."""
    from types import SimpleNamespace

    from conftest import tiny_model

    from sfm_ttr_ros.core.pipeline import SfmTTR
    from sfm_ttr_ros.core.window_io import TTRConfig

    sfm, reg = street(units=0.5)  # 0.5 m per SfM unit
    cfg = TTRConfig(weight_policy="continue", metric=MetricConfig(source="camera_height"))
    ttr = SfmTTR(tiny_model(), cfg)
    targets, verdicts = [], []
    try:
        for s_hat in (0.5, 0.5, 0.5 / 1.4, 0.5):  # k = m / ŝ: 1, 1, 1.4, 1
            fit = AlignmentResult(s_hat, np.ones(1, bool), np.ones(1, bool))
            res = SimpleNamespace(sfm=sfm, scale=s_hat, alignment=fit, metric=None)
            w = SimpleNamespace(result=res, registered=reg, scaled=True, metric=None,
                                frames=[SimpleNamespace(name=n, stamp=0.1 * i)
                                        for i, n in enumerate(reg)])
            assert ttr._measure_metric(w) is None
            ttr.metric.accept(cfg.metric, w.metric, cfg.weight_policy)
            targets.append(res.alignment.scale)
            verdicts.append(w.metric.verdict)
    finally:
        ttr.close()
    assert verdicts == ["candidate", "confirms", "disagrees", "agrees"]
    assert targets == pytest.approx([0.5, 0.5, 0.5 / 1.4, 0.5], rel=0.02)
    assert ttr.metric_status().state == "metric"


def test_the_node_warns_while_the_metres_are_stale():
    """ros/metric_watch.py: the node's timer warns (throttled by warn_every's key) while the
    state is stale, with its reason; nothing otherwise."""
    from types import SimpleNamespace

    from sfm_ttr_ros.ros.metric_watch import warn_if_stale

    cfg = MetricConfig(source="camera_height", stale_windows=1)
    scale, odom, said = MetricScale(), OdometryTrack(), []
    ttr = SimpleNamespace(metric_status=lambda: scale.status(cfg, odom))

    def warn(key, message):
        said.append((key, message))

    for _ in range(2):
        Network(1.0).window(scale, cfg, 1.0)
    assert not warn_if_stale(ttr, warn) and said == []
    scale.judge(cfg, WindowMetric("camera_height", reason="no ground plane"), "continue")
    assert warn_if_stale(ttr, warn)
    assert said[0][0] == "metric_stale" and "1 windows in a row" in said[0][1]
    assert not warn_if_stale(SimpleNamespace(), warn)  # a ttr without a metric status
