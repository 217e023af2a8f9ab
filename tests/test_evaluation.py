"""KITTI evaluation protocol (Monodepth2): hand-computed checks."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.evaluation import (
    EIGEN_CROP,
    MAX_DEPTH,
    METRICS,
    MIN_DEPTH,
    EvalConfig,
    Evaluator,
    compute_errors,
    eigen_crop_bounds,
    evaluate_folders,
    evaluate_frame,
    format_table,
    means_by_part,
    relative_gain,
    scaled_prediction,
    valid_mask,
)


def test_constants():
    assert EIGEN_CROP == (0.40810811, 0.99189189, 0.03594771, 0.96405229)
    assert MIN_DEPTH == 1e-3 and MAX_DEPTH == 80.0
    cfg = EvalConfig()
    assert (cfg.min_depth, cfg.max_depth, cfg.eigen_crop, cfg.median_scaling) == (
        1e-3,
        80.0,
        False,
        True,
    )


def test_compute_errors_by_hand():
    # gt=[1,2,4], pred=[1,1,8]: diff = [0, 1, -4], gt/pred ratios = [1, 2, 2]
    e = compute_errors(np.array([1.0, 2.0, 4.0]), np.array([1.0, 1.0, 8.0]))
    assert e["abs_rel"] == pytest.approx((0 + 1 / 2 + 4 / 4) / 3)  # 0.5
    assert e["sq_rel"] == pytest.approx((0 + 1 / 2 + 16 / 4) / 3)  # 1.5
    assert e["rmse"] == pytest.approx(math.sqrt((0 + 1 + 16) / 3))
    # log differences: [0, ln 2, -ln 2]
    assert e["rmse_log"] == pytest.approx(math.log(2) * math.sqrt(2 / 3))
    # max ratio 1 < 1.25; 2 > 1.25**3 = 1.953125
    assert e["a1"] == pytest.approx(1 / 3)
    assert e["a2"] == pytest.approx(1 / 3)
    assert e["a3"] == pytest.approx(1 / 3)
    assert set(e) == {"abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3"}


def test_compute_errors_delta_thresholds():
    # ratios 1.2 < 1.25; 1.5 < 1.5625; 1.9 < 1.953125; 3 above all
    e = compute_errors(np.ones(4), np.array([1.2, 1.5, 1.9, 3.0]))
    assert (e["a1"], e["a2"], e["a3"]) == (0.25, 0.5, 0.75)
    # symmetric: under-estimation by the same ratio counts the same
    e2 = compute_errors(np.array([1.2, 1.5, 1.9, 3.0]), np.ones(4))
    assert (e2["a1"], e2["a2"], e2["a3"]) == (0.25, 0.5, 0.75)


def test_compute_errors_rejects_bad_input():
    with pytest.raises(InputError):
        compute_errors(np.ones(3), np.ones(2))
    with pytest.raises(InputError):
        compute_errors(np.array([]), np.array([]))
    with pytest.raises(InputError):
        compute_errors(np.ones(2), np.array([1.0, 0.0]))


def test_eigen_crop_indices_match_monodepth2():
    # 0.40810811*375 = 153.04, 0.99189189*375 = 371.96, 0.03594771*1242 = 44.65,
    # 0.96405229*1242 = 1197.35 -> truncated by astype(np.int32)
    assert eigen_crop_bounds(375, 1242) == (153, 371, 44, 1197)
    gt = np.full((375, 1242), 10.0)
    m = valid_mask(gt, EvalConfig(eigen_crop=True))
    rows = np.flatnonzero(m.any(axis=1))
    cols = np.flatnonzero(m.any(axis=0))
    assert (rows[0], rows[-1], cols[0], cols[-1]) == (153, 370, 44, 1196)
    assert m.sum() == (371 - 153) * (1197 - 44)
    assert valid_mask(gt, EvalConfig(eigen_crop=False)).all()


def test_depth_range_excludes_80m_and_min():
    gt = np.array([[0.0, 1e-3, 0.5, 79.9, 80.0, 100.0]])
    assert valid_mask(gt).tolist() == [[False, False, True, True, False, False]]
    # a far-away GT pixel with a wildly wrong prediction does not change the result
    pred = np.array([[5.0, 5.0, 0.5, 79.9, 1.0, 1.0]])
    r = evaluate_frame(pred, gt, EvalConfig(median_scaling=False))
    assert r.num_pixels == 2 and r.metrics["abs_rel"] == pytest.approx(0.0)


def test_median_scaling_makes_scaled_prediction_perfect():
    rng = np.random.default_rng(0)
    gt = rng.uniform(2.0, 30.0, size=(20, 30))
    gt[rng.random(gt.shape) < 0.5] = 0.0  # sparse LiDAR-like GT
    pred = gt * 0.25 + (gt == 0) * 7.0  # scale-less prediction, defined everywhere
    r = evaluate_frame(pred, gt)
    assert r.ratio == pytest.approx(4.0)
    assert r.metrics["abs_rel"] == pytest.approx(0.0, abs=1e-12)
    assert r.metrics["rmse"] == pytest.approx(0.0, abs=1e-9)
    assert r.metrics["a1"] == 1.0
    # without scaling: |gt - gt/4| / gt = 0.75 everywhere, every ratio is 4 > 1.25**3
    r2 = evaluate_frame(pred, gt, EvalConfig(median_scaling=False))
    assert r2.ratio == pytest.approx(4.0)  # measured (the scale's spread), not applied
    assert r2.metrics["abs_rel"] == pytest.approx(0.75)
    assert r2.metrics["a3"] == 0.0


def test_prediction_clamped_after_scaling():
    gt = np.array([[10.0, 10.0, 10.0]])
    pred = np.array([[10.0, 200.0, -1.0]])  # too far and negative: clamped to [1e-3, 80]
    r = evaluate_frame(pred, gt, EvalConfig(median_scaling=False))
    expected = compute_errors(np.full(3, 10.0), np.array([10.0, 80.0, 1e-3]))
    assert r.metrics == pytest.approx(expected)


def test_non_finite_prediction_excluded_and_counted():
    gt = np.array([[1.0, 2.0, 4.0, 0.0]])
    pred = np.array([[1.0, np.nan, 8.0, np.inf]])  # the inf sits on a pixel without GT
    ev = Evaluator(EvalConfig(median_scaling=False))
    r = ev.add("f", pred, gt)
    assert r.invalid_pred == 1 and r.num_pixels == 2
    assert r.metrics["abs_rel"] == pytest.approx((0 + 1) / 2)
    assert ev.summary()["invalid_pred"] == 1
    # nothing finite left: skipped, with the reason
    assert ev.add("g", np.full((1, 4), np.nan), gt) is None
    assert ev.summary()["skipped_frames"] == {"g": "no_finite_pred"}


def test_prediction_resized_to_gt_size():
    gt = np.full((20, 40), 10.0)
    pred_small = np.tile(np.linspace(5.0, 15.0, 20), (10, 1))  # 10 x 20, column gradient
    cfg = EvalConfig(median_scaling=False)
    r = evaluate_frame(pred_small, gt, cfg)
    assert r.num_pixels == 20 * 40
    resized = cv2.resize(pred_small, (40, 20), interpolation=cv2.INTER_LINEAR)
    expected = compute_errors(gt.ravel(), resized.ravel())
    assert r.metrics == pytest.approx(expected)
    # constant prediction at half the GT depth: abs rel 0.5 at every resized pixel
    r2 = evaluate_frame(np.full((10, 20), 5.0), gt, cfg)
    assert r2.metrics["abs_rel"] == pytest.approx(0.5)


def test_empty_gt_frame_is_skipped_and_counted():
    assert evaluate_frame(np.ones((4, 4)), np.zeros((4, 4))) is None
    ev = Evaluator()
    assert ev.add("empty", np.ones((4, 4)), np.zeros((4, 4))) is None
    ev.add("ok", np.full((4, 4), 2.0), np.full((4, 4), 4.0))
    s = ev.summary()
    assert s["frames"] == 1 and s["skipped"] == 1
    assert s["skipped_frames"] == {"empty": "no_valid_gt"}
    assert s["abs_rel"] == pytest.approx(0.0)


def test_bad_shapes_raise_input_error():
    with pytest.raises(InputError):
        evaluate_frame(np.ones((2, 3, 3)), np.ones((2, 3)))
    with pytest.raises(InputError):
        evaluate_frame(np.ones((2, 3)), np.ones(6))
    with pytest.raises(InputError):
        EvalConfig(min_depth=10.0, max_depth=1.0)


def test_evaluator_averages_per_frame_not_per_pixel():
    ev = Evaluator(EvalConfig(median_scaling=False))
    # frame A: 16 valid pixels, perfect -> abs rel 0
    ev.add("a", np.full((4, 4), 10.0), np.full((4, 4), 10.0))
    # frame B: 1 valid pixel, prediction twice the GT -> abs rel 1
    gt_b = np.zeros((4, 4))
    gt_b[1, 2] = 10.0
    ev.add("b", np.full((4, 4), 20.0), gt_b)
    s = ev.summary()
    assert s["frames"] == 2 and s["skipped"] == 0
    assert s["abs_rel"] == pytest.approx(0.5)  # per pixel it would be 1/17
    assert s["rmse"] == pytest.approx(5.0)  # (0 + 10) / 2
    assert s["a1"] == pytest.approx(0.5)
    assert [f["name"] for f in s["per_frame"]] == ["a", "b"]
    assert [f["pixels"] for f in s["per_frame"]] == [16, 1]


def test_scaling_ratio_statistics():
    ev = Evaluator()
    gt = np.full((3, 3), 12.0)
    for i, s in enumerate((2.0, 4.0, 8.0)):
        ev.add(str(i), gt / s, gt)  # ratios 2, 4, 8
    s = ev.summary()
    assert s["ratio_median"] == pytest.approx(4.0)
    assert s["ratio_std"] == pytest.approx(np.std([0.5, 1.0, 2.0]))
    assert Evaluator(EvalConfig(median_scaling=False)).summary()["ratio_median"] is None


def test_summary_without_frames_is_nan():
    s = Evaluator().summary()
    assert s["frames"] == 0 and math.isnan(s["abs_rel"])


def _write_gt(path, depth, scale=256.0):
    assert cv2.imwrite(str(path), np.round(depth * scale).astype(np.uint16))


def test_evaluate_folders_round_trip(tmp_path):
    gt_dir, pred_dir = tmp_path / "gt", tmp_path / "pred"
    gt_dir.mkdir()
    pred_dir.mkdir()
    rng = np.random.default_rng(1)
    gts = {}
    for name in ("000", "001", "002"):
        depth = np.round(rng.uniform(2.0, 60.0, size=(12, 16)) * 256) / 256
        depth[rng.random(depth.shape) < 0.3] = 0.0
        gts[name] = depth
        _write_gt(gt_dir / f"{name}.png", depth)
    # predictions (scale-less, x0.1) for 000 and 001 only, plus one without GT
    for name in ("000", "001"):
        np.save(pred_dir / f"{name}.npy", np.where(gts[name] > 0, gts[name] * 0.1, 1.0))
    np.save(pred_dir / "999.npy", np.ones((12, 16)))

    back = cv2.imread(str(gt_dir / "000.png"), cv2.IMREAD_UNCHANGED)
    assert back.dtype == np.uint16 and np.allclose(back / 256.0, gts["000"])

    s = evaluate_folders(pred_dir, gt_dir)
    assert s["frames"] == 2 and s["skipped"] == 0
    assert s["missing_pred"] == 1 and s["missing_pred_names"] == ["002"]
    assert s["missing_gt"] == 1 and s["missing_gt_names"] == ["999"]
    assert s["abs_rel"] == pytest.approx(0.0, abs=1e-9)
    assert s["a1"] == 1.0
    assert s["ratio_median"] == pytest.approx(10.0)

    # 16-bit PNG predictions (metric, half the GT depth), no median scaling
    png_dir = tmp_path / "pred_png"
    png_dir.mkdir()
    for name in ("000", "001", "002"):
        _write_gt(png_dir / f"{name}.png", gts[name] / 2)
    s2 = evaluate_folders(
        png_dir, gt_dir, pred_format="png", config=EvalConfig(median_scaling=False)
    )
    assert s2["frames"] == 3 and s2["missing_pred"] == 0 and s2["missing_gt"] == 0
    assert s2["abs_rel"] == pytest.approx(0.5, abs=1e-3)


def test_evaluate_folders_missing_folder(tmp_path):
    (tmp_path / "gt").mkdir()
    with pytest.raises(InputError, match="does not exist"):
        evaluate_folders(tmp_path / "nope", tmp_path / "gt")
    with pytest.raises(InputError, match="does not exist"):
        evaluate_folders(tmp_path / "gt", tmp_path / "nope")
    with pytest.raises(InputError, match="no ground-truth PNG"):
        evaluate_folders(tmp_path / "gt", tmp_path / "gt")
    with pytest.raises(InputError, match="pred_format"):
        _write_gt(tmp_path / "gt" / "a.png", np.ones((2, 2)))
        evaluate_folders(tmp_path / "gt", tmp_path / "gt", pred_format="jpg")


def test_format_table_and_relative_gain():
    before = {
        "abs_rel": 0.071,
        "sq_rel": 0.3,
        "rmse": 3.23,
        "rmse_log": 0.1,
        "a1": 0.9,
        "a2": 0.97,
        "a3": 0.99,
        "frames": 652,
    }
    after = {
        "abs_rel": 0.056,
        "sq_rel": 0.2,
        "rmse": 2.60,
        "rmse_log": 0.08,
        "a1": 0.95,
        "a2": 0.98,
        "a3": 0.99,
        "frames": 652,
    }
    table = format_table({"no_ttr": before, "sfm_ttr": after})
    lines = table.strip().splitlines()
    assert lines[0] == "| method | abs_rel | sq_rel | rmse | rmse_log | a1 | a2 | a3 | frames |"
    assert lines[2] == "| no_ttr | 0.071 | 0.300 | 3.230 | 0.100 | 0.900 | 0.970 | 0.990 | 652 |"
    assert lines[3].startswith("| sfm_ttr | 0.056 | 0.200 | 2.600 |")
    assert "0.0710" in format_table({"x": before}, decimals=4)
    g = relative_gain(before, after)
    assert g["abs_rel"] == pytest.approx((0.071 - 0.056) / 0.071)
    assert g["rmse"] == pytest.approx((3.23 - 2.60) / 3.23)
    assert g["a1"] == pytest.approx((0.95 - 0.9) / 0.9)
    assert g["a3"] == pytest.approx(0.0)
    assert "frames" not in g


def test_nan_in_low_resolution_prediction_stays_invalid_after_resize():
    gt = np.full((4, 4), 10.0)
    pred = np.array([[10.0, np.nan], [10.0, 10.0]])
    r = evaluate_frame(pred, gt, EvalConfig(median_scaling=False))
    assert r.invalid_pred > 0 and r.num_pixels == 16 - r.invalid_pred
    assert all(math.isfinite(v) for v in r.metrics.values())
    assert r.metrics["abs_rel"] == pytest.approx(0.0)  # NaN did not leak into its neighbours


def test_relative_inverse_depth_is_fitted_in_disparity_per_frame():
    rng = np.random.default_rng(0)
    gt = rng.uniform(2.0, 60.0, (24, 40))
    pred = 0.37 / gt + 0.05  # affine-invariant inverse depth: right up to scale and shift
    cfg = EvalConfig(prediction="relative_inverse_depth")
    exact = evaluate_frame(pred, gt, cfg)
    assert exact.metrics["abs_rel"] == pytest.approx(0.0, abs=1e-9) and exact.ratio is None
    # read as depth (median scaling), the same map is badly wrong: the shift bends it
    assert evaluate_frame(pred, gt).metrics["abs_rel"] > 0.5
    # a sky-like region pushed past infinity by the fit is clamped to max_depth, not lost
    noisy = pred.copy()
    noisy[:2] = 0.0
    r = evaluate_frame(noisy, gt, cfg)
    assert r is not None and r.num_pixels == gt.size and r.metrics["abs_rel"] > 0
    flat = Evaluator(cfg)
    assert flat.add("flat", np.full_like(gt, 0.3), gt) is None
    assert flat.summary()["skipped_frames"] == {"flat": "no_affine_fit"}
    with pytest.raises(InputError, match="prediction must be one of"):
        EvalConfig(prediction="disparity")


def test_means_by_part_cuts_the_frames_in_order_into_nearly_equal_parts():
    rows = [{m: float(k) for m in METRICS} for k in range(7)]
    parts = means_by_part(rows, 3)
    assert [p["frames"] for p in parts] == [2, 2, 3]
    assert [p["abs_rel"] for p in parts] == [0.5, 2.5, 5.0]
    assert [p["frames"] for p in means_by_part(rows[:2], 3)] == [1, 1]  # one part per row
    with pytest.raises(ValueError):
        means_by_part(rows, 0)


def _protocol_written_out(pred, gt, cfg):
    """Monodepth2's protocol step by step on 1-D arrays, as ``_evaluate`` computed it before it
    took the prediction from :func:`scaled_prediction`: (metrics, ratio, pixels, invalid) or
    None for a skipped frame."""
    gt, pred = np.asarray(gt, np.float64), np.asarray(pred, np.float64)
    if pred.shape != gt.shape:
        bad = ~np.isfinite(pred)
        h, w = gt.shape
        pred = cv2.resize(np.where(bad, 0.0, pred), (w, h), interpolation=cv2.INTER_LINEAR)
        if bad.any():
            pred[cv2.resize(bad.astype(np.float32), (w, h)) > 0] = np.nan
    mask = valid_mask(gt, cfg)
    gt_v, pred_v = gt[mask], pred[mask]
    finite = np.isfinite(pred_v)
    gt_v, pred_v = gt_v[finite], pred_v[finite]
    if not gt_v.size:
        return None
    ratio = None
    if cfg.prediction == "relative_inverse_depth":
        from sfm_ttr_ros.core.evaluation import inverse_affine_to_depth

        pred_v = inverse_affine_to_depth(pred_v, gt_v, cfg.max_depth)
        if pred_v is None:
            return None
    else:
        if float(np.median(pred_v)) > 0:
            ratio = float(np.median(gt_v)) / float(np.median(pred_v))
        if cfg.median_scaling:
            if ratio is None:
                return None
            pred_v = pred_v * ratio
    pred_v = np.clip(pred_v, cfg.min_depth, cfg.max_depth)
    return compute_errors(gt_v, pred_v), ratio, gt_v.size, int(np.count_nonzero(~finite))


def test_the_metrics_are_the_protocol_written_out_bit_for_bit():
    """The headline metrics come from :func:`scaled_prediction` and are exactly (``==``, not
    approximately) the protocol computed step by step, on frames with NaN, inf, negative and
    out-of-range predictions, of another size than the GT, for every prediction kind."""
    rng = np.random.default_rng(7)
    evaluated = 0
    for _ in range(300):
        h, w = (int(v) for v in rng.integers(4, 30, 2))
        gt = rng.uniform(-5.0, 100.0, (h, w))
        gt[rng.random((h, w)) < 0.3] = 0.0
        shape = tuple(int(v) for v in rng.integers(3, 40, 2)) if rng.random() < 0.5 else (h, w)
        inverse = rng.random() < 0.3
        pred = rng.uniform(0.01, 1.0, shape) if inverse else rng.uniform(-2.0, 90.0, shape)
        for v in (np.nan, np.inf, -np.inf, -3.0, 0.0, 1e4):
            pred[rng.random(shape) < 0.05] = v
        cfg = EvalConfig(eigen_crop=bool(rng.integers(2)), median_scaling=bool(rng.integers(2)),
                         prediction="relative_inverse_depth" if inverse else "depth")
        want = _protocol_written_out(pred, gt, cfg)
        got = evaluate_frame(pred, gt, cfg)
        assert (got is None) == (want is None)
        if got is not None:
            evaluated += 1
            assert (got.metrics, got.ratio, got.num_pixels, got.invalid_pred) == want
            scaled = scaled_prediction(pred, gt, cfg)
            assert scaled.skip is None and scaled.depth.shape == gt.shape
            assert compute_errors(*scaled.values()) == got.metrics
    assert evaluated > 150


def test_scaled_prediction_keeps_non_finite_predictions_out_of_range_clamping():
    """+-inf is "no prediction" (NaN, left out and counted), never clamped into the depth
    range; negative and too-far depths are clamped after scaling; the frame's skip reason is
    the evaluator's."""
    gt = np.full((2, 3), 10.0)
    pred = np.array([[np.inf, -np.inf, np.nan], [-1.0, 5.0, 1e6]])
    s = scaled_prediction(pred, gt, EvalConfig(median_scaling=False))
    assert s.skip is None and s.invalid_pred == 3 and s.ratio == 2.0  # measured, not applied
    assert s.pixels.tolist() == [[False, False, False], [True, True, True]]
    assert np.isnan(s.depth[0]).all() and s.depth[1].tolist() == [MIN_DEPTH, 5.0, MAX_DEPTH]
    assert scaled_prediction(pred, np.zeros((2, 3))).skip == "no_valid_gt"
    assert scaled_prediction(np.full((2, 3), np.nan), gt).skip == "no_finite_pred"
    assert scaled_prediction(-np.ones((2, 3)), gt).skip == "nonpositive_median_pred"
