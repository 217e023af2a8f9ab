"""The metric scale (sfm_ttr_ros.core.metric): a ground plane under the cameras gives their
height in SfM units, odometry the travelled distance, and one steady factor (the median of the
accepted windows) turns the outputs into metres; a jump is refused; what is not metric says
so."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.metric.ground import ground_plane
from sfm_ttr_ros.core.metric.metric_config import MetricConfig
from sfm_ttr_ros.core.metric.odometry_track import OdometryTrack, path_length
from sfm_ttr_ros.core.metric.scale import MetricScale, WindowMetric, estimate
from sfm_ttr_ros.core.sfm.result import FrameObservations, SfmResult


def street(units: float = 0.5, height: float = 1.65, pitch_deg: float = 0.0, n: int = 10,
           seed: int = 0, ground_points: int = 300) -> tuple[SfmResult, list[str]]:
    """A reconstruction of a camera driving along +z at ``height`` m above the plane y = 0
    (y down: the camera at y = -height), in SfM units of ``units`` m: ground points over 3-30 m
    ahead, +-6 m sideways, and building points at x = +-8 m."""
    rng = np.random.default_rng(seed)
    s = 1.0 / units  # metres -> SfM units
    g = np.c_[rng.uniform(-6, 6, ground_points), rng.normal(0, 0.01, ground_points),
              rng.uniform(3, 30, ground_points)]
    walls = np.c_[rng.choice([-8.0, 8.0], 200), rng.uniform(-6, 0, 200), rng.uniform(3, 30, 200)]
    points = np.vstack([g, walls]) * s
    a = math.radians(pitch_deg)
    R = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    frames = {}
    for j in range(n):
        C = np.array([0.0, -height, 0.6 * j]) * s
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, -R @ C
        name = f"{j:04d}"
        frames[name] = FrameObservations(name, np.zeros((1, 2)), np.ones(1), np.zeros(1),
                                         np.zeros(1), np.zeros(1, np.int64), T)
    sfm = SfmResult(True, "", n, frames=frames, points_xyz=points)
    return sfm, list(frames)


def test_the_camera_height_is_found_in_sfm_units_under_any_scale():
    cfg = MetricConfig(source="camera_height")
    for units in (0.5, 3.0):
        sfm, reg = street(units=units)
        plane = ground_plane(sfm, reg, cfg)
        assert plane.height == pytest.approx(1.65 / units, rel=0.02), plane.reason
        # the ground within metric.corridor (1.5 camera heights) of the track: ~125 of 300
        assert plane.inliers >= 100 and plane.spread < 0.05 and abs(plane.pitch_deg) < 1
        w = estimate(cfg, sfm, reg, [0.1 * i for i in range(10)], alignment_scale=2.0,
                     odometry=None)
        assert w.ok and w.metres_per_sfm_unit == pytest.approx(units, rel=0.02)
        assert w.metres_per_net_unit == pytest.approx(units / 2.0, rel=0.02)
        assert w.metres_per_net_unit_after == 1.0  # learn: the refined network predicts metres


@pytest.mark.parametrize("kind, why", [
    ("no_ground", "points on the ground plane"),
    ("pitched", ""),  # "points below the cameras" or "no plane across ...": refused either way
    ("table", "spans"),
])
def test_no_ground_plane_is_refused_with_the_reason(kind, why):
    """What a hand-held camera indoors gives (hololens_000 refused every window measured): no
    plane under the camera, a camera looking down at a surface, a small table top."""
    cfg = MetricConfig(source="camera_height")
    if kind == "no_ground":
        sfm, reg = street(ground_points=5)
    elif kind == "pitched":
        sfm, reg = street(pitch_deg=40.0)
    else:
        sfm, reg = street()
        table = sfm.points_xyz[:300] * np.array([0.05, 1, 0.05]) + np.array([0, 0, 6.0]) / 0.5
        sfm.points_xyz = np.vstack([table, sfm.points_xyz[300:]])
    plane = ground_plane(sfm, reg, cfg)
    assert math.isnan(plane.height) and why in plane.reason
    w = estimate(cfg, sfm, reg, [0.1 * i for i in range(10)], 1.0, None)
    assert not w.ok and w.reason.startswith("no ground plane:")


def test_odometry_gives_metres_per_sfm_unit_from_the_travelled_path():
    sfm, reg = street(units=0.5)  # the camera moves 0.6 m a frame: 1.2 SfM units
    track = OdometryTrack()
    for i in range(-5, 40):  # 20 Hz positions, the frames at 10 Hz
        assert track.add(0.05 * i, [0.0, 0.0, 0.3 * i])
    assert not track.add(1.9, [0, 0, 0])  # out of order (< 1 s back): rejected, counted
    assert not track.add(9.0, [np.nan, 0, 0]) and track.rejected == 2
    cfg = MetricConfig(source="odometry")
    w = estimate(cfg, sfm, reg, [0.1 * i for i in range(10)], 1.0, track)
    assert w.ok and w.metres_per_sfm_unit == pytest.approx(0.5) and w.travel_m == pytest.approx(5.4)
    assert not estimate(cfg, sfm, reg, [0.1 * i + 5 for i in range(10)], 1.0, track).ok
    standing = OdometryTrack()
    for i in range(20):
        standing.add(0.1 * i, [0.0, 0.0, 0.001 * i])
    assert "min_travel" in estimate(cfg, sfm, reg, [0.1 * i for i in range(10)], 1.0,
                                    standing).reason
    assert path_length(np.zeros((1, 3))) == 0.0


def test_a_network_that_learns_metres_is_served_as_metric_and_a_jump_is_refused():
    """learn (the default): the refined weights predict metres (factor 1); each window's k
    says how metric the network was before it, a window far from it is refused."""
    cfg = MetricConfig(source="camera_height", max_jump=1.5)
    scale = MetricScale()
    assert scale.factor(cfg) is None  # waiting for the first accepted estimate
    # start-up units: 0.6 m each
    first = WindowMetric("camera_height", metres_per_net_unit=0.6, metres_per_net_unit_after=1.0)
    assert scale.judge(cfg, first, "continue") == ""  # no reference yet
    scale.accept(cfg, first, "continue")
    assert scale.factor(cfg) == 1.0
    for k in (1.02, 0.97):
        w = WindowMetric("camera_height", metres_per_net_unit=k, metres_per_net_unit_after=1.0)
        assert scale.judge(cfg, w, "continue") == ""
        scale.accept(cfg, w, "continue")
    assert scale.spread() == pytest.approx(0.025, abs=1e-9)
    jump = WindowMetric("camera_height", metres_per_net_unit=1.8, metres_per_net_unit_after=1.0)
    assert "metric.max_jump" in scale.judge(cfg, jump, "continue")


def test_scaled_outputs_take_the_median_of_the_accepted_windows():
    cfg = MetricConfig(source="camera_height", max_jump=1.5, learn=False)
    scale = MetricScale()
    for k in (0.5, 0.52, 0.49):
        w = WindowMetric("camera_height", metres_per_net_unit=k, metres_per_net_unit_after=k)
        assert scale.judge(cfg, w, "continue") == ""
        scale.accept(cfg, w, "continue")
    assert scale.factor(cfg) == pytest.approx(0.5) and scale.spread() < 0.05
    jump = WindowMetric("camera_height", metres_per_net_unit=0.9, metres_per_net_unit_after=0.9)
    assert "metric.max_jump 1.5" in scale.judge(cfg, jump, "continue")
    # no estimate: no verdict
    assert scale.judge(cfg, WindowMetric("camera_height"), "continue") == ""
    assert scale.factor(MetricConfig(source="fixed", factor=2.5)) == 2.5
    assert scale.factor(MetricConfig()) is None  # none: the network's units


def test_under_reset_a_window_is_judged_against_the_start_up_weights():
    """reset: every window starts from the start-up weights, whose k the windows before
    measured; their refined weights are metric (learn) all the same."""
    cfg = MetricConfig(source="camera_height", max_jump=1.5)
    scale = MetricScale()
    for k in (0.6, 0.62, 0.58):
        w = WindowMetric("camera_height", metres_per_net_unit=k, metres_per_net_unit_after=1.0)
        assert scale.judge(cfg, w, "reset") == "", k
        scale.accept(cfg, w, "reset")
    assert scale.factor(cfg) == 1.0 and scale.reference(cfg, "reset") == pytest.approx(0.6)
    far = WindowMetric("camera_height", metres_per_net_unit=1.2, metres_per_net_unit_after=1.0)
    assert scale.judge(cfg, far, "reset")


def test_metric_settings_validate_themselves():
    for bad in ({"source": "gps"}, {"camera_height": 0.0}, {"factor": -1.0},
                {"max_jump": 0.5}):
        with pytest.raises(InputError):
            MetricConfig(**bad)


def test_the_outputs_are_in_metres_once_there_is_a_factor():
    """The windowed outputs are multiplied by the stream's factor when there is one (and say
    so); the served weights carry their factor, withdrawn with them."""
    from conftest import tiny_model
    from test_stream import INTR, ScriptedTTR, frames

    from sfm_ttr_ros.core.stream.serving import ServingModel
    from sfm_ttr_ros.core.stream.window_runner import StreamSettings, WindowRunner

    ttr = ScriptedTTR()
    ttr.metres_per_unit = None
    s = WindowRunner(ttr, StreamSettings(window_size=2, window_stride=2))
    outs = s.push(frames(1)[0], INTR) + s.push(frames(2)[1], INTR)
    assert [o.metres_per_unit for o in outs] == [None, None]
    assert float(outs[0].depth.mean()) == 2.0  # the scripted refined depth, network units
    ttr.metres_per_unit = 1.5
    more = frames(4)
    outs = s.push(more[2], INTR) + s.push(more[3], INTR)
    assert [o.metres_per_unit for o in outs] == [1.5, 1.5]
    assert float(outs[0].depth.mean()) == pytest.approx(3.0)

    model = tiny_model((32, 48), downsample=False)
    serving = ServingModel(model)
    image = np.random.default_rng(0).integers(0, 255, (32, 48, 3), np.uint8)
    plain, _ = serving.predict(image)
    state = {k: v.clone() for k, v in model.encoder.state_dict().items()}
    serving.update(state, 1, metres_per_unit=2.0)
    assert np.allclose(serving.predict(image)[0], 2.0 * plain)
    serving.preview(state, 2, step=5)
    serving.set_metres_per_unit(3.0)
    assert serving.revert() and serving.metres_per_unit == 2.0


@pytest.mark.parametrize("source", ["camera_height", "odometry", "fixed"])
def test_a_metric_source_on_relative_inverse_depth_is_refused_before_and_after_loading(source):
    """Affine-invariant inverse depth (up to scale and shift) has no factor to metres: a metric
    source on such a network is refused where the settings are built (an explicit
    ``output_kind``, before any model is loaded) and where the model meets its options (the
    kind the model says, detected or a plug-in's: the node does not start, nor do the CLI's
    run and benchmark); ``none`` and networks that predict depth are let through."""
    from conftest import tiny_model

    from sfm_ttr_ros.core.params import values
    from sfm_ttr_ros.core.pipeline import SfmTTR
    from sfm_ttr_ros.core.window_io import TTRConfig

    hf = {"model_type": "hf", "model_path": "some/model", "metric.source": source}
    why = values.validate({**hf, "output_kind": "relative_inverse_depth"})
    assert f"metric.source '{source}'" in why and "relative_inverse_depth" in why
    assert values.validate({**hf, "output_kind": "relative_depth"}) == ""
    assert values.validate({**hf, "output_kind": ""}) == ""  # detected at loading: below
    assert values.validate({**hf, "metric.source": "none",
                            "output_kind": "relative_inverse_depth"}) == ""
    model = tiny_model()
    model.output_kind = "relative_inverse_depth"
    config = TTRConfig(metric=MetricConfig(source=source))
    with pytest.raises(InputError, match="affine-invariant"):
        SfmTTR(model, config)
    ttr = SfmTTR(model, TTRConfig())  # metric.source none: the relative topics
    try:
        with pytest.raises(InputError, match=f"metric.source '{source}'"):
            ttr.set_config(config)  # a live change is refused alike
    finally:
        ttr.close()
    model.output_kind = "metric_depth"
    SfmTTR(model, config).close()
