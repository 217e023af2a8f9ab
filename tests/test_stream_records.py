"""The stream's settings and output records: StreamSettings' validation and backlog bound,
WindowStats read from the core's WindowResult (built once, no figure kept twice)."""

from __future__ import annotations

import numpy as np
import pytest

from sfm_ttr_ros.core.alignment.scale import AlignmentResult
from sfm_ttr_ros.core.checks.measures import CheckReport
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Frame
from sfm_ttr_ros.core.metric.scale import WindowMetric
from sfm_ttr_ros.core.outcomes import Unrefined
from sfm_ttr_ros.core.pipeline import WindowResult
from sfm_ttr_ros.core.refinement.encoder import RefinementResult
from sfm_ttr_ros.core.sfm.result import FrameObservations, SfmResult
from sfm_ttr_ros.core.stream.records import FrameOutput, WindowStats, unrefined_result
from sfm_ttr_ros.core.stream.settings import StreamSettings


@pytest.mark.parametrize("bad", [
    {"window_size": 1}, {"first_window_size": 1}, {"window_size": 4, "first_window_size": 5},
    {"window_stride": -1}, {"window_size": 4, "window_stride": 5}, {"keyframe_policy": "some"},
    {"max_pending": 0}, {"min_keyframe_interval_s": -1.0}, {"min_keyframe_motion": float("nan")},
    {"idle_flush_s": float("inf")}, {"live_max_queue": 0}, {"worker_threads": -1},
    {"serve_every_steps": -1}, {"worker_nice": 20}, {"overload_pending": -1}])
def test_settings_refuse_each_bad_value_with_its_name(bad):
    with pytest.raises(InputError, match=next(iter(bad))):
        StreamSettings(**bad)


def test_the_backlog_bound_holds_only_when_unrefined_frames_are_not_republished():
    assert StreamSettings(window_size=4, window_stride=2, overload_pending=6).backlog_images == 10
    assert StreamSettings(overload_pending=0).backlog_images == 0
    assert StreamSettings(republish_unrefined=True).backlog_images == 0


def observations(name: str, errors: list[float]) -> FrameObservations:
    n = len(errors)
    return FrameObservations(name, np.zeros((n, 2), np.float32), np.ones(n), np.array(errors),
                             np.ones(n), np.arange(n), np.eye(4))


def full_result(refined: bool) -> WindowResult:
    names = ["a", "b", "c"]
    depth = {n: np.ones((4, 6), np.float32) for n in names}
    sfm = SfmResult(True, "", 3, frames={"a": observations("a", [0.5, 1.5]),
                                         "b": observations("b", [1.0])},
                    point_ids=np.arange(7), attempts=[{}, {}])
    return WindowResult(
        names, dict(depth), dict(depth), refined, "" if refined else "rolled back",
        None if refined else Unrefined.ROLLED_BACK, check=CheckReport(unsupported_change=0.1),
        depths_candidate=dict(depth), sfm=sfm,
        alignment=AlignmentResult(2.0, np.array([True, True, False, True]),
                                  np.array([True, False, False, True])),
        refinement=RefinementResult(steps_done=3, step_mode="eager", step_mode_reason="cpu"),
        metric=WindowMetric("ground", metres_per_net_unit=0.5, reason="ok"), scale=2.0,
        loss_before=0.4,
        loss_after=0.2, cloud_frame="c", cloud_xyz=np.ones((7, 3), np.float32),
        cloud_error=np.ones(7, np.float32), timings={"sfm": 1.0})


def test_window_stats_read_every_figure_from_the_result_they_keep_once():
    res = full_result(refined=True)
    w = WindowStats.of(2, 3, res, steps=5, started_at=1.0)
    assert w.result is not res and w.result.sfm is res.sfm  # one copy of each figure
    assert w.result.depths == {} and w.result.depths_before == {}  # no maps in the history
    assert w.result.depths_candidate == {} and res.depths  # the core's result is untouched
    assert (w.index, w.new_frames, w.steps, w.started_at) == (2, 3, 5, 1.0)
    assert w.names == ["a", "b", "c"] and w.refined and w.ok
    assert w.reason_key is None and w.reason == ""
    assert (w.registered, w.points, w.mapping_attempts) == (2, 7, 2)
    assert w.reprojection_error == pytest.approx(1.0)
    assert (w.inlier_ratio, w.selected_points) == (0.75, 2)
    assert (w.scale, w.loss_before, w.loss_after, w.steps_done) == (2.0, 0.4, 0.2, 3)
    assert w.step_mode == "eager: cpu"
    assert (w.unsupported_change, w.metric_estimate, w.metric_reason) == (0.1, 0.5, "ok")
    assert w.cloud_xyz.shape == (7, 3) and w.cloud_error.shape == (7,)
    res.timings["later"] = 2.0  # the history keeps the timings the window ended with
    assert w.timings == {"sfm": 1.0}


def test_an_unrefined_window_gives_its_reason_and_no_figures_it_did_not_reach():
    w = WindowStats.of(0, 2, full_result(refined=False), steps=5, started_at=0.0)
    assert not w.refined and w.reason_key == Unrefined.ROLLED_BACK and w.reason == "rolled back"
    skipped = WindowStats.of(1, 2, unrefined_result(["a", "b"], Unrefined.OVERLOAD, "busy"),
                             steps=5, started_at=0.0)
    assert (skipped.reason_key, skipped.reason, skipped.names) == ("overload", "busy", ["a", "b"])
    assert (skipped.registered, skipped.points, skipped.steps_done, skipped.step_mode) == \
        (0, 0, 0, "")
    for figure in ("reprojection_error", "inlier_ratio", "scale", "unsupported_change",
                   "metric_estimate"):
        assert np.isnan(getattr(skipped, figure)), figure
    assert skipped.cloud_xyz.shape == (0, 3) and skipped.cloud_frame is None


def test_a_frame_output_without_depth_is_live_only():
    f = Frame(0, np.zeros((2, 2, 3), np.uint8))
    assert FrameOutput(f, None, False, Unrefined.OVERLOAD).live_only
    assert not FrameOutput(f, np.ones((2, 2), np.float32), True).live_only
