"""The camera's path (core/camera_path.py): windows chained on synthetic poses, the stream's
one path in its depth's metres (core/stream/path.py), and the drift measure of the benchmark
(tools/benchmark/path.py)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from sfm_ttr_ros.core.camera_path import (
    BODY_FROM_OPTICAL,
    UNKNOWN_VARIANCE,
    CameraPath,
    WindowPoses,
    fit_similarity,
    metres_per_sfm_unit,
    result_poses,
    window_poses,
)
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Frame
from sfm_ttr_ros.core.stream.records import FramePose
from sfm_ttr_ros.tools.benchmark.path import path_drift


def _rot(axis: int, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    i, j = [k for k in range(3) if k != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def _drive(n: int = 30) -> list[np.ndarray]:
    """Camera-to-world optical poses (metres) of a camera driving forward (+z) at 1 m per
    frame while turning slowly about its down axis (y)."""
    poses, R, c = [], np.eye(3), np.zeros(3)
    for _ in range(n):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, c
        poses.append(T)
        c = c + R @ np.array([0.0, 0.0, 1.0])
        R = R @ _rot(1, 0.02)
    return poses


def _world(gt: np.ndarray, s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """cam_from_world of the camera ``gt`` (camera-to-world) in a world x_w = s·R·x_gt + t."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R @ gt[:3, :3], s * R @ gt[:3, 3] + t
    inv = np.eye(4)
    inv[:3, :3], inv[:3, 3] = T[:3, :3].T, -T[:3, :3].T @ T[:3, 3]
    return inv


def _window(gt, frames, s, R, t, mapping="", metres=None, var=1e-4) -> WindowPoses:
    names = [f"{i:04d}" for i in frames]
    return WindowPoses({n: _world(gt[i], s, R, t) for n, i in zip(names, frames, strict=True)},
                       {n: 0.1 * i for n, i in zip(names, frames, strict=True)}, mapping,
                       metres, {n: var for n in names}, {n: var for n in names})


def _reported(path: CameraPath, added) -> list[FramePose]:
    """``added`` (one window's new poses) as the stream reports them, in the path's units."""
    return [FramePose(Frame(int(p.name), np.zeros((1, 1, 3), np.uint8), p.stamp, p.name), p,
                      path.units) for p in added]


def _drift(path: CameraPath, added, gt) -> dict[str, object]:
    return path_drift(_reported(path, added), path.summary(), gt)


def _expected(gt, i, scale=1.0) -> np.ndarray:
    """The GT pose of frame i in odom (the first frame's body axes), positions × scale."""
    rel = np.linalg.inv(gt[0]) @ gt[i]
    out = np.eye(4)
    out[:3, :3] = BODY_FROM_OPTICAL @ rel[:3, :3]
    out[:3, 3] = scale * BODY_FROM_OPTICAL @ rel[:3, 3]
    return out


def test_continued_windows_chain_in_metres_on_odoms_rep103_axes():
    gt = _drive()
    R, t, s = _rot(0, 0.3) @ _rot(2, -1.1), np.array([3.0, -2.0, 7.0]), 0.25
    path = CameraPath()
    first = path.add(_window(gt, range(0, 10), s, R, t, "fresh", metres=1 / s))
    more = path.add(_window(gt, range(5, 15), s, R, t, "continued", metres=None))
    assert path.units == "m" and [p.name for p in more] == [f"{i:04d}" for i in range(10, 15)]
    assert [p.chain for p in first + more] == ["first"] * 10 + ["continued"] * 5
    np.testing.assert_allclose(first[0].odom_from_camera[:3, :3], BODY_FROM_OPTICAL, atol=1e-9)
    for p in first + more:
        np.testing.assert_allclose(p.odom_from_camera, _expected(gt, int(p.name)), atol=1e-9)
    # forward motion is +x in odom, and the variances come from the window (× s² in metres)
    assert more[-1].position[0] > 13.5
    assert more[0].position_var == pytest.approx(1e-4 / s**2)
    assert path.summary()["chains"] == {"first": 1, "continued": 1, "shared": 0, "break": 0}


def test_fresh_mapping_chains_through_shared_frames_with_its_own_scale():
    gt = _drive()
    path = CameraPath()
    path.add(_window(gt, range(0, 10), 2.0, np.eye(3), np.zeros(3), "fresh"))  # SfM units
    R2, t2 = _rot(1, 2.0) @ _rot(0, -0.4), np.array([-5.0, 1.0, 0.5])
    added = path.add(_window(gt, range(6, 16), 0.3, R2, t2, "fresh"))
    assert path.units == "sfm" and [p.chain for p in added] == ["shared"] * 6
    for p in added:  # in the first reconstruction's units (2 per metre)
        np.testing.assert_allclose(p.odom_from_camera, _expected(gt, int(p.name), 2.0),
                                   atol=1e-8)
    # exact poses: no residual; the shared frames' variance (the first reconstruction's units)
    # plus the frame's own, scaled by s² = (2 / 0.3)²
    assert added[0].position_var == pytest.approx(1e-4 + 1e-4 * (2 / 0.3) ** 2)


def _observed(name: str, cam_from_world: np.ndarray):
    from sfm_ttr_ros.core.sfm.result import FrameObservations

    ones = np.ones(20)
    return FrameObservations(name, np.zeros((20, 2), np.float32), 5.0 * ones, 0.5 * ones,
                             0.5 * ones, np.arange(20), cam_from_world)


def test_a_fresh_map_chains_through_its_anchors_not_its_window():
    """A fresh mapping of a window that shares no frame with the path, mapped with the map's
    last frames (``SfmResult.anchors``), joins it through them: no break, the right poses, and
    the anchors, older than the path's end, are not published again."""
    from sfm_ttr_ros.core.sfm.result import SfmResult

    gt = _drive()
    path = CameraPath()
    path.add(_window(gt, range(0, 10), 1.0, np.eye(3), np.zeros(3), "fresh", metres=1.0))
    R2, t2 = _rot(1, 0.7), np.array([2.0, 0.0, -1.0])
    world = {i: _world(gt[i], 1.0, R2, t2) for i in range(7, 20)}
    sfm = SfmResult(True, "", 10, {f"{i:04d}": _observed(f"{i:04d}", world[i])
                                   for i in range(10, 20)})
    stamps = {f"{i:04d}": 0.1 * i for i in range(20)}
    alone = window_poses(sfm, stamps, "fresh", 1.0)
    sfm.anchors = {f"{i:04d}": _observed(f"{i:04d}", world[i]) for i in range(7, 10)}
    added = path.add(window_poses(sfm, stamps, "fresh", 1.0))
    assert set(alone.poses) == {f"{i:04d}" for i in range(10, 20)}
    assert [p.name for p in added] == [f"{i:04d}" for i in range(10, 20)]
    assert {p.chain for p in added} == {"shared"} and path.summary()["breaks"] == 0
    for p in added:
        np.testing.assert_allclose(p.odom_from_camera, _expected(gt, int(p.name)), atol=1e-8)


def test_a_batch_window_with_metres_keeps_metres_and_a_noisy_fit_raises_the_covariance():
    gt = _drive()
    path = CameraPath()
    path.add(_window(gt, range(0, 10), 1.0, np.eye(3), np.zeros(3), metres=1.0, var=0.0))
    noisy = _window(gt, range(5, 15), 4.0, _rot(2, 0.5), np.ones(3), metres=0.25, var=0.0)
    noisy.poses["0007"] = _world(gt[7] @ np.array([[1, 0, 0, 0.3], [0, 1, 0, 0], [0, 0, 1, 0],
                                                   [0, 0, 0, 1.0]]), 4.0, _rot(2, 0.5),
                                 np.ones(3))
    added = path.add(noisy)
    assert [p.chain for p in added] == ["shared"] * 5
    assert added[0].position_var > 0.005  # the fit's residual of a 0.3 m error
    np.testing.assert_allclose(added[-1].position, _expected(gt, 14)[:3, 3], atol=0.2)


def test_a_window_sharing_no_frame_is_a_counted_break_on_a_constant_velocity_guess():
    gt = _drive()
    path = CameraPath()
    path.add(_window(gt, range(0, 10), 1.0, np.eye(3), np.zeros(3), metres=1.0))
    end = path.last
    added = path.add(_window(gt, range(12, 20), 0.5, _rot(0, 1.0), np.zeros(3), "fresh"))
    assert path.breaks == 1 and added[0].chain == "break"
    # three frames' worth of the last velocity (1 m per frame) ahead of the end
    guess = end.position + 3 * (end.position - list(path.poses.values())[8].position)
    np.testing.assert_allclose(added[0].position, guess, atol=1e-9)
    assert added[0].position_var >= end.position_var + 9.0 - 1e-6  # the guessed 3 m, squared
    # the guess keeps the last heading: the 0.06 rad turned in the gap costs ~0.06 x 7 m here
    np.testing.assert_allclose(added[-1].position, _expected(gt, 19)[:3, 3], atol=0.6)


def test_a_break_with_no_velocity_to_guess_from_says_the_pose_is_unknown():
    gt = _drive()
    path = CameraPath()
    path.add(_window(gt, [0], 1.0, np.eye(3), np.zeros(3), metres=1.0))
    added = path.add(_window(gt, range(3, 6), 1.0, _rot(1, 0.4), np.ones(3), "fresh"))
    assert added[0].chain == "break" and added[0].position_var >= UNKNOWN_VARIANCE
    np.testing.assert_allclose(added[0].position, path.poses["0000"].position)


def test_nothing_older_than_the_path_end_joins_it_and_bad_limits_are_refused():
    gt = _drive()
    path = CameraPath(max_poses=6)
    path.add(_window(gt, range(5, 10), 1.0, np.eye(3), np.zeros(3), metres=1.0))
    late = path.add(_window(gt, range(0, 12), 1.0, np.eye(3), np.zeros(3), "continued"))
    assert [p.name for p in late] == ["0010", "0011"] and len(path.poses) == 6
    assert path.add(WindowPoses({}, {})) == [] and path.summary()["windows"] == 2
    with pytest.raises(InputError):
        CameraPath(max_poses=1)


def test_a_fitted_scale_needs_two_distinct_centres():
    gt = _drive()
    one = [_world(gt[3], 1.0, np.eye(3), np.zeros(3))]
    assert fit_similarity([gt[3]], one, None) is None
    assert fit_similarity([gt[3]], one, 1.0) is not None
    assert fit_similarity([], [], 1.0) is None


def test_drift_is_zero_on_the_poses_themselves_and_grows_with_a_wrong_scale():
    gt = _drive(40)
    path = CameraPath()
    added = path.add(_window(gt, range(40), 1.0, np.eye(3), np.zeros(3), metres=1.0))
    names = {f"{i:04d}": gt[i] for i in range(40)}
    exact = _drift(path, added, names)
    assert exact["compared"] == 40 and exact["drift_pct"] < 1e-6 and not exact["scale_fitted"]
    # a path 3 % too long ends 3 % of its chord off: 3 % x chord / distance travelled
    longer = CameraPath()
    added = longer.add(_window(gt, range(40), 1.0, np.eye(3), np.zeros(3), metres=1.03))
    assert longer.units == "m"
    chord = np.linalg.norm(gt[39][:3, 3] - gt[0][:3, 3])
    drift = _drift(longer, added, names)
    assert drift["length_m"] == pytest.approx(39.0)
    assert drift["drift_pct"] == pytest.approx(3.0 * chord / 39.0, rel=1e-6)
    unscaled = CameraPath()
    added = unscaled.add(_window(gt, range(40), 1.0, np.eye(3), np.zeros(3)))
    assert _drift(unscaled, added, names)["scale_fitted"]
    assert _drift(CameraPath(), [], names)["compared"] == 0


def test_a_path_in_sfm_units_turns_metric_at_the_first_window_in_metres():
    """The depth turned metric: the window is chained in the path's units, then the path
    scaled into metres about its origin (no jump); the poses handed out before keep theirs."""
    gt = _drive()
    path = CameraPath()
    before = path.add(_window(gt, range(0, 10), 2.0, np.eye(3), np.zeros(3), "fresh"))
    assert path.units == "sfm"
    R2, t2 = _rot(1, 0.8), np.array([1.0, 2.0, 3.0])
    after = path.add(_window(gt, range(6, 16), 0.5, R2, t2, "fresh", metres=2.0))
    assert path.units == "m" and [p.chain for p in after] == ["shared"] * 6
    for p in [*path.poses.values()]:  # all of it in metres now, the earlier poses too
        np.testing.assert_allclose(p.odom_from_camera, _expected(gt, int(p.name)), atol=1e-8)
    np.testing.assert_allclose(before[-1].position, _expected(gt, 9, 2.0)[:3, 3], atol=1e-8)
    assert path.poses["0009"].position_var == pytest.approx(before[-1].position_var / 4)
    # a continued window of the same map goes on in metres (its scale the window's metres)
    more = path.add(_window(gt, range(12, 20), 0.5, R2, t2, "continued", metres=2.0))
    for p in more:
        np.testing.assert_allclose(p.odom_from_camera, _expected(gt, int(p.name)), atol=1e-8)
    # and a path that began in SfM units, continued, turns metric without a jump
    cont = CameraPath()
    cont.add(_window(gt, range(0, 10), 2.0, np.eye(3), np.zeros(3), "fresh"))
    late = cont.add(_window(gt, range(6, 16), 2.0, np.eye(3), np.zeros(3), "continued",
                            metres=0.5))
    assert cont.units == "m"
    for p in [*cont.poses.values(), *late]:
        np.testing.assert_allclose(p.odom_from_camera, _expected(gt, int(p.name)), atol=1e-8)


def test_a_windows_metres_are_its_depth_outputs_factor_times_its_alignment_scale():
    from sfm_ttr_ros.core.metric.scale import WindowMetric
    from sfm_ttr_ros.core.window_io import WindowResult

    measured = WindowMetric("camera_height", metres_per_sfm_unit=2.0, metres_per_net_unit=0.5)
    # metric.learn: ŝ is the window's metres (the supervision's), the factor 1
    res = WindowResult(["a"], {}, {}, refined=True, metric=measured, scale=2.0)
    assert metres_per_sfm_unit(res, 1.0) == pytest.approx(2.0)
    assert metres_per_sfm_unit(res, None) is None  # the depth is not in metres: nor the path
    # outputs scaled: the outputs' factor (the accepted windows' median) times ŝ
    assert metres_per_sfm_unit(dataclasses.replace(res, scale=4.0), 0.6) == pytest.approx(2.4)
    # metres the window did not measure (no estimate, or not refined): the path's own scale
    assert metres_per_sfm_unit(dataclasses.replace(res, metric=WindowMetric("camera_height")),
                               1.0) is None
    assert metres_per_sfm_unit(dataclasses.replace(res, refined=False), 1.0) is None
    fixed = WindowResult(["a"], {}, {}, refined=False, metric=WindowMetric("fixed"), scale=4.0)
    assert metres_per_sfm_unit(fixed, 0.5) == pytest.approx(2.0)
    assert metres_per_sfm_unit(dataclasses.replace(fixed, scale=float("nan")), 0.5) is None


def test_the_streams_path_stamps_its_poses_from_the_frames_and_reports_their_units():
    from sfm_ttr_ros.core.metric.scale import WindowMetric
    from sfm_ttr_ros.core.sfm.result import SfmResult
    from sfm_ttr_ros.core.stream.path import StreamPath
    from sfm_ttr_ros.core.window_io import WindowResult

    gt = _drive()
    frames = [Frame(i, np.zeros((4, 4, 3), np.uint8), 0.1 * i, f"{i:04d}", header=f"h{i}")
              for i in range(20)]

    def result(idx, anchors=(), scale=2.0):
        world = {i: _world(gt[i], 1.0, np.eye(3), np.zeros(3)) for i in (*anchors, *idx)}
        sfm = SfmResult(True, "", len(idx), {f"{i:04d}": _observed(f"{i:04d}", world[i])
                                              for i in idx})
        sfm.anchors = {f"{i:04d}": _observed(f"{i:04d}", world[i]) for i in anchors}
        return WindowResult([f"{i:04d}" for i in idx], {}, {}, True, sfm=sfm, scale=scale,
                            metric=WindowMetric("camera_height", metres_per_sfm_unit=scale,
                                                metres_per_net_unit=1.0))

    path = StreamPath()
    first = path.window(frames[0:6], result(range(0, 6)), None)
    assert [(p.name, p.units, p.frame.header) for p in first[:2]] == [("0000", "sfm", "h0"),
                                                                      ("0001", "sfm", "h1")]
    assert first[0].frame.image.size == 0 and first[3].pose.stamp == pytest.approx(0.3)
    # a fresh map of frames 8-11 mapped with 4-5 (before the window: the path's stamps) joins
    # the path through them, in metres now that the depth is: 0.5 m per unit x ŝ 2
    later = path.window(frames[8:12], result(range(8, 12), anchors=(4, 5)), 0.5)
    assert [p.name for p in later] == ["0008", "0009", "0010", "0011"]
    assert {p.units for p in later} == {"m"} and {p.pose.chain for p in later} == {"shared"}
    assert path.summary()["breaks"] == 0
    np.testing.assert_allclose(later[-1].pose.odom_from_camera, _expected(gt, 11), atol=1e-8)
    assert path.window(frames[8:12], WindowResult(["0008"], {}, {}, False), 0.5) == []


@pytest.mark.slow
def test_the_path_of_a_short_generated_drive_drifts_less_than_its_metric_scale_errs():
    """Batch windows of 8 frames, stride 4, on a 20-frame generated drive (416x128, ~12.6 m):
    each window chained through its 4 shared frames, in metres from the camera height. The
    ground plane's metres per SfM unit were measured within 2.5 % of the true ones per window on
    this drive (0.458, 0.471, 0.457 against 0.463, 0.460, 0.459): an end-point drift under 5 %
    (twice that) is what the chaining may add on top; the shape alone (the scale fitted) lies
    within 1 % of the distance of the poses."""
    from conftest import tiny_model

    from sfm_ttr_ros.core.frames import Frame
    from sfm_ttr_ros.core.metric.metric_config import MetricConfig
    from sfm_ttr_ros.core.pipeline import SfmTTR, TTRConfig
    from sfm_ttr_ros.core.sfm.sfm_config import SfmConfig
    from sfm_ttr_ros.core.stream.path import StreamPath
    from sfm_ttr_ros.data.synthetic import make_sequence

    seq = make_sequence(seed=0, domain="A", num_frames=20, width=416, height=128)
    cfg = TTRConfig()
    cfg.refinement.steps = 1
    cfg.sfm = SfmConfig(mode="batch", first_octave=-1)  # batch windows, as measured
    cfg.metric = MetricConfig(source="camera_height", camera_height=seq.params.camera_height)
    ttr = SfmTTR(tiny_model(), cfg)
    frames = [Frame(index=i, image=im, stamp=s)
              for i, (im, s) in enumerate(zip(seq.images, seq.stamps, strict=True))]
    path, shape = StreamPath(), CameraPath()
    reported, shape_added = [], []
    try:
        for start in range(0, 13, 4):
            res = ttr.process_window(frames[start:start + 8], seq.intrinsics)
            reported += path.window(frames[start:start + 8], res, ttr.metres_per_unit)
            unscaled = result_poses(res, {f.name: f.stamp for f in frames})
            unscaled.metres_per_sfm_unit = None  # the same windows without metres
            shape_added += shape.add(unscaled)
    finally:
        ttr.close()
    gt = {f.name: np.linalg.inv(seq.cam_from_world[f.index]) for f in frames}
    drift = path_drift(reported, path.summary(), gt)
    drift_shape = _drift(shape, shape_added, gt)
    assert drift["units"] == "m" and drift["compared"] == 20 and drift["breaks"] == 0
    assert drift["length_m"] == pytest.approx(12.57, abs=0.1)
    assert drift["drift_pct"] < 5.0, drift
    assert drift_shape["scale_fitted"] and drift_shape["ate_rmse"] < 0.01 * 12.57, drift_shape
    _assert_odom_up_is_the_grounds(reported, seq.cam_from_world)


def _assert_odom_up_is_the_grounds(reported, cam_from_world) -> None:
    """~/odom's z against the generated world's up (y down) on a path whose windows measured
    the ground (camera_height): within 3 degrees, for a mount 8 degrees off the camera's true
    pitch; the first base pose's axes (no ground) would be the 8 degrees off."""
    from sfm_ttr_ros.core.stream.base_odometry import BaseOdometry, parse_camera_mount

    mount = parse_camera_mount("0 0 0 -98 0 -90")
    up = np.array([0.0, -1.0, 0.0])
    assert reported[0].pose.ground_up is not None  # odom is set at the first pose
    for ground in (True, False):
        odometry = BaseOdometry(mount)
        for p in reported:
            pose = p.pose if ground else dataclasses.replace(p.pose, ground_up=None)
            odom = odometry.add(pose).odom_from_base
            up_in_base = mount[:3, :3] @ cam_from_world[p.frame.index][:3, :3] @ up
            angle = math.degrees(math.acos(np.clip((odom[:3, :3] @ up_in_base)[2], -1, 1)))
            assert angle < 3.0 if ground else angle > 5.0, (p.name, ground, angle)


def test_the_benchmark_reports_the_path_only_where_the_sequence_has_poses():
    from sfm_ttr_ros.tools.benchmark.path import path_lines, path_report

    gt = _drive(12)
    path = CameraPath()
    added = _reported(path, path.add(_window(gt, range(12), 1.0, np.eye(3), np.zeros(3),
                                              metres=1.02)))
    assert path_report(added, path.summary(), None, int) == {}
    report = path_report(added, path.summary(), np.array(gt), int)
    assert report["path"]["compared"] == 12 and report["path"]["drift_pct"] > 0
    lines = path_lines({"node_online": report, "no_ttr": {}}, ["no_ttr", "node_online"])
    assert len(lines) == 6 and lines[-2].startswith("| node_online | m | 12 | 11.00 |")
    assert path_lines({"no_ttr": {}}, ["no_ttr"]) == []
