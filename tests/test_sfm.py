"""Stage 1, sparse SfM with pycolmap: accuracy against exact ground truth (generated street and
the real hololens_000 video), what a result holds, the feature cache across windows, and
windows that cannot be reconstructed.

Depth error = median over all observations of |s·D_sfm − D_gt| / D_gt after ONE scale
s = median(D_gt / D_sfm) for the whole window (a reconstruction has its own arbitrary scale).
"""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pycolmap
import pytest
from conftest import open_hololens
from helpers import reconstruct_window

from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.sfm.names import frame_name
from sfm_ttr_ros.core.sfm.reconstruction import (
    SfmConfig,
    SfmReconstructor,
    SfmResult,
)

# 640 x 192 is the smallest size that registered every window we tried: at 416 x 128 seed 1
# "succeeded" with a wrong reconstruction (camera path 32 degrees off, depth error 33 %),
# while at 640 x 192 seeds 0-5 all gave 0.5-1.0 % depth error.
W, H = 640, 192


def depth_errors(result: SfmResult, frames: list[Frame], gt: dict[str, np.ndarray]):
    """(relative errors after one median scale, the scale, fraction of observations with GT)."""
    d_sfm, d_gt = [], []
    for f in frames:
        obs = result.frames.get(f.name)
        if obs is None:
            continue
        px = np.rint(obs.pixels).astype(int)  # pixel centres at integers (OpenCV convention)
        g = gt[f.name][px[:, 1], px[:, 0]]
        d_sfm.append(obs.depths[g > 0])
        d_gt.append(g[g > 0])
    d_sfm, d_gt = np.concatenate(d_sfm), np.concatenate(d_gt)
    total = sum(len(o) for o in result.frames.values())
    s = float(np.median(d_gt / d_sfm))
    return np.abs(s * d_sfm - d_gt) / d_gt, s, d_gt.size / total


@pytest.fixture(scope="module")
def street():
    from sfm_ttr_ros.data.synthetic import make_sequence

    seq = make_sequence(seed=0, domain="A", num_frames=12, width=W, height=H)
    frames = [Frame(i, im, stamp=s) for i, (im, s) in
              enumerate(zip(seq.images, seq.stamps, strict=True))]
    gt = {f.name: seq.depths[f.index] for f in frames}
    return SimpleNamespace(seq=seq, frames=frames, gt=gt, intr=seq.intrinsics)


@pytest.fixture(scope="module")
def windows(street):
    """Windows through ONE reconstructor (its default options), extraction spied on: frames
    0-9; the same again with ``refine_intrinsics`` on (cached features: mapping only); frames
    4-11 (overlap 4-9); then 6 frames whose names were used before but whose pixels are other
    frames' (frames 2-7 renamed 0-5: a second sequence named by index)."""
    extracted: list[list[str]] = []
    real = pycolmap.extract_features

    def spy(*args, image_names=None, **kwargs):
        extracted.append([frame_name(n) for n in image_names])
        return real(*args, image_names=image_names, **kwargs)

    f = street.frames
    renamed = [Frame(i, f[i + 2].image, name=f[i].name) for i in range(6)]
    out = SimpleNamespace(extracted=extracted, counts=[], renamed=renamed)
    with pytest.MonkeyPatch.context() as mp, SfmReconstructor() as rec:
        mp.setattr(pycolmap, "extract_features", spy)
        out.first = rec.reconstruct(f[0:10], street.intr)
        out.counts.append(rec.frames_extracted)
        # free focal lengths: the mapper now and then collapses this forward window to a few
        # points (1 run in 10-20, whatever sfm.overlap); more seeds, as the mapper's retry rule
        default = rec.config
        rec.config = replace(default, refine_intrinsics=True, mapping_attempts=4)
        out.free_focal = rec.reconstruct(f[0:10], street.intr)
        rec.config = default
        out.counts.append(rec.frames_extracted)
        out.second = rec.reconstruct(f[4:12], street.intr)
        out.counts.append(rec.frames_extracted)
        out.third = rec.reconstruct(renamed, street.intr)
        out.counts.append(rec.frames_extracted)
    return out


@pytest.mark.slow
def test_registers_the_window_and_depths_match_exact_ground_truth(street, windows):
    res = windows.first
    assert res.ok and res.reason == "" and res.num_frames == 10
    assert res.num_registered >= 9  # >= 90 % of the frames
    rel, scale, with_gt = depth_errors(res, street.frames[:10], street.gt)
    # Measured: 10/10 registered, 1463 points, 7855 observations, median error 0.80 %
    # (seeds 0-5: 0.5-1.0 %); 90th percentile 6.9 % (keypoints on depth edges read the other
    # side's GT at the rounded pixel); 0.4 % of the observations fall on sky (GT 0).
    assert np.median(rel) <= 0.02
    assert with_gt >= 0.95 and scale > 0
    # The poses carry the same scale: camera baselines scaled by s match the true ones.
    names = [fr.name for fr in street.frames[:10] if fr.name in res.frames]

    def centre(T):
        return -T[:3, :3].T @ T[:3, 3]

    c_sfm = np.array([centre(res.frames[n].cam_from_world) for n in names])
    c_gt = np.array([centre(street.seq.cam_from_world[int(n)]) for n in names])
    base_sfm = np.linalg.norm(c_sfm - c_sfm[0], axis=1)[1:] * scale
    base_gt = np.linalg.norm(c_gt - c_gt[0], axis=1)[1:]
    np.testing.assert_allclose(base_sfm, base_gt, rtol=0.03)


def test_fixed_intrinsics_are_unchanged(street, windows):
    for res in (windows.first, windows.second, windows.third):
        got, want = res.intrinsics, street.intr
        assert (got.width, got.height) == (want.width, want.height)
        assert (got.fx, got.fy) == (want.fx, want.fy)  # never touched, bit for bit
        assert got.cx == pytest.approx(want.cx, abs=1e-9)  # through COLMAP's +0.5 convention
        assert got.cy == pytest.approx(want.cy, abs=1e-9)
    # The check can fail: with refine_intrinsics on, bundle adjustment does move the focal
    # lengths, and far (measured fx 360.8 -> 575.9, fy -> 222.0 on this 10-frame forward
    # drive: why they are held fixed by default); only the principal point stays.
    free = windows.free_focal
    assert free.ok and free.intrinsics.fx != street.intr.fx
    assert free.intrinsics.cx == pytest.approx(street.intr.cx, abs=1e-9)


def test_observations_points_and_reprojection_errors_are_consistent(street, windows):
    res = windows.first
    K = street.intr.K
    assert res.points_xyz.shape == (res.num_points, 3)
    assert res.points_rgb.shape == (res.num_points, 3) and res.points_rgb.dtype == np.uint8
    assert res.points_error.shape == (res.num_points,)
    assert np.all(np.isfinite(res.points_xyz)) and np.all(res.points_error >= 0)
    assert len(np.unique(res.point_ids)) == res.num_points
    row = {int(p): i for i, p in enumerate(res.point_ids)}
    all_err, dups = [], 0
    for name, obs in res.frames.items():
        n = len(obs)
        assert n > 50 and obs.name == name
        assert obs.pixels.shape == (n, 2) and obs.depths.shape == (n,)
        assert obs.reproj_errors.shape == obs.track_errors.shape == obs.point_ids.shape == (n,)
        dups += n - len(np.unique(obs.point_ids))
        assert set(obs.point_ids.tolist()) <= set(row)
        assert np.all((obs.pixels >= -0.5) & (obs.pixels <= [W - 0.5, H - 0.5]))
        assert np.all(np.isfinite(obs.depths)) and np.all(obs.depths > 0)
        # Depth = z of the 3D point in this camera; the reprojection error recomputed here with
        # the known K in the OpenCV pixel convention (COLMAP's is shifted by 0.5).
        X = res.points_in_frame(name)[[row[int(p)] for p in obs.point_ids]]
        np.testing.assert_allclose(obs.depths, X[:, 2], rtol=1e-9)
        proj = (X @ K.T)[:, :2] / X[:, 2:]
        np.testing.assert_allclose(obs.reproj_errors, np.linalg.norm(proj - obs.pixels, axis=1),
                                   atol=1e-3)
        assert np.all(np.isfinite(obs.reproj_errors)) and np.all(obs.track_errors >= 0)
        all_err.append(obs.reproj_errors)
    err = np.concatenate(all_err)
    # COLMAP may keep two keypoints of one image (SIFT detections < 1-2 px apart) in one track:
    # measured 96 of 7855 observations (1.2 %), each with its own small reprojection error.
    assert dups <= 0.05 * err.size
    # Measured: median 0.15 px, 99th percentile 1.9 px, max 3.6 px (COLMAP filters at 4 px).
    assert np.median(err) < 0.5 and np.percentile(err, 99) < 4.0


@pytest.mark.slow
def test_overlapping_windows_reuse_features(street, windows):
    first, second = windows.extracted[:2]
    assert first == [f.name for f in street.frames[0:10]]
    assert second == [street.frames[10].name, street.frames[11].name]  # only the new frames
    assert windows.counts[:3] == [10, 10, 12]
    res = windows.second
    assert res.ok and res.num_registered >= 7 and res.num_frames == 8  # measured 8/8, 0.78 %
    assert res.timings["extract"] < windows.first.timings["extract"]
    rel, _, _ = depth_errors(res, street.frames[4:12], street.gt)
    assert np.median(rel) <= 0.02


@pytest.mark.slow
def test_reused_names_with_new_pixels_are_extracted_again(street, windows):
    # Regression: the cache used to be keyed by name only, so this window silently got the
    # features of the first window's frames 0-5 (its depth error against the true frames 2-7
    # was 16 %, against frames 0-5 0.95 %). Now: 6/6 registered, 0.67 %.
    assert windows.extracted[2] == [f.name for f in windows.renamed]
    assert windows.counts[3] == 18
    res = windows.third
    assert res.ok and res.num_registered >= 5
    truth = {f.name: street.gt[street.frames[f.index + 2].name] for f in windows.renamed}
    rel, _, _ = depth_errors(res, windows.renamed, truth)
    assert np.median(rel) <= 0.02


# ------------------------------------------------------------------ windows that fail
def small(street) -> tuple[list[np.ndarray], Intrinsics]:
    """Quarter-size frames (cheap) with matching intrinsics."""
    import cv2

    intr = street.intr.scaled(W // 2, H // 2)
    return [cv2.resize(f.image, (W // 2, H // 2), interpolation=cv2.INTER_AREA)
            for f in street.frames[:4]], intr


def failed(result: SfmResult, n: int, reason: str) -> None:
    assert not result.ok and result.num_frames == n
    assert reason in result.reason, result.reason
    assert result.num_registered == 0 and result.num_points == 0


def test_one_frame_is_a_failed_window_not_an_error(street):
    res = reconstruct_window(street.frames[:1], street.intr)
    failed(res, 1, "at least 2 frames")


def test_no_motion_fails_with_a_reason(street):
    images, intr = small(street)
    frames = [Frame(i, images[0].copy()) for i in range(4)]
    res = reconstruct_window(frames, intr)
    failed(res, 4, "too little motion")
    assert "map" not in res.timings  # the pre-check spared the mapper (5-13 s on such input)


def test_textureless_frames_fail_with_a_reason(street):
    images, intr = small(street)
    flat = [np.full_like(images[0], 90 + 20 * i) for i in range(4)]
    failed(reconstruct_window([Frame(i, im) for i, im in enumerate(flat)], intr), 4,
           "too few features")


def test_unrelated_frames_fail_with_a_reason(street):
    _, intr = small(street)
    rng = np.random.default_rng(0)
    noise = [rng.integers(0, 255, (H // 2, W // 2, 3), np.uint8) for _ in range(3)]
    frames = [Frame(i, im) for i, im in enumerate(noise)]
    # from the upsampled octave SIFT finds keypoints in the noise, none of which match
    res = reconstruct_window(frames, intr, SfmConfig(max_num_features=1024, first_octave=-1))
    failed(res, 3, "no frame pair of the window could be matched")
    # from octave 0 (the default) quarter-size noise holds too few keypoints to get that far
    res = reconstruct_window(frames, intr, SfmConfig(max_num_features=1024))
    failed(res, 3, "too few features")


# ------------------------------------------------------------------ mapping attempts
def test_every_mapping_attempt_is_recorded_and_the_best_one_kept(street):
    """retry_above_error 0: all three seeds run on the same matches; the kept reconstruction is
    the one with the most registered frames, then the lowest mean reprojection error."""
    with SfmReconstructor(SfmConfig(mapping_attempts=3, retry_above_error=0.0)) as rec:
        res = rec.reconstruct(street.frames[0:8], street.intr)
    assert res.ok and [a["seed"] for a in res.attempts] == [0, 1, 2]
    assert [a["kept"] for a in res.attempts].count(True) == 1
    kept = next(a for a in res.attempts if a["kept"])
    best = max(res.attempts, key=lambda a: (a["registered"], -a["reprojection_error"]))
    assert kept["reprojection_error"] == best["reprojection_error"] == res.reprojection_error
    assert kept["registered"] == res.num_registered and kept["points"] == res.num_points
    assert res.timings["map"] >= sum(a["seconds"] for a in res.attempts) > 0
    assert len(res.points_rgb) == res.num_points  # colours of the kept reconstruction
    # a well-fitting first reconstruction is not mapped again
    with SfmReconstructor(SfmConfig(mapping_attempts=3, retry_above_error=50.0)) as rec:
        once = rec.reconstruct(street.frames[0:8], street.intr)
    assert [a["seed"] for a in once.attempts] == [0] and once.attempts[0]["kept"]


def fake_result(registered: int, error: float, ok: bool = True) -> SfmResult:
    from sfm_ttr_ros.core.sfm.result import FrameObservations

    obs = {str(i): FrameObservations(str(i), np.zeros((4, 2), np.float32), np.ones(4),
                                     np.full(4, error), np.full(4, error),
                                     np.arange(4), np.eye(4)) for i in range(registered)}
    return SfmResult(ok, "" if ok else "failed", 5, frames=obs)


def map_best(rec: SfmReconstructor) -> SfmResult:
    """The reconstructor's mapper runs on an empty window (its runs monkeypatched)."""
    return rec.mapper.map_best(rec.config, [], {}, pycolmap.CancellationToken(), lambda: None)


@pytest.mark.parametrize("runs, threshold, seeds, kept_seed", [
    # the second run fits better and falls under the threshold: no third run
    ([(5, 1.1), (5, 0.6), (5, 0.5)], 0.8, [7, 8], 8),
    # every run above it: all run, the lowest error kept
    ([(5, 1.1), (5, 0.9), (5, 1.0)], 0.8, [7, 8, 9], 8),
    # more registered frames win over a lower error
    ([(5, 1.1), (4, 0.5), (3, 0.4)], 0.8, [7, 8, 9], 7),
    # a run that failed with a model (too few points) is tried again; success wins
    ([(2, 0.01, False), (5, 0.9), (5, 0.7)], 0.8, [7, 8, 9], 9),
])
def test_the_mapper_runs_again_only_while_the_best_error_is_high(monkeypatch, runs, threshold,
                                                                seeds, kept_seed):
    rec = SfmReconstructor(SfmConfig(mapping_attempts=3, retry_above_error=threshold, seed=7))
    results = iter([fake_result(*r) for r in runs])
    calls = []
    monkeypatch.setattr(rec.mapper, "_map", lambda cfg, names, token, seed: calls.append(seed))
    monkeypatch.setattr(rec.mapper, "_collect", lambda cfg, recs, names, timings: next(results))
    res = map_best(rec)
    rec.close()
    assert calls == seeds == [a["seed"] for a in res.attempts]
    assert [a["seed"] for a in res.attempts if a["kept"]] == [kept_seed]


@pytest.mark.parametrize("ratio, seeds", [(1.3, [0, 1]), (0.0, [0])])
def test_the_mapper_runs_again_above_the_streams_usual_error(monkeypatch, ratio, seeds):
    """A camera whose reconstructions fit to 0.3 px: 0.5 px is far under retry_above_error
    but 1.7x the stream's median, so with retry_above_ratio 1.3 the mapper runs again."""
    rec = SfmReconstructor(SfmConfig(mapping_attempts=3, retry_above_ratio=ratio))
    results = iter([fake_result(5, e) for e in (0.3, 0.31, 0.29, 0.5, 0.32, 0.3)])
    calls = []
    monkeypatch.setattr(rec.mapper, "_map", lambda cfg, names, token, seed: calls.append(seed))
    monkeypatch.setattr(rec.mapper, "_collect", lambda cfg, recs, names, timings: next(results))
    for _ in range(3):  # the stream's first windows: one run each (no history, then < 1.3x)
        map_best(rec)
    assert calls == [0, 0, 0]
    calls.clear()
    res = map_best(rec)
    assert calls == seeds and res.reprojection_error == pytest.approx(0.32 if ratio else 0.5)
    rec.reset()  # a new stream forgets the errors: 0.5 px is no reason to map again
    calls.clear()
    map_best(rec)
    assert calls == [0]
    rec.close()


def test_a_mapping_without_a_model_is_not_repeated(monkeypatch):
    rec = SfmReconstructor(SfmConfig(mapping_attempts=3, retry_above_error=0.0))
    calls = []
    monkeypatch.setattr(rec.mapper, "_map", lambda cfg, names, token, seed: calls.append(seed))
    monkeypatch.setattr(rec.mapper, "_collect",
                        lambda cfg, recs, names, timings: fake_result(0, 0, False))
    res = map_best(rec)
    rec.close()
    assert calls == [0] and not res.ok and res.attempts[0]["kept"]


@pytest.mark.parametrize("field, value", [("mapping_attempts", 0),
                                          ("retry_above_error", -1.0),
                                          ("retry_above_ratio", -0.1),
                                          ("retry_above_error", float("nan"))])
def test_bad_mapping_attempt_options_are_refused(field, value):
    from sfm_ttr_ros.core.errors import InputError

    with pytest.raises(InputError, match=f"sfm.{field}"):
        SfmConfig(**{field: value})


# -------------------------------------------------------------------------- real data
@pytest.mark.slow
def test_real_hololens_window(shared_data):
    seq = open_hololens(shared_data)
    assert (seq.intrinsics.width, seq.intrinsics.height) == (540, 360)
    frames = seq.frames(55, 65)  # files 00058 .. 00067: ~0.95 m of hand-held motion, 23 deg
    gt = {f.name: seq.gt(f.name) for f in frames}
    assert all(g is not None for g in gt.values())
    res = reconstruct_window(frames, seq.intrinsics)
    assert res.ok, res.reason
    assert res.num_registered >= 8
    rel, scale, with_gt = depth_errors(res, frames, gt)
    # Measured: 10/10 registered, ~2460 points, ~9800 observations with GT (78 %; the GT has
    # holes), median error 1.05 % (other 10-frame windows starting at 45-65: 0.7-1.9 %; one
    # starting at 42, where the camera mostly rotates (62 deg over 0.35 m), gave 30 %).
    assert np.median(rel) <= 0.05
    assert with_gt >= 0.5 and scale > 0
    med = float(np.median(np.concatenate([g[g > 0] for g in gt.values()])))
    assert 0.5 < med < 10.0  # GT read in metres (PNG millimetres / 1000)


def test_sfm_begun_ahead_is_the_windows_own_reconstruction(street):
    """SfmPrefetch reconstructs a window's frames in its own thread and workspace; take()
    hands exactly that window's result over (once), other frames get None."""
    from sfm_ttr_ros.core.sfm.prefetch import SfmPrefetch

    ahead = SfmPrefetch(SfmConfig(seed=0))
    try:
        window = street.frames[:10]
        assert ahead.start(window, street.intr)
        assert not ahead.start(window, street.intr)  # the same frames are not begun twice
        assert ahead.take(street.frames[1:11], street.intr) is None  # other frames: not this
        got = ahead.take(window, street.intr)
        assert got is not None and got.ok and got.num_registered == 10
        errors, _, _ = depth_errors(got, window, street.gt)
        assert float(np.median(errors)) < 0.05
        assert ahead.take(window, street.intr) is None  # handed over once
        assert ahead.counters() == {"started": 1, "used": 1, "discarded": 0}
        assert ahead.reconstructor.workspace.path.exists()
    finally:
        ahead.close()
    assert not ahead.reconstructor.workspace.path.exists()


def test_sfm_begun_ahead_waits_for_its_window_while_the_next_one_starts(street, monkeypatch):
    """The next window's frames may all be queued before the current window takes its own
    reconstruction: a finished one is kept (the two newest) until its window takes it."""
    from sfm_ttr_ros.core.sfm.prefetch import SfmPrefetch

    ahead = SfmPrefetch(SfmConfig())
    monkeypatch.setattr(ahead.reconstructor, "reconstruct",
                        lambda frames, intr: SfmResult(True, "", len(frames)))
    a, b, c = street.frames[0:4], street.frames[4:8], street.frames[8:12]
    try:
        for window in (a, b):
            assert ahead.start(window, street.intr)
            ahead._thread.join()
        assert ahead.take(a, street.intr).num_frames == 4  # kept while b was reconstructed
        assert ahead.start(c, street.intr)
        ahead._thread.join()
        assert ahead.take(c, street.intr) is not None and ahead.take(b, street.intr) is not None
        assert ahead.counters() == {"started": 3, "used": 3, "discarded": 0}
    finally:
        ahead.close()
