"""Affine (scale + shift) alignment of affine-invariant inverse depth."""

import numpy as np
import pytest

from sfm_ttr_ros.core.alignment.affine import (
    AffineAlignmentConfig,
    affine_targets,
    affine_to_depth,
    align_affine,
    weighted_ls_affine,
)
from sfm_ttr_ros.core.alignment.scale import AlignmentResult, align_scale
from sfm_ttr_ros.core.errors import InputError

SCALE, SHIFT = 2.6, 0.4  # network output p = SCALE / D_sfm + SHIFT


def planted(seed: int, n: int = 2000, outlier_fraction: float = 0.30, noise: float = 0.03):
    """SfM depths and a relative-inverse-depth prediction p = a/D + b with heteroscedastic noise
    (σ ∝ a/D) and a one-sided block of outliers (the network seeing things 1.6-3x closer)."""
    rng = np.random.default_rng(seed)
    d_sfm = rng.uniform(2.0, 60.0, n)
    inv = SCALE / d_sfm
    pred = inv * (1.0 + noise * rng.standard_normal(n)) + SHIFT
    out = rng.random(n) < outlier_fraction
    pred[out] = inv[out] * rng.uniform(1.6, 3.0, out.sum()) + SHIFT
    return d_sfm, pred, out


def test_recovers_scale_and_shift_exactly_on_clean_data():
    d_sfm, pred, _ = planted(0, outlier_fraction=0.0, noise=0.0)
    res = align_affine(d_sfm, pred)
    assert isinstance(res, AlignmentResult) and res.ok and res.reason == ""
    assert res.scale == pytest.approx(SCALE, rel=1e-9)
    assert res.shift == pytest.approx(SHIFT, rel=1e-9)
    assert res.ransac_inliers.all() and res.selected.all()
    np.testing.assert_allclose(affine_targets(res, d_sfm), pred, rtol=1e-9)
    np.testing.assert_allclose(affine_to_depth(res, pred), d_sfm, rtol=1e-9)


@pytest.mark.parametrize("seed", range(4))
def test_recovers_scale_and_shift_with_30_percent_outliers(seed):
    d_sfm, pred, out = planted(seed)
    assert out.mean() >= 0.28
    res = align_affine(d_sfm, pred)
    assert res.ok
    assert abs(res.scale / SCALE - 1) < 0.01
    assert abs(res.shift - SHIFT) < 0.002
    # the RANSAC inliers are true inliers, the relaxed pass selects (nearly) all true inliers
    # and none of the outliers (they are 60-200 % off, beyond relaxed_tau = 0.5)
    assert (res.ransac_inliers & out).sum() <= 0.02 * res.ransac_inliers.sum()
    assert (res.selected & ~out).sum() >= 0.99 * (~out).sum()
    assert not (res.selected & out).any()
    assert res.stats["points"] == d_sfm.size and res.stats["selected"] == res.selected.sum()


def test_a_single_rule_for_any_output_scale_and_shift():
    """Affine invariance: the same points are selected whatever the network's units."""
    d_sfm, pred, _ = planted(5)
    base = align_affine(d_sfm, pred)
    other = align_affine(d_sfm, 160.0 * pred - 3.0)
    assert np.array_equal(base.ransac_inliers, other.ransac_inliers)
    assert np.array_equal(base.selected, other.selected)
    assert other.scale == pytest.approx(160.0 * base.scale, rel=1e-9)
    assert other.shift == pytest.approx(160.0 * base.shift - 3.0, rel=1e-9)


def test_scale_only_data_agrees_with_the_papers_path():
    """Depth outputs D_nn = s·D_sfm given as p = 1/D_nn: shift ≈ 0, 1/a ≈ the paper's ŝ."""
    rng = np.random.default_rng(1)
    d_sfm = rng.uniform(0.5, 20.0, 2000)
    d_nn = 3.7 * d_sfm * (1.0 + 0.05 * rng.standard_normal(2000))
    out = rng.random(2000) < 0.35
    d_nn[out] *= rng.uniform(0.2, 0.6, out.sum())
    paper = align_scale(d_sfm, d_nn)
    res = align_affine(d_sfm, 1.0 / d_nn)
    assert abs((1.0 / res.scale) / paper.scale - 1) < 0.02
    assert abs(res.shift) < 0.01 * np.median(1.0 / d_nn)


def test_seeded_and_deterministic():
    d_sfm, pred, _ = planted(3)
    cfg = AffineAlignmentConfig(ransac_iterations=5, seed=7)
    a, b = align_affine(d_sfm, pred, cfg), align_affine(d_sfm, pred, cfg)
    assert (a.scale, a.shift, a.ransac_scale) == (b.scale, b.shift, b.ransac_scale)
    assert np.array_equal(a.selected, b.selected)
    seeds = {align_affine(d_sfm, pred, AffineAlignmentConfig(ransac_iterations=1, seed=s))
             .ransac_scale for s in range(6)}
    assert len(seeds) > 1  # the seed does drive the sampling


def test_invalid_points_are_never_used():
    d_sfm, pred, _ = planted(2, outlier_fraction=0.0, noise=0.0)
    d_sfm[:5] = [0.0, -1.0, np.nan, np.inf, 3.0]
    pred[4:8] = [0.0, -2.0, np.nan, np.inf]
    res = align_affine(d_sfm, pred)
    assert res.ok and res.scale == pytest.approx(SCALE, rel=1e-9)
    assert not res.selected[:8].any() and not res.ransac_inliers[:8].any()
    assert res.selected[8:].all() and res.stats["valid"] == d_sfm.size - 8


@pytest.mark.parametrize("d_sfm, pred, words", [
    (np.full(50, 7.0), np.linspace(0.1, 1.0, 50), "SfM depths are equal"),
    (np.linspace(2.0, 40.0, 50), np.full(50, 0.3), "constant"),
    (np.array([5.0]), np.array([0.5]), "at least 2"),
    (np.array([]), np.array([]), "at least 2"),
    (np.array([5.0, -1.0, 3.0]), np.array([0.5, 0.2, np.nan]), "at least 2"),
])
def test_degenerate_input_is_a_clear_failure(d_sfm, pred, words):
    res = align_affine(d_sfm, pred)
    assert not res.ok and words in res.reason
    assert res.selected.shape == (d_sfm.size,) and not res.selected.any()
    with pytest.raises(InputError, match="no affine fit"):
        affine_targets(res, d_sfm)


def test_decreasing_prediction_has_no_model():
    """Inverse depth that falls as SfM inverse depth grows fits no a > 0."""
    d_sfm = np.linspace(2.0, 40.0, 100)
    res = align_affine(d_sfm, 0.01 * d_sfm)
    assert not res.ok and "a > 0" in res.reason


def test_bad_arguments_raise_input_error():
    with pytest.raises(InputError, match="differ in length"):
        align_affine(np.ones(3), np.ones(4))
    with pytest.raises(InputError):
        AffineAlignmentConfig(ransac_iterations=0)
    with pytest.raises(InputError):
        AffineAlignmentConfig(tau=0.0)


def test_weighted_least_squares_closed_form():
    """The 2 x 2 closed form is the argmin of Σ (c·p·D + d·D − 1)² (checked against lstsq)."""
    rng = np.random.default_rng(4)
    d_sfm = rng.uniform(2.0, 60.0, 300)
    pred = SCALE / d_sfm * (1 + 0.1 * rng.standard_normal(300)) + SHIFT
    a, b = weighted_ls_affine(d_sfm, pred)
    design = np.stack([pred * d_sfm, d_sfm], axis=1)
    (c, d), *_ = np.linalg.lstsq(design, np.ones(300), rcond=None)
    assert a == pytest.approx(1 / c, rel=1e-9) and b == pytest.approx(-d / c, rel=1e-9)
    assert np.isnan(weighted_ls_affine(np.full(10, 4.0), np.full(10, 0.2))[0])


def test_the_affine_path_takes_its_own_ransac_iterations():
    """alignment.affine_ransac_iterations, not the one-point model's 20, runs the two-point
    RANSAC: with 1 iteration a 30 %-outlier frame is fitted from one random pair (the inlier
    count of that pair), with the default 200 from the best of many."""
    from sfm_ttr_ros.core.alignment.affine import align_output
    from sfm_ttr_ros.core.alignment.scale import AlignmentConfig

    d_sfm, pred, out = planted(3, n=400)
    kind = "relative_inverse_depth"
    default = align_output(d_sfm, pred, kind, AlignmentConfig())
    assert AlignmentConfig().affine_ransac_iterations == 200
    one = [align_output(d_sfm, pred, kind, AlignmentConfig(affine_ransac_iterations=1, seed=s))
           for s in range(5)]
    many = default.ransac_inliers.sum()
    assert all(r.ransac_inliers.sum() <= many for r in one)
    assert any(r.ransac_inliers.sum() < many for r in one)
    assert not (default.ransac_inliers & out).any()
    with pytest.raises(InputError, match="affine_ransac_iterations"):
        AlignmentConfig(affine_ransac_iterations=0)
