"""refinement.frozen_encoder_levels: the encoder kept fixed up to its L-th feature map, computed
once per frame (a speed option), must give exactly the refinement of the remaining
stages."""

import logging

import numpy as np
import pytest
import torch
from conftest import tiny_model

import sfm_ttr_ros.core.refinement.encoder as encoder_module
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.geometry import normalized_grid, sample_depth
from sfm_ttr_ros.core.models.mobilenet import MobileDepthNet
from sfm_ttr_ros.core.models.monodepth2 import Monodepth2
from sfm_ttr_ros.core.pipeline import SfmTTR, TTRConfig
from sfm_ttr_ros.core.refinement.encoder import frozen_stage_count, refine_encoder
from sfm_ttr_ros.core.refinement.refinement_config import RefinementConfig
from sfm_ttr_ros.core.refinement.supervision import FrameSupervision, weighted_l1


def mobile(seed: int = 0) -> MobileDepthNet:
    torch.manual_seed(seed)
    return MobileDepthNet(input_size=(64, 96)).eval()


def one_frame(seed: int = 0, points: int = 200) -> list[FrameSupervision]:
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 255, (64, 96, 3), dtype=np.uint8)
    px = np.c_[rng.uniform(0, 95, points), rng.uniform(0, 63, points)]
    return [FrameSupervision("0000", img, px, rng.uniform(2.0, 30.0, points),
                             rng.uniform(0.2, 1.0, points))]


@pytest.mark.parametrize("make", [mobile, lambda: Monodepth2(18, input_size=(64, 96)).eval()])
def test_staged_forward_equals_forward(make):
    torch.manual_seed(0)
    model = make()
    enc = model.encoder
    x = torch.rand(1, 3, 64, 96)
    with torch.no_grad():
        full = enc(x)
        for k in (1, enc.num_stages // 2, enc.num_stages - 1):
            mid, feats = enc.forward_stages(x, 0, k, [])
            _, split = enc.forward_stages(mid, k, enc.num_stages, feats)
            assert len(split) == len(full) == 5
            for a, b in zip(split, full, strict=True):
                assert torch.equal(a, b)
        # level L needs exactly the stages that produce the first L feature maps
        for level, k in enumerate(enc.level_stages, start=1):
            assert len(enc.forward_stages(x, 0, k, [])[1]) == level
            assert len(enc.forward_stages(x, 0, k - 1, [])[1]) == level - 1


def test_level_stages_of_the_shipped_encoders():
    assert mobile().encoder.level_stages == (2, 4, 7, 14, 18)
    assert Monodepth2(18, input_size=(64, 96)).encoder.level_stages == (1, 2, 3, 4, 5)
    assert frozen_stage_count(mobile().encoder, 0) == 0
    assert frozen_stage_count(mobile().encoder, 3) == 7


def test_frozen_stages_train_exactly_the_remaining_stages():
    """Same weights as plain Adam over the later stages' parameters on the full forward."""
    level, k, steps, lr = 3, 7, 6, 1e-3  # up to the 1/8 map: features.0 … features.6
    sup = one_frame()
    model, ref = mobile(), mobile()
    start = {n: v.clone() for n, v in model.encoder.state_dict().items()}
    res = refine_encoder(model, sup, RefinementConfig(steps=steps, lr=lr,
                                                      frozen_encoder_levels=level))
    assert res.steps_done == steps

    # the reference: the whole network run every step, stages < k without gradients
    for p in ref.parameters():
        p.requires_grad_(False)
    params = [p for i in range(k, ref.encoder.num_stages)
              for m in ref.encoder.stage_modules(i) for p in m.parameters()]
    for p in params:
        p.requires_grad_(True)
    opt = torch.optim.Adam(params, lr=lr)
    s = sup[0]
    x = ref.preprocess(s.image)
    grid = normalized_grid(s.pixels, 96, 64)
    target, w = torch.as_tensor(s.target).float(), torch.as_tensor(s.weights).float()
    for _ in range(steps):
        loss = weighted_l1(sample_depth(ref(x), grid), target, w)
        opt.zero_grad()
        loss.backward()
        opt.step()

    got, want = model.encoder.state_dict(), ref.encoder.state_dict()
    frozen_names = {n for i in range(k) for n, _ in model.encoder.features[i].named_parameters(
        prefix=f"features.{i}")}
    assert frozen_names
    changed = 0
    for name, value in got.items():
        assert torch.allclose(value, want[name], atol=1e-6), name
        if name in frozen_names:
            assert torch.equal(value, start[name]), name
        elif not torch.equal(value, start[name]):
            changed += 1
    assert changed > 10


def test_frozen_levels_validation():
    for bad_level in (-1, 5):
        with pytest.raises(InputError, match=r"0\.\.4"):
            RefinementConfig(frozen_encoder_levels=bad_level)
    assert frozen_stage_count(tiny_model().encoder, 2) == 0  # no stages: none kept fixed

    class ThreeMaps(torch.nn.Module):  # a protocol encoder with fewer feature maps
        num_stages, level_stages = 3, (1, 2, 3)
        stage_modules = forward_stages = None
    with pytest.raises(InputError, match="below the encoder's 3 feature maps"):
        frozen_stage_count(ThreeMaps(), 3)

    model = mobile()
    ttr = SfmTTR(model, TTRConfig())
    class NoStageLeft(torch.nn.Module):
        num_stages, level_stages = 2, (1, 2, 2, 2, 2)
        stage_modules = forward_stages = None
    with pytest.raises(InputError, match="does not leave a stage"):
        frozen_stage_count(NoStageLeft(), 2)
    ttr.set_config(TTRConfig(refinement=RefinementConfig(frozen_encoder_levels=4)))
    assert ttr.config.refinement.frozen_encoder_levels == 4
    ttr.close()


def test_an_encoder_without_stages_trains_whole_and_says_so_once(caplog):
    """frozen_encoder_levels > 0 on an encoder without the staged-encoder protocol (the stand-in's
    Sequential): every encoder parameter trains, exactly as with 0; one warning per model, the
    reason in every result; the pipeline accepts the configuration."""
    sup = one_frame()
    whole, fallback = tiny_model(), tiny_model()
    start = {n: v.clone() for n, v in fallback.encoder.state_dict().items()}
    ref = refine_encoder(whole, sup, RefinementConfig(steps=3, lr=1e-3, frozen_encoder_levels=0))
    assert ref.frozen_levels_reason == ""
    with caplog.at_level(logging.WARNING, logger=encoder_module.__name__):
        runs = [refine_encoder(fallback, sup, RefinementConfig(steps=3, lr=1e-3,
                                                               frozen_encoder_levels=2))
                for _ in range(2)]
        other = refine_encoder(tiny_model(), sup, RefinementConfig(steps=1,
                                                                   frozen_encoder_levels=1))
    assert runs[0].loss_history == ref.loss_history  # the same steps as the whole encoder's
    for name, value in fallback.encoder.state_dict().items():
        assert not torch.equal(value, start[name]), name  # the first layers trained too
    reason = runs[0].frozen_levels_reason
    assert "Sequential has no encoder stages" in reason and "whole encoder trains" in reason
    assert runs[1].frozen_levels_reason == reason and other.frozen_levels_reason
    # once per model: the second refinement of the same model does not repeat it
    assert [r.getMessage() for r in caplog.records] == [reason, other.frozen_levels_reason]
    # a staged encoder is still held to its range, through the same configuration
    SfmTTR(tiny_model(), TTRConfig(refinement=RefinementConfig(frozen_encoder_levels=2))).close()
    with pytest.raises(InputError, match="below the encoder's"):
        frozen_stage_count(mobile().encoder, 5)
