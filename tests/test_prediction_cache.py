"""SfmTTR.predict reuses a prediction made with the same weights for the same pixels
(``TTRConfig.reuse_predictions``): the overlap frames of consecutive windows are predicted once
per weights instead of twice, with the same numbers: bit for bit when every image is its own
batch (``predict_batch`` 1); otherwise a frame may be computed in another batch than it would
have been, which changes the last bits (~2e-7 relative here), as any ``predict_batch`` does.

A tiny network and a stand-in for the SfM stage (sparse depths read off the original network's
prediction, scaled and perturbed) keep the windows fast and deterministic."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from conftest import tiny_model

from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.geometry import sample_at
from sfm_ttr_ros.core.pipeline import SfmTTR, TTRConfig
from sfm_ttr_ros.core.prediction import PREDICTION_CACHE_FRAMES
from sfm_ttr_ros.core.refinement.refinement_config import RefinementConfig
from sfm_ttr_ros.core.sfm.result import FrameObservations, SfmResult
from sfm_ttr_ros.core.sfm.sfm_config import SfmConfig

W, H = 160, 64
INTR = Intrinsics(100.0, 100.0, W / 2, H / 2, W, H)


def bn_model():
    """The tiny network with a BatchNorm after its first convolution, at (32, 96)."""
    return tiny_model((32, 96), batch_norm=1)


def images(n: int) -> list[np.ndarray]:
    rng = np.random.default_rng(1)
    base = rng.integers(0, 255, (H, W + 3 * n, 3), np.uint8)
    return [np.ascontiguousarray(base[:, 3 * i:3 * i + W]) for i in range(n)]  # a panning view


class FakeReconstructor:
    """Sparse 'SfM' depths: the ORIGINAL network's depth at fixed pixels / 3, +-20 % noise."""

    def __init__(self):
        self.model = bn_model()

    def reconstruct(self, frames, intrinsics) -> SfmResult:
        res = SfmResult(True, "", len(frames), timings={"extract": 0.0})
        pts = []
        for k, f in enumerate(frames):
            rng = np.random.default_rng(f.index)
            px = np.stack([rng.uniform(0, W - 1, 300), rng.uniform(0, H - 1, 300)], 1)
            d = sample_at(self.model.predict([f.image])[0], px) / 3.0
            d = d * rng.uniform(0.8, 1.2, d.size)
            res.frames[f.name] = FrameObservations(
                f.name, px.astype(np.float32), d.astype(np.float64), np.full(d.size, 0.3),
                np.full(d.size, 0.3), np.arange(d.size) + 1000 * k, np.eye(4))
            pts.append(np.column_stack([px, d]))
        res.points_xyz = np.concatenate(pts)
        res.point_ids = np.arange(res.points_xyz.shape[0])
        res.points_error = np.full(res.points_xyz.shape[0], 0.3)
        return res

    def close(self) -> None:
        pass


def make_ttr(reuse: bool, weight_policy: str = "continue", batch: int = 1) -> SfmTTR:
    cfg = TTRConfig(refinement=RefinementConfig(steps=3, lr=1e-2),
                    sfm=SfmConfig(mode="batch"),  # the fake stands in for the batch mapper
                    reuse_predictions=reuse, weight_policy=weight_policy,
                    predict_batch=batch)
    cfg.check.min_parallax = 0.0  # the fake SfM's cameras do not move: no parallax to check
    ttr = SfmTTR(bn_model(), cfg)
    ttr.sfm.reconstructor.close()
    ttr.sfm.reconstructor = FakeReconstructor()
    return ttr


def windows(ttr: SfmTTR, imgs: list[np.ndarray]):
    frames = [Frame(index=i, image=im) for i, im in enumerate(imgs)]
    return [ttr.process_window(frames[0:10], INTR), ttr.process_window(frames[5:15], INTR)]


@pytest.mark.parametrize("batch", [1, 4])
def test_overlapping_windows_predict_the_overlap_once_with_the_same_numbers(one_thread, batch):
    imgs = images(15)
    on, off = make_ttr(True, batch=batch), make_ttr(False, batch=batch)
    res_on, res_off = windows(on, imgs), windows(off, imgs)
    same = np.array_equal if batch == 1 else lambda a, b: np.allclose(a, b, rtol=1e-5, atol=0)
    for a, b in zip(res_on, res_off, strict=True):
        assert a.refined and b.refined
        for name in a.names:
            assert same(a.depths_before[name], b.depths_before[name])
            assert same(a.depths[name], b.depths[name])
    # the refinement did change the weights between the two predictions of a window
    assert not np.array_equal(res_on[0].depths["0000000005"], res_on[0].depths_before["0000000005"])
    # off: 4 passes of 10 frames; on: window 2's "before" of frames 5-9 = window 1's "after"
    assert (off.predictor.computed, off.predictor.reused) == (40, 0)
    assert (on.predictor.computed, on.predictor.reused) == (35, 5)


def test_reset_each_window_reuses_the_original_weights_predictions(one_thread):
    ttr = make_ttr(True, weight_policy="reset")
    res = windows(ttr, images(15))
    assert all(r.refined for r in res)
    # window 2 starts from the original weights again: the "before" of its overlap frames 5-9
    # is window 1's "before" (original weights), not its refined "after"
    assert (ttr.predictor.computed, ttr.predictor.reused) == (35, 5)
    for name in ("0000000005", "0000000009"):
        assert np.array_equal(res[1].depths_before[name], res[0].depths_before[name])
        assert not np.array_equal(res[1].depths_before[name], res[0].depths[name])
    fresh = make_ttr(False, weight_policy="reset")
    recomputed = windows(fresh, images(15))
    for name in res[1].names:
        assert np.array_equal(res[1].depths_before[name], recomputed[1].depths_before[name])
        assert np.array_equal(res[1].depths[name], recomputed[1].depths[name])


def test_cache_follows_the_pixels_and_the_weights(one_thread):
    ttr = make_ttr(True)
    imgs = images(3)
    first = ttr.predictor.predict(imgs)
    assert ttr.predictor.computed == 3
    again = ttr.predictor.predict([im.copy() for im in imgs])  # same pixels, other arrays: reused
    assert (ttr.predictor.computed, ttr.predictor.reused) == (3, 3)
    assert all(np.array_equal(a, b) for a, b in zip(first, again, strict=True))
    again[0][:] = -1.0  # callers get their own arrays
    assert np.array_equal(ttr.predictor.predict(imgs[:1])[0], first[0])
    assert ttr.predictor.computed == 3

    changed = imgs[1].copy()
    changed[0, 0] ^= 1  # one pixel
    ttr.predictor.predict([changed])
    assert ttr.predictor.computed == 4

    with torch.no_grad():  # any in-place change of the weights
        next(ttr.model.encoder.parameters()).add_(0.5)
    moved = ttr.predictor.predict(imgs[:1])[0]
    assert ttr.predictor.computed == 5 and not np.array_equal(moved, first[0])
    ttr.weights.reset()  # back to the original weights: their predictions are still known
    assert np.array_equal(ttr.predictor.predict(imgs[:1])[0], first[0])
    assert ttr.predictor.computed == 5
    ttr.predictor.clear()
    assert np.array_equal(ttr.predictor.predict(imgs[:1])[0], first[0])
    assert ttr.predictor.computed == 6

    ttr.model.encoder.train()  # a BatchNorm statistics update (bn_mode "train" refinement)
    ttr.model.encoder(ttr.model.preprocess(imgs[2]))
    ttr.model.eval()
    ttr.predictor.predict(imgs[:1])
    assert ttr.predictor.computed == 7


def test_cache_is_bounded_and_can_be_off(one_thread):
    ttr = make_ttr(True)
    imgs = images(40)
    # untouched weights are the original ones: their predictions live in the original cache
    ttr.predictor.predict(imgs[:30])  # one large call keeps all of its frames
    assert len(ttr.predictor._original_cache) == 30
    ttr.predictor.predict(imgs[30:31])  # later small calls trim it to the latest ones
    assert len(ttr.predictor._original_cache) == PREDICTION_CACHE_FRAMES
    computed = ttr.predictor.computed
    ttr.predictor.predict(imgs[30:31] + imgs[29:30])  # the most recent frames are the ones kept
    assert ttr.predictor.computed == computed
    for im in imgs[31:]:
        ttr.predictor.predict([im])
    assert len(ttr.predictor._original_cache) == PREDICTION_CACHE_FRAMES
    off = copy.deepcopy(ttr.config)
    off.reuse_predictions = False
    ttr.set_config(off)
    before = ttr.predictor.computed
    ttr.predictor.predict(imgs[:2])
    ttr.predictor.predict(imgs[:2])
    assert ttr.predictor.computed == before + 4 and len(ttr.predictor._original_cache) == 0


def test_frames_per_pass_depend_on_the_device(one_thread, monkeypatch):
    """``predict_batch`` on the CPU (unchanged), ``predict_batch_cuda`` on CUDA (a window in one
    pass; 0 = predict_batch); the passes the network makes follow it."""
    from sfm_ttr_ros.core.errors import InputError
    from sfm_ttr_ros.core.prediction import Predictor

    model = bn_model()
    p = Predictor(model, batch=2, cuda_batch=16)
    assert p.effective_batch == 2
    passes = []
    real = model.predict
    model.predict = lambda ims: passes.append(len(ims)) or real(ims)
    p.run(images(5))
    assert passes == [2, 2, 1]
    model.predict = real
    cuda = type("Dev", (), {"type": "cuda"})()  # as if on CUDA: only the batch is read
    monkeypatch.setattr(type(model), "device", property(lambda self: cuda))
    assert p.effective_batch == 16
    p.cuda_batch = 0
    assert p.effective_batch == 2
    monkeypatch.undo()
    assert TTRConfig().predict_batch_cuda == 16 and TTRConfig().predict_batch == 2
    with pytest.raises(InputError, match="predict_batch_cuda"):
        TTRConfig(predict_batch_cuda=-1)
