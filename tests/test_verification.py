"""The window checks (sfm_ttr_ros.core.checks.measures), unit by unit: the held-out
split by track, the check error, the verdict, and each sanity statistic on constructed data
whose right answer is known."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sfm_ttr_ros.core.checks.measures import (
    UNSUPPORTED_MIN_HISTORY,
    CheckConfig,
    CheckReport,
    PathReference,
    frame_scale_spread,
    frame_unsupported_change,
    probe_frames,
    reprojection_refusal,
    sanity_check,
    scale_jump,
    unsupported_change,
    unsupported_refusal,
)
from sfm_ttr_ros.core.outcomes import CHECKS, Unrefined
from sfm_ttr_ros.core.params import build, validate


def test_frame_scale_spread_finds_the_frame_with_another_scale():
    rng = np.random.default_rng(0)
    d_sfm = [rng.uniform(1, 10, 80) for _ in range(5)]
    same = [2.0 * d * rng.uniform(0.9, 1.1, 80) for d in d_sfm]  # one scale, noisy network
    assert frame_scale_spread(d_sfm, same) == pytest.approx(1.0, abs=0.03)
    bent = same[:4] + [3.0 * d_sfm[4]]  # the last frame disagrees by 1.5x
    assert frame_scale_spread(d_sfm, bent) == pytest.approx(1.5, rel=0.03)
    # invalid pairs are ignored; frames with too few valid points do not count
    holes = [np.where(np.arange(80) % 2 == 0, d, np.nan) for d in bent]
    assert frame_scale_spread(d_sfm, holes) == pytest.approx(1.5, rel=0.05)
    few = same[:4] + [np.r_[3.0 * d_sfm[4][:5], np.zeros(75)]]
    assert frame_scale_spread(d_sfm, few) == pytest.approx(1.0, abs=0.03)
    assert math.isnan(frame_scale_spread(d_sfm[:1], same[:1]))


def test_scale_jump_compares_the_shared_path():
    prev = PathReference({n: np.array([0.0, 0.0, z]) for n, z in
                          (("a", 0.0), ("b", 1.0), ("c", 2.0))})
    same = PathReference({n: c + 5.0 for n, c in prev.centres.items()})  # shifted: same path
    assert scale_jump(same, prev) == pytest.approx(1.0)
    doubled = PathReference({n: 2.0 * c for n, c in prev.centres.items()})
    assert scale_jump(doubled, prev) == pytest.approx(2.0)
    halved = PathReference({n: 0.5 * c for n, c in prev.centres.items()})
    assert scale_jump(halved, prev) == pytest.approx(2.0)
    assert math.isnan(scale_jump(PathReference({"c": np.zeros(3), "d": np.ones(3)}), prev))
    assert math.isnan(scale_jump(doubled, None))
    still = PathReference({n: np.zeros(3) for n in "abc"})
    assert math.isnan(scale_jump(still, prev))  # a static camera: nothing to compare


def test_parallax_is_the_camera_span_over_the_median_depth():
    from sfm_ttr_ros.core.checks.measures import parallax
    from sfm_ttr_ros.core.sfm.result import FrameObservations, SfmResult

    def frame(z: float, depths: np.ndarray) -> FrameObservations:
        T = np.eye(4)
        T[2, 3] = -z  # camera centre at (0, 0, z)
        n = depths.size
        return FrameObservations(f"{z}", np.zeros((n, 2), np.float32), depths, np.zeros(n),
                                 np.zeros(n), np.arange(n), T)

    depths = np.array([10.0, 20.0, 30.0])
    sfm = SfmResult(True, "", 3, frames={"a": frame(0.0, depths), "b": frame(1.0, depths),
                                         "c": frame(4.0, depths)})
    assert parallax(sfm, ["a", "b", "c"]) == pytest.approx(4.0 / 20.0)
    assert parallax(sfm, ["a", "b"]) == pytest.approx(1.0 / 20.0)
    assert math.isnan(parallax(sfm, ["a"]))
    c = sanity_check(CheckConfig(min_parallax=0.1), CheckReport(parallax=0.05))
    assert c.reason_key is Unrefined.CHECK_PARALLAX and "0.05" in c.reason


def test_sanity_check_names_the_first_failing_check_and_skips_what_is_off():
    stats = dict(reprojection_error=2.5, parallax=0.05, track_length=2.1, inlier_ratio=0.3,
                 scale_spread=1.9, scale_jump=1.5)
    off = sanity_check(CheckConfig(max_reprojection_error=0.0, min_parallax=0.0,
                                   max_scale_jump=0.0), CheckReport(**stats))
    assert off.reason_key is None
    c = sanity_check(CheckConfig(max_reprojection_error=2.0, min_parallax=0.1,
                                 max_scale_jump=1.2), CheckReport(**stats))
    assert c.reason_key is Unrefined.CHECK_REPROJECTION and "2.5 px > " in c.reason
    c = sanity_check(CheckConfig(max_reprojection_error=0.0, max_scale_jump=1.2),
                     CheckReport(**stats))
    assert c.reason_key is Unrefined.CHECK_PARALLAX
    c = sanity_check(CheckConfig(min_parallax=0.0, max_scale_jump=1.2), CheckReport(**{
        **stats, "reprojection_error": 0.5}))
    assert c.reason_key is Unrefined.CHECK_SCALE_JUMP and c.reason_key in CHECKS
    c = sanity_check(CheckConfig(max_scale_jump=1.2), CheckReport(scale_jump=float("nan")))
    assert c.reason_key is None  # NaN: no shared frames, nothing to judge
    # the statistics without a threshold are still measured and reported
    assert {"track_length", "inlier_ratio", "scale_spread"} <= set(CheckReport(**stats).summary())


def test_check_parameters_reach_the_config_and_bad_ones_are_refused():
    cfg = build({"check.min_parallax": 0.3, "check.max_scale_jump": 1.8}).ttr.check
    assert (cfg.min_parallax, cfg.max_scale_jump) == (0.3, 1.8)
    assert "factor >= 1" in validate({"check.max_scale_jump": 0.5})
    assert validate({"check.min_parallax": -0.1})


def _grid_points(h: int, w: int, hole: tuple[slice, slice], spacing: int = 8) -> np.ndarray:
    """SfM observations every ``spacing`` px over an h x w frame, none inside ``hole``."""
    ys, xs = np.mgrid[0:h:spacing, 0:w:spacing]
    px = np.c_[xs.ravel(), ys.ravel()].astype(np.float64)
    inside = ((px[:, 1] >= hole[0].start) & (px[:, 1] < hole[0].stop)
              & (px[:, 0] >= hole[1].start) & (px[:, 0] < hole[1].stop))
    return px[~inside]


def test_unsupported_change_sees_a_region_without_points_move_and_nothing_else():
    h, w = 200, 400
    rng = np.random.default_rng(0)
    before = rng.uniform(2, 30, (h, w))
    hole = (slice(60, 180), slice(120, 280))  # no SfM point in here (a vehicle moving along)
    px = _grid_points(h, w, hole)
    # a global scale change is no error: the depth is up to scale
    assert frame_unsupported_change(before, 3.0 * before, px, step=1) == 0.0
    # the region without points pushed 2x away: its pixels farther than 5 % of the width
    # (20 px) from every point count, nothing else
    after = before.copy()
    after[hole] *= 2.0
    got = frame_unsupported_change(before, after, px, step=1)
    yy, xx = np.mgrid[0:h, 0:w]
    interior = ((yy >= 60 + 20) & (yy < 180) & (xx >= 120 + 20) & (xx < 280 - 20))
    assert got == pytest.approx(interior.mean(), rel=0.1) and got > 0.05
    # ... and by less than the factor τ = 1.5: nothing
    after[hole] = before[hole] * 1.4
    assert frame_unsupported_change(before, after, px, step=1) == 0.0
    # a supported region (points in it) that moves is refinement doing its job
    after = before.copy()
    after[:60, :120] *= 2.0
    assert frame_unsupported_change(before, after, px, step=1) == 0.0
    # the sampled version (every 4th pixel, the default) agrees
    after = before.copy()
    after[hole] *= 2.0
    assert frame_unsupported_change(before, after, px) == pytest.approx(got, abs=0.02)
    # nothing to measure
    assert math.isnan(frame_unsupported_change(before, after, np.zeros((0, 2))))
    assert math.isnan(frame_unsupported_change(before, np.full_like(before, np.nan), px))


def test_window_unsupported_change_is_the_mean_over_frames_and_its_verdict():
    h, w = 100, 200
    before = {n: np.full((h, w), 10.0) for n in "ab"}
    after = {"a": before["a"] * 1.5, "b": before["b"].copy()}
    after["b"][:, 100:] = 30.0  # the right half of frame b tripled, no point there
    px = np.c_[np.arange(0, 100, 5), np.full(20, 50.0)]
    u = unsupported_change(before, after, {"a": px, "b": px, "missing": px})
    share_b = frame_unsupported_change(before["b"], after["b"], px)
    assert 0.3 < share_b < 0.5 and u == pytest.approx(share_b / 2)
    def absolute(threshold: float) -> CheckConfig:  # the threshold alone: no stream ratio
        return CheckConfig(max_unsupported_change=threshold, unsupported_change_ratio=0.0)

    assert unsupported_refusal(absolute(0.1), u).startswith(f"{u:.3g} of the pixels moved")
    assert unsupported_refusal(absolute(0.5), u) == ""
    assert unsupported_refusal(absolute(0.0), u) == ""  # 0 = off
    assert unsupported_refusal(absolute(0.1), float("nan")) == ""
    assert Unrefined.CHECK_UNSUPPORTED_CHANGE in CHECKS
    assert validate({"check.max_unsupported_change": 1.5})


def test_the_unsupported_change_ratio_judges_a_window_against_the_streams_accepted_ones():
    cfg = CheckConfig(max_unsupported_change=0.025, unsupported_change_ratio=5.0)
    driving = [0.002, 0.001, 0.0007, 0.009]  # median 0.0015: a truck's 0.056 stands out
    assert "unsupported_change_ratio 5 x 0.0015" in unsupported_refusal(cfg, 0.056, driving)
    assert unsupported_refusal(cfg, 0.02, driving) == ""  # under the absolute floor
    indoor = [0.36, 0.18, 0.32]  # walls move far from every point on every window
    assert unsupported_refusal(cfg, 0.3, indoor) == ""
    assert unsupported_refusal(cfg, 1.0, indoor) == ""  # 1.0 <= 5 x 0.32
    assert unsupported_refusal(cfg, 0.5, []) == ""  # no accepted window yet: no reference
    assert unsupported_refusal(cfg, 0.5, [float("nan")]) == ""
    # one or two accepted windows are no reference yet (the demo drive's second window)
    assert UNSUPPORTED_MIN_HISTORY == 3
    assert unsupported_refusal(cfg, 0.046, [0.0046]) == ""
    assert unsupported_refusal(cfg, 0.046, [0.0046, 0.005, float("nan")]) == ""
    assert "the last 3 accepted" in unsupported_refusal(cfg, 0.046, [0.0046, 0.005, 0.004])
    plain = CheckConfig(max_unsupported_change=0.025, unsupported_change_ratio=0.0)  # absolute
    assert unsupported_refusal(plain, 0.3, indoor) and unsupported_refusal(plain, 0.05, [])
    assert validate({"check.unsupported_change_ratio": 0.5})  # a factor >= 1 or 0
    assert not validate({"check.unsupported_change_ratio": 5.0})
    assert cfg.after_refinement and not CheckConfig(max_unsupported_change=0.0).after_refinement
    # the defaults are the real-footage check: 0.025, judged against the stream's windows
    assert (CheckConfig().max_unsupported_change, CheckConfig().unsupported_change_ratio) == (
        0.025, 5.0)


def test_the_reprojection_ratio_judges_a_window_against_the_streams_accepted_ones():
    cfg = CheckConfig(max_reprojection_ratio=1.25)
    right = [0.70, 0.65]  # hololens_000's first two windows; its frames 30-44 came out at 0.89
    assert "1.25 x 0.675 px (the median of the last 2 accepted" in reprojection_refusal(
        cfg, 0.89, right)
    assert reprojection_refusal(cfg, 0.84, right) == ""  # 1.24x: within the factor
    assert reprojection_refusal(cfg, 0.89, [0.70]) == ""  # one window is no reference yet
    assert reprojection_refusal(cfg, 0.89, [0.70, float("nan")]) == ""
    assert reprojection_refusal(cfg, float("nan"), right) == ""
    assert reprojection_refusal(CheckConfig(max_reprojection_ratio=0.0), 5.0, right) == ""
    assert validate({"check.max_reprojection_ratio": 0.5})  # a factor >= 1 or 0
    assert not validate({"check.max_reprojection_ratio": 1.25})
    assert build({}).ttr.check.max_reprojection_ratio == 1.25  # the node's default


def test_a_window_is_judged_against_the_reprojection_errors_of_accepted_windows_only():
    from sfm_ttr_ros.core.alignment.scale import AlignmentResult
    from sfm_ttr_ros.core.checks.judge import WindowJudge
    from sfm_ttr_ros.core.sfm.result import FrameObservations, SfmResult

    checks, cfg = WindowJudge(), CheckConfig(max_reprojection_ratio=1.25)
    empty = np.zeros(0)
    align = AlignmentResult(1.0, empty.astype(bool), empty.astype(bool))

    def window(error: float) -> CheckReport:
        n = 5
        obs = FrameObservations("a", np.zeros((n, 2)), np.full(n, 10.0), np.full(n, error),
                                np.full(n, error), np.arange(n), np.eye(4))
        sfm = SfmResult(True, "", 1, frames={"a": obs})
        checks.begin_window()
        return checks.before_refining(cfg, sfm, ["a"], empty, empty, align, scaled=False)

    for error in (0.70, 0.65):
        c = window(error)
        assert c.reason_key is None and c.reprojection_error == pytest.approx(error)
        checks.accept(c, SfmResult(True, "", 1), [], 1.0, scaled=False)
    wrong = window(0.92)
    assert wrong.reason_key == "check_reprojection" and "0.675 px" in wrong.reason
    # a refused window is no reference: the next is judged against the accepted two
    assert window(0.88).reason_key == "check_reprojection"
    assert window(0.80).reason_key is None


def test_interim_weights_are_checked_on_frames_spread_over_the_window():
    names = [f"{i:02d}" for i in range(15)]
    assert probe_frames(names) == ["03", "11"]  # the centres of the window's two halves
    assert probe_frames(names, 3) == ["02", "07", "12"] and probe_frames(names, 1) == ["07"]
    assert probe_frames(names[:1]) == ["00"] and probe_frames([]) == []
