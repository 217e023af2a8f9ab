"""``refinement.loss``: Eq. (5) (``sfm``), Ph-TTR (``photometric``) and the hybrid,
in refine_encoder and through SfmTTR.process_window, on a rendered drive with its true poses
(no COLMAP: the window's SfM result is built from the generator's ground truth)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from conftest import tiny_model

import sfm_ttr_ros.core.pipeline as pipeline_module
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Frame
from sfm_ttr_ros.core.pipeline import SfmTTR, TTRConfig
from sfm_ttr_ros.core.refinement.encoder import refine_encoder
from sfm_ttr_ros.core.refinement.photometric import (
    network_intrinsics,
    photometric_objective,
    prepare_frames,
    relative_pose,
    scale_outputs,
)
from sfm_ttr_ros.core.refinement.refinement_config import RefinementConfig
from sfm_ttr_ros.core.refinement.supervision import FrameSupervision
from sfm_ttr_ros.core.sfm.result import FrameObservations, SfmResult
from sfm_ttr_ros.core.sfm.sfm_config import SfmConfig
from sfm_ttr_ros.data.synthetic import render_sequence, sample_scene_params

W, H = 256, 80
INPUT = (40, 128)  # the network runs at half size: K must follow (network_intrinsics)
N_FRAMES = 4
SFM_UNITS = 2.5  # the fake SfM reconstructs the drive 2.5x too small (a monocular scale)
POINTS = 300


@pytest.fixture(scope="module")
def drive(one_thread):
    seq = render_sequence(sample_scene_params(0, "A"), N_FRAMES, W, H, blur_sigma=0.8)
    names = [f"{i:010d}" for i in range(N_FRAMES)]
    return seq, names


def fake_sfm(seq, names, registered=None) -> SfmResult:
    """What pycolmap would give with perfect tracks: GT depths and poses in SfM units (metres /
    SFM_UNITS), ``POINTS`` observations per frame, small reprojection errors."""
    rng = np.random.default_rng(0)
    frames = {}
    for i, name in enumerate(names):
        if registered is not None and name not in registered:
            continue
        ys, xs = np.nonzero(seq.depths[i] > 0)
        k = rng.choice(len(xs), POINTS, replace=False)
        T = seq.cam_from_world[i].copy()
        T[:3, 3] /= SFM_UNITS
        frames[name] = FrameObservations(
            name, np.c_[xs[k], ys[k]].astype(np.float32),
            seq.depths[i][ys[k], xs[k]].astype(np.float64) / SFM_UNITS,
            np.full(POINTS, 0.3), np.full(POINTS, 0.3), np.arange(POINTS), T)
    return SfmResult(True, "", len(names), frames, intrinsics=seq.intrinsics)


def supervision(seq, names, scale: float = SFM_UNITS) -> list[FrameSupervision]:
    sfm = fake_sfm(seq, names)
    return [FrameSupervision(n, seq.images[i], sfm.frames[n].pixels,
                             scale * sfm.frames[n].depths, np.exp(-0.09) * np.ones(POINTS))
            for i, n in enumerate(names)]


def photometric_frames(model, seq, names, **kw):
    sfm = fake_sfm(seq, names, **kw)
    return prepare_frames(model, names, dict(zip(names, seq.images, strict=True)), sfm.frames,
                          SFM_UNITS, seq.intrinsics, RefinementConfig().photometric_config())


def encoder_state(model) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in model.encoder.state_dict().items()}


def run(seq, names, loss: str, weight: float = 1.0, steps: int = 12, **kw):
    model = tiny_model(INPUT, batch_norm=1)
    cfg = RefinementConfig(steps=steps, lr=1e-3, loss=loss, photometric_weight=weight, **kw)
    res = refine_encoder(model, supervision(seq, names), cfg,
                         photometric=photometric_frames(model, seq, names))
    return model, res


def mean_photometric(model, frames) -> float:
    cfg = RefinementConfig().photometric_config()
    with torch.no_grad():
        return float(np.mean([
            float(photometric_objective(scale_outputs(model, model.encoder(f.target)),
                                        f.target, f.sources, f.K, f.poses, cfg,
                                        f.identity).total) for f in frames]))


def test_hybrid_with_zero_weight_is_sfm_bit_for_bit(drive):
    seq, names = drive
    m_sfm, r_sfm = run(seq, names, "sfm")
    m_hyb, r_hyb = run(seq, names, "hybrid", 0.0, sfm_residual="absolute")
    assert r_hyb.loss_history == r_sfm.loss_history and r_sfm.steps_done == 12
    a, b = encoder_state(m_sfm), encoder_state(m_hyb)
    assert all(torch.equal(a[k], b[k]) for k in a)
    # the relative residual (the default) divides each point's term by its target: other steps
    _, r_rel = run(seq, names, "hybrid", 0.0)
    assert r_rel.loss_history != r_sfm.loss_history
    # λ > 0 changes the steps; a tiny λ changes them only a little: the hybrid's Eq. (5) term
    # comes from the same forward pass as sfm's
    _, r_tiny = run(seq, names, "hybrid", 1e-3, sfm_residual="absolute")
    _, r_one = run(seq, names, "hybrid", 1.0, sfm_residual="absolute")
    assert r_tiny.loss_history != r_sfm.loss_history
    assert r_tiny.loss_history == pytest.approx(r_sfm.loss_history, rel=1e-4)
    assert r_one.loss_history[0] > r_sfm.loss_history[0]  # + λ·photometric on step 1
    assert r_one.loss_history != pytest.approx(r_sfm.loss_history, rel=1e-2)


def metric_abs_rel(model, seq) -> float:
    """abs rel against the generator's depth WITHOUT median scaling: the poses fix the scale."""
    out = []
    for image, gt in zip(seq.images, seq.depths, strict=True):
        d, m = model.predict(image)[0], (gt > 0) & (gt < 80)
        out.append(np.mean(np.abs(d[m] - gt[m]) / gt[m]))
    return float(np.mean(out))


def test_photometric_refinement_moves_depth_toward_the_truth_without_sfm_targets(drive):
    """Ph-TTR from a network that says ~10 m everywhere (decoder bias), with the true poses in
    network units: the photometric objective falls and the metric depth error falls with it
    (measured: 0.061 -> 0.054 and abs rel 0.71 -> 0.56)."""
    seq, names = drive
    model = tiny_model(INPUT, batch_norm=1)
    with torch.no_grad():
        model.decoder[0].bias -= 4.7  # sigmoid ~0.009: depth ~10 m
    frames = photometric_frames(model, seq, names)
    before, err_before = mean_photometric(model, frames), metric_abs_rel(model, seq)
    sup = supervision(seq, names)
    for s in sup:  # Ph-TTR never reads the SfM targets: NaN would poison any Eq. (5) step
        s.target = np.full_like(s.target, np.nan)
    res = refine_encoder(model, sup, RefinementConfig(steps=40, lr=1e-2, loss="photometric"),
                         photometric=frames)
    after, err_after = mean_photometric(model, frames), metric_abs_rel(model, seq)
    assert res.steps_done == 40 and res.frames_used == N_FRAMES
    assert np.all(np.isfinite(res.loss_history))
    assert after < 0.92 * before, (before, after)
    assert err_after < 0.9 * err_before, (err_before, err_after)
    assert not any(p.requires_grad for p in model.parameters()) and not model.training


def test_photometric_trains_only_frames_with_a_registered_neighbour(drive):
    """Frames 0, 1 and 3 registered: 0 and 1 are each other's source; 3's neighbour 2 is not
    registered, so frame 3 has no photometric term and Ph-TTR trains on two frames only."""
    seq, names = drive
    model = tiny_model(INPUT)
    frames = photometric_frames(model, seq, names, registered={names[0], names[1], names[3]})
    assert [f.name for f in frames] == names[:2]
    assert [f.source_names for f in frames] == [[names[1]], [names[0]]]
    res = refine_encoder(model, supervision(seq, names), RefinementConfig(
        steps=3, lr=1e-3, loss="photometric"), photometric=frames)
    assert res.frames_used == 2 and res.steps_done == 3
    # no photometric frame at all: nothing to train
    res = refine_encoder(model, supervision(seq, names), RefinementConfig(
        steps=3, loss="photometric"), photometric=[])
    assert res.frames_used == 0 and res.steps_done == 0


def test_loss_settings_are_checked():
    cfg = RefinementConfig(loss="hybrid", photometric_weight=0.5, photometric_alpha=0.5,
                           smoothness_weight=0.01, photometric_sources="-2, -1,1", seed=7)
    p = cfg.photometric_config()
    assert (p.alpha, p.smoothness_weight, p.source_offsets, p.seed) == (0.5, 0.01, (-2, -1, 1), 7)
    assert cfg.uses_photometric and RefinementConfig(loss="photometric").uses_photometric
    assert not RefinementConfig(loss="hybrid", photometric_weight=0.0).uses_photometric
    assert RefinementConfig().loss == "auto"  # the default: resolved per network (below)
    assert not RefinementConfig(loss="sfm").uses_photometric
    for kw, msg in (({"loss": "ssim"}, "loss must be one of"),
                    ({"photometric_weight": -1.0}, "photometric_weight"),
                    ({"photometric_weight": float("inf")}, "photometric_weight"),
                    ({"photometric_alpha": 1.5}, "alpha"),
                    ({"smoothness_weight": -1e-3}, "smoothness_weight"),
                    ({"photometric_sources": "-1,x"}, "integers"),
                    ({"photometric_sources": "0,1"}, "non-zero"),
                    ({"photometric_sources": "1,1"}, "distinct"),
                    ({"photometric_sources": ""}, "source_offsets")):
        with pytest.raises(InputError, match=msg):
            RefinementConfig(**kw)


# -- through the pipeline -----------------------------------------------------------------------

@pytest.fixture(scope="module")
def window(drive):
    seq, names = drive
    frames = [Frame(i, im, stamp=s, name=n) for i, (n, im, s) in
              enumerate(zip(names, seq.images, seq.stamps, strict=True))]
    return frames, fake_sfm(seq, names)


def process(window, monkeypatch, **refinement):
    """process_window with the fake SfM, refine_encoder spied on; (result, its kwargs)."""
    frames, sfm = window
    calls = []
    real = pipeline_module.refine_encoder

    def spy(*args, **kwargs):
        calls.append(kwargs)
        return real(*args, **kwargs)

    cfg = TTRConfig(min_supervision_points=20, sfm=SfmConfig(mode="batch"))  # the fake's mapper
    cfg.refinement = replace(cfg.refinement, steps=6, lr=1e-3, **refinement)
    ttr = SfmTTR(tiny_model(INPUT, batch_norm=1), cfg)
    monkeypatch.setattr(ttr.sfm.reconstructor, "reconstruct", lambda *a, **k: sfm)
    monkeypatch.setattr(pipeline_module, "refine_encoder", spy)
    try:
        res = ttr.process_window(frames, sfm.intrinsics)
    finally:
        ttr.close()
    return res, calls[0]


def test_pipeline_hybrid_zero_is_sfm_and_poses_are_in_network_units(window, monkeypatch):
    frames, sfm = window
    res_sfm, kw_sfm = process(window, monkeypatch, loss="sfm")
    res_zero, kw_zero = process(window, monkeypatch, loss="hybrid", photometric_weight=0.0,
                                sfm_residual="absolute")
    assert res_sfm.refined and res_zero.refined
    assert list(kw_sfm["photometric"]) == [] and list(kw_zero["photometric"]) == []
    assert res_zero.refinement.loss_history == res_sfm.refinement.loss_history
    for n in res_sfm.depths:
        assert np.array_equal(res_zero.depths[n], res_sfm.depths[n])

    res, kw = process(window, monkeypatch, loss="hybrid", photometric_weight=1.0)
    assert res.refined and res.refinement.loss_history != res_sfm.refinement.loss_history
    ph = kw["photometric"]
    names = [f.name for f in frames]
    assert [f.name for f in ph] == names  # every frame registered, with a neighbour
    # the alignment scale ŝ found the fake SfM's units (the network's depth / SfM depth) and
    # the poses' translations were multiplied by it; K is the network's
    assert res.scale > 0
    for f in ph:
        for src, T in zip(f.source_names, f.poses, strict=True):
            want = relative_pose(sfm.frames[f.name].cam_from_world,
                                 sfm.frames[src].cam_from_world, res.scale)
            np.testing.assert_allclose(T, want, atol=1e-12)
        np.testing.assert_allclose(f.K, network_intrinsics(sfm.intrinsics, INPUT))
    assert [f.source_names for f in ph][0] == [names[1]]
    assert [f.source_names for f in ph][1] == [names[0], names[2]]

    res_ph, kw_ph = process(window, monkeypatch, loss="photometric")
    assert res_ph.refined and len(kw_ph["photometric"]) == len(frames)
    assert res_ph.refinement.frames_used == len(frames)


def test_relative_sfm_residual_divides_each_point_by_its_target():
    """|ŝD − D_nn| / (ŝD): the step's weights are exp(−r²) / target, so a point 10x farther
    weighs 10x less than with Eq. (5)'s absolute residual, and the same relative error costs
    the same near and far."""
    from sfm_ttr_ros.core.refinement.objective import step_weights
    from sfm_ttr_ros.core.refinement.refinement_config import RefinementConfig
    from sfm_ttr_ros.core.refinement.supervision import FrameSupervision

    s = FrameSupervision("a", np.zeros((4, 4, 3), np.uint8), np.zeros((2, 2)),
                         np.array([2.0, 20.0]), np.array([0.5, 0.5]))
    assert np.allclose(step_weights(s, "absolute"), [0.5, 0.5])
    w = step_weights(s, "relative")
    assert np.allclose(w, [0.25, 0.025])
    pred = s.target * 1.1  # 10 % too far at both depths
    assert np.allclose(w * np.abs(pred - s.target), [0.05, 0.05])
    with pytest.raises(ValueError, match="sfm_residual"):
        RefinementConfig(sfm_residual="squared")


def test_auto_objective_is_photometric_unless_the_network_is_affine_invariant():
    """loss "auto" (the default): the hybrid for a network that predicts depth up to scale, the
    paper's Eq. (5) for one whose output is relative inverse depth (nothing to warp with) or
    when refine_encoder gets no photometric frames."""
    from sfm_ttr_ros.core.refinement.refinement_config import resolve_loss

    model = tiny_model()
    cfg = RefinementConfig()
    assert cfg.loss == "auto"
    assert resolve_loss(cfg, model).loss == "hybrid"
    assert resolve_loss(cfg, model, photometric_frames=False).loss == "sfm"
    assert resolve_loss(replace(cfg, loss="sfm"), model).loss == "sfm"
    model.output_kind = "relative_inverse_depth"
    assert resolve_loss(cfg, model).loss == "sfm"
    ttr = SfmTTR(model, TTRConfig())
    try:
        assert ttr.config.refinement.loss == "sfm"
    finally:
        ttr.close()
