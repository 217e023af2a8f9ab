"""transformers depth models as DepthModels, and parameter-efficient refinement.

Tiny randomly initialised Depth Anything and DPT configs are written with ``save_pretrained``
to a temporary directory and loaded back offline: nothing is downloaded."""

import dataclasses
import json
import os

os.environ["HF_HUB_OFFLINE"] = "1"  # before transformers / huggingface_hub read it

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402
from helpers import remove_lora, reset_lora  # noqa: E402

transformers = pytest.importorskip("transformers", reason="extra 'hf' not installed")
pytest.importorskip("peft", reason="extra 'hf' not installed")

from sfm_ttr_ros.core.errors import InputError  # noqa: E402
from sfm_ttr_ros.core.models import ModelConfig, ModelLoadError, build_model  # noqa: E402
from sfm_ttr_ros.core.models.hf import (  # noqa: E402
    HFDepthModel,
    Preprocessing,
    detect_output_kind,
)
from sfm_ttr_ros.core.models.mobilenet import MobileDepthNet  # noqa: E402
from sfm_ttr_ros.core.refinement import trainable  # noqa: E402
from sfm_ttr_ros.core.refinement.encoder import refine_encoder, restore_encoder, snapshot_encoder  # noqa: E402
from sfm_ttr_ros.core.refinement.refinement_config import RefinementConfig  # noqa: E402
from sfm_ttr_ros.core.refinement.supervision import FrameSupervision  # noqa: E402

DA_PROCESSOR = {  # what Depth Anything V2's hub preprocessor_config.json holds, at 56 px
    "image_processor_type": "DPTImageProcessor", "do_resize": True,
    "size": {"height": 56, "width": 56}, "keep_aspect_ratio": True, "ensure_multiple_of": 14,
    "resample": 3, "do_rescale": True, "rescale_factor": 1 / 255, "do_normalize": True,
    "image_mean": [0.485, 0.456, 0.406], "image_std": [0.229, 0.224, 0.225], "do_pad": False,
}
FRAME = (np.random.default_rng(0).random((40, 130, 3)) * 255).astype(np.uint8)


def _pretrained_like(net: torch.nn.Module) -> torch.nn.Module:
    """transformers' 0.02-std init leaves a random tiny DPT's ReLU output at 0 everywhere (no
    gradient): PyTorch's default init and a positive bias on the last conv of the head give a
    network in a trained one's regime (positive, varying output)."""
    for m in net.modules():
        if m is not net and hasattr(m, "reset_parameters"):
            m.reset_parameters()
    last = [m for m in net.head.modules() if isinstance(m, torch.nn.Conv2d)][-1]
    torch.nn.init.constant_(last.bias, 1.0)
    return net


@pytest.fixture(scope="module")
def model_dirs(tmp_path_factory):
    from transformers import (
        DepthAnythingConfig,
        DepthAnythingForDepthEstimation,
        Dinov2Config,
        DPTConfig,
        DPTForDepthEstimation,
    )

    torch.manual_seed(0)
    root = tmp_path_factory.mktemp("hf")
    backbone = Dinov2Config(hidden_size=32, num_hidden_layers=2, num_attention_heads=2,
                            intermediate_size=64, image_size=56, patch_size=14,
                            out_indices=[1, 2], reshape_hidden_states=False)
    da = DepthAnythingForDepthEstimation(DepthAnythingConfig(
        backbone_config=backbone, reassemble_hidden_size=32, neck_hidden_sizes=[8, 16],
        reassemble_factors=[2, 1], fusion_hidden_size=16, head_hidden_size=8))
    _pretrained_like(da).save_pretrained(root / "da")
    (root / "da" / "preprocessor_config.json").write_text(json.dumps(DA_PROCESSOR))
    dpt = DPTForDepthEstimation(DPTConfig(
        hidden_size=32, num_hidden_layers=2, num_attention_heads=2, intermediate_size=64,
        image_size=64, patch_size=16, backbone_out_indices=[0, 1], neck_hidden_sizes=[8, 16],
        reassemble_factors=[2, 1], fusion_hidden_size=16, head_hidden_size=8))
    _pretrained_like(dpt).save_pretrained(root / "dpt")  # no processor file: the fallback
    return {"da": str(root / "da"), "dpt": str(root / "dpt")}


def load(model_dirs, name: str, **kwargs) -> HFDepthModel:
    return build_model(ModelConfig(type="hf", model_path=model_dirs[name], **kwargs))


@pytest.mark.parametrize("name, net_size", [("da", (56, 182)), ("dpt", (64, 64))])
def test_loads_offline_and_predicts_the_frames_size(model_dirs, name, net_size):
    model = load(model_dirs, name)
    assert isinstance(model, HFDepthModel) and not model.training
    assert model.output_kind == "relative_inverse_depth"
    x = model.preprocess(FRAME)
    assert tuple(x.shape) == (1, 3, *net_size) and 0.0 <= float(x.min()) <= float(x.max()) <= 1
    depth = model.predict([FRAME, FRAME[::-1].copy()])
    assert depth.shape == (2, *FRAME.shape[:2]) and np.isfinite(depth).all()
    assert depth.std() > 0
    assert {n for n, _ in model.net.named_children()} == (
        {"backbone", "neck", "head"} if name == "da" else {"dpt", "neck", "head"})
    assert model.encoder is (model.net.backbone if name == "da" else model.net.dpt)
    enc, dec = ({id(p) for p in part.parameters()} for part in (model.encoder, model.decoder))
    assert not enc & dec and enc | dec == {id(p) for p in model.parameters()}


def test_forward_normalises_like_the_processor(model_dirs):
    model = load(model_dirs, "da")
    x = model.preprocess(FRAME)
    mean = torch.tensor(DA_PROCESSOR["image_mean"]).view(1, 3, 1, 1)
    std = torch.tensor(DA_PROCESSOR["image_std"]).view(1, 3, 1, 1)
    with torch.no_grad():
        direct = model.net(pixel_values=(x - mean) / std).predicted_depth
        assert torch.equal(model(x)[:, 0], direct)


def test_normalisation_constants_are_buffers_outside_the_state_dict(model_dirs):
    """mean / std live on the model's device as buffers (a forward copies nothing from the
    host, which a CUDA graph capture refuses); the state dict keeps the network's own keys;
    a preprocessing with other constants is followed."""
    model = load(model_dirs, "da")
    names = {n for n, _ in model.named_buffers()}
    assert {"pixel_mean", "pixel_std"} <= names
    assert not {"pixel_mean", "pixel_std"} & set(model.state_dict())
    assert model.pixel_mean.flatten().tolist() == pytest.approx(DA_PROCESSOR["image_mean"])
    x = model.preprocess(FRAME)
    model.preprocessing = dataclasses.replace(model.preprocessing, mean=(0.0, 0.0, 0.0),
                                              std=(1.0, 1.0, 1.0))
    assert torch.equal(model.normalise(x), x * model.preprocessing.pixel_scale)
    assert model.pixel_std.flatten().tolist() == [1.0, 1.0, 1.0]


def test_input_size_sets_the_resize_target(model_dirs):
    model = load(model_dirs, "da", input_height=28, input_width=28)
    assert model.input_size == (28, 28)
    # aspect kept (130·0.7 = 91), sides to a multiple of 14 with Python's round as transformers
    # (91 / 14 = 6.5 rounds to 6: 84)
    assert tuple(model.preprocess(FRAME).shape[-2:]) == (28, 84)


def test_resize_rule_matches_the_dpt_processor():
    da = Preprocessing.from_processor({**DA_PROCESSOR, "size": {"height": 518, "width": 518}})
    assert da.output_size(480, 640) == (518, 686)  # Depth Anything's conversion script
    assert da.output_size(375, 1242) == (518, 1722)  # KITTI: the factor closer to 1
    assert da.output_size(168, 518) == (168, 518)
    dpt = Preprocessing.from_processor({"image_processor_type": "DPTImageProcessor"})
    assert dpt.output_size(375, 1242) == (384, 384) and dpt.mean == (0.5, 0.5, 0.5)
    glpn = Preprocessing.from_processor({"image_processor_type": "GLPNImageProcessor"})
    assert glpn.output_size(375, 1242) == (352, 1216) and glpn.mean is None


def test_output_kind_detection_and_override(model_dirs):
    from transformers import DepthAnythingConfig, DPTConfig, GLPNConfig, PretrainedConfig

    assert detect_output_kind(DepthAnythingConfig()) == "relative_inverse_depth"
    assert detect_output_kind(DepthAnythingConfig(depth_estimation_type="metric",
                                                  max_depth=80)) == "metric_depth"
    assert detect_output_kind(DPTConfig()) == "relative_inverse_depth"
    assert detect_output_kind(GLPNConfig()) == "metric_depth"
    with pytest.raises(ModelLoadError, match="output_kind"):
        detect_output_kind(PretrainedConfig())
    assert load(model_dirs, "da", output_kind="relative_depth").output_kind == "relative_depth"
    with pytest.raises(InputError, match="output_kind"):
        load(model_dirs, "da", output_kind="disparity")


def test_bad_model_paths_are_clear_errors(model_dirs, tmp_path):
    with pytest.raises(InputError, match="model_path"):
        build_model(ModelConfig(type="hf"))
    (tmp_path / "weights.bin").write_bytes(b"0")
    with pytest.raises(InputError, match="is a file"):
        build_model(ModelConfig(type="hf", model_path=str(tmp_path / "weights.bin")))
    with pytest.raises(ModelLoadError, match="cannot load"):
        build_model(ModelConfig(type="hf", model_path=str(tmp_path)))  # no config.json
    with pytest.raises(ModelLoadError, match="cannot load"):
        build_model(ModelConfig(type="hf", model_path="no-such-org/no-such-model"))


@pytest.mark.parametrize("name", ["da", "dpt"])
def test_norm_and_lora_select_far_fewer_parameters(model_dirs, name):
    model = load(model_dirs, name)
    encoder_size = sum(p.numel() for p in model.encoder.parameters())
    count = {mode: sum(p.numel() for p in trainable.select_trainable(model, mode, rank=2))
             for mode in trainable.TRAINABLE_MODES}  # in this order: lora is added last
    assert count["encoder"] == encoder_size
    assert count["norm"] < 0.05 * count["encoder"] and count["lora"] < 0.1 * count["encoder"]
    trainable_now = [p for p in model.parameters() if p.requires_grad]
    assert sum(p.numel() for p in trainable_now) == count["lora"]
    assert not any(p.requires_grad for p in model.decoder.parameters())


@pytest.mark.parametrize("name", ["da", "dpt"])
@pytest.mark.parametrize("mode", trainable.TRAINABLE_MODES)
def test_a_few_adam_steps_lower_the_loss(model_dirs, name, mode):
    model = load(model_dirs, name)
    x = model.preprocess(FRAME)
    with torch.no_grad():
        target = 1.3 * model(x) + 0.1
    params = trainable.select_trainable(model, mode, rank=4)
    optimizer = torch.optim.Adam(params, lr=3e-2)
    losses = []
    for _ in range(8):
        loss = (model(x) - target).abs().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    # norm on the tiny DPT is the slowest: ~0.7 % in 8 steps; a mode whose parameters do not
    # reach the output would not move the loss at all
    assert losses[-1] < 0.995 * losses[0], losses
    assert sum(b < a for a, b in zip(losses[:-1], losses[1:], strict=True)) >= 6, losses


def test_lora_starts_as_identity_and_merges_or_is_removed(model_dirs):
    model = load(model_dirs, "da")
    x = model.preprocess(FRAME)
    keys = set(model.encoder.state_dict())
    with torch.no_grad():
        original = model(x)
    params = trainable.select_trainable(model, "lora", rank=4)
    assert trainable.has_lora(model)
    with pytest.raises(InputError, match="already has LoRA"):
        trainable.add_lora(model)
    with torch.no_grad():
        assert torch.allclose(model(x), original, atol=1e-6)  # B = 0 at the start
        for p in params:
            p.add_(0.05 * torch.randn_like(p))
        adapted = model(x)
    assert not torch.allclose(adapted, original, atol=1e-4)
    assert reset_lora(model) > 0
    with torch.no_grad():
        assert torch.allclose(model(x), original, atol=1e-6)
        for p in params:
            p.add_(0.05 * torch.randn_like(p))
        adapted = model(x)
    assert trainable.merge_lora(model) > 0 and not trainable.has_lora(model)
    assert set(model.encoder.state_dict()) == keys
    with torch.no_grad():
        assert torch.allclose(model(x), adapted, atol=1e-5)
    fresh = load(model_dirs, "da")
    trainable.select_trainable(fresh, "lora", rank=4)
    with torch.no_grad():
        for p in fresh.parameters():
            if p.requires_grad:
                p.add_(0.05 * torch.randn_like(p))
    assert remove_lora(fresh) > 0
    with torch.no_grad():
        assert torch.equal(fresh(x), original)


def test_conv_encoders_refuse_lora_and_take_norm():
    model = MobileDepthNet()
    with pytest.raises(InputError, match="attention projections"):
        trainable.select_trainable(model, "lora")
    norm = trainable.select_trainable(model, "norm")
    bn = [m for m in model.encoder.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    assert len(norm) == 2 * len(bn) > 0
    with pytest.raises(InputError, match="trainable must be one of"):
        trainable.select_trainable(model, "decoder")


@pytest.mark.parametrize("frozen_stages", [0, 2])
def test_encoder_mode_is_the_papers_selection(frozen_stages):
    """'encoder' selects the encoder's parameters minus its first frozen stages, in the
    encoder's order, and nothing else requires grad (the paper's Sec. 3.3 selection, which
    refine_encoder used before it called select_trainable)."""
    model = MobileDepthNet()
    frozen = {id(p) for i in range(frozen_stages)
              for m in model.encoder.stage_modules(i) for p in m.parameters()}
    expected = [id(p) for p in model.encoder.parameters() if id(p) not in frozen]
    for p in model.parameters():
        p.requires_grad_(True)
    got = trainable.select_trainable(model, "encoder", frozen_stages=frozen_stages)
    assert [id(p) for p in got] == expected
    assert {id(p) for p in model.parameters() if p.requires_grad} == set(expected)


@pytest.mark.parametrize("mode", trainable.TRAINABLE_MODES)
def test_trainable_blocks_select_only_the_last_blocks(model_dirs, mode):
    model = load(model_dirs, "da")
    blocks = trainable.encoder_blocks(model.encoder)
    assert blocks == ["encoder.layer.0", "encoder.layer.1"]
    trainable.check_trainable(model, mode, 1)
    every = {id(p) for p in trainable.select_trainable(load(model_dirs, "da"), mode)}
    params = trainable.select_trainable(model, mode, rank=2, blocks=1)
    inside = {id(p) for p in model.encoder.get_submodule("encoder.layer.1").parameters()}
    assert params and {id(p) for p in params} <= inside
    assert len(params) < len(every)
    with pytest.raises(InputError, match="exceeds"):
        trainable.check_trainable(model, mode, 3)
    with pytest.raises(InputError, match="transformer encoder"):
        trainable.check_trainable(MobileDepthNet(), mode, 1)


def test_refine_encoder_runs_on_a_transformers_model(model_dirs):
    """The paper's refinement loop (encoder mode) on the adapter, targets in its own space."""
    model = load(model_dirs, "da")
    before = model.predict(FRAME)[0]
    original = snapshot_encoder(model)
    rng = np.random.default_rng(1)
    pixels = np.stack([rng.uniform(0, 129, 60), rng.uniform(0, 39, 60)], axis=1)
    target = 1.2 * before[pixels[:, 1].astype(int), pixels[:, 0].astype(int)] + 0.05
    sup = FrameSupervision("f0", FRAME, pixels, target, np.ones(60))
    result = refine_encoder(model, [sup], RefinementConfig(steps=8, lr=1e-3,
                                                           frozen_encoder_levels=0))
    assert result.steps_done == 8
    assert np.mean(result.loss_history[-2:]) < 0.9 * result.loss_history[0]
    assert not np.allclose(model.predict(FRAME)[0], before)
    restore_encoder(model, original)
    np.testing.assert_array_equal(model.predict(FRAME)[0], before)


def test_staged_depth_anything_matches_its_forward(model_dirs):
    """Depth Anything's blocks as stages (models/hf_stages.py): split at any stage, the staged
    forward gives the model's own output; DPT (no staged form here) keeps its backbone."""
    from sfm_ttr_ros.core.models.hf_stages import Dinov2Stages
    from sfm_ttr_ros.core.refinement.encoder import frozen_stage_count, unstaged_reason

    model = load(model_dirs, "da")
    stages = model.staged_encoder
    assert isinstance(stages, Dinov2Stages)
    assert (stages.num_stages, stages.level_stages) == (3, (2, 3))
    x = model.preprocess(FRAME)
    with torch.no_grad():
        whole = model(x)
        for split in range(stages.num_stages + 1):
            mid = stages.forward_stages(x, 0, split, [])
            _, feats = stages.forward_stages(mid[0] if split else x, split,
                                             stages.num_stages, mid[1])
            torch.testing.assert_close(model.depth_from_features(feats), whole,
                                       rtol=0, atol=1e-6)
    assert frozen_stage_count(stages, 1) == 2
    # its 2 feature maps: level 2 (the default) would leave none to train, and is refused
    with pytest.raises(InputError, match="below the encoder's 2 feature maps"):
        frozen_stage_count(stages, 2)
    dpt = load(model_dirs, "dpt")
    assert dpt.staged_encoder is dpt.encoder  # no stages: frozen levels train it whole
    assert frozen_stage_count(dpt.staged_encoder, 1) == 0
    assert "has no encoder stages" in unstaged_reason(dpt.staged_encoder, 1)


@pytest.mark.parametrize("mode", ["norm", "lora"])
def test_trainable_blocks_compute_the_blocks_before_them_once(model_dirs, monkeypatch, mode):
    """trainable_blocks = 1 on the 2-block tiny Depth Anything: the embedding and block 0 run
    once per frame, not per step, and the refined network is the one the whole forward at every
    step gives (same steps, same weights up to float rounding)."""
    from sfm_ttr_ros.core.refinement import encoder as refinement

    rng = np.random.default_rng(3)
    pixels = np.stack([rng.uniform(0, 129, 60), rng.uniform(0, 39, 60)], axis=1)
    sup = [FrameSupervision(f"f{i}", FRAME, pixels, rng.uniform(0.5, 2.0, 60), np.ones(60))
           for i in range(2)]
    cfg = RefinementConfig(steps=5, lr=1e-2, trainable=mode, lora_rank=2, trainable_blocks=1,
                           frozen_encoder_levels=0)  # the tiny model's 2 maps: blocks alone
    cached = load(model_dirs, "da")
    assert refinement.block_prefix_stages(cached, 1) == 2
    calls = []
    block0 = cached.staged_encoder.blocks[0]
    block0.register_forward_hook(lambda *a: calls.append(1))
    loss_cached = refine_encoder(cached, sup, cfg).loss_history
    assert len(calls) == len(sup)  # once per frame, not 5 steps
    monkeypatch.setattr(refinement, "block_prefix_stages", lambda model, blocks: 0)
    whole = load(model_dirs, "da")
    loss_whole = refine_encoder(whole, sup, cfg).loss_history
    np.testing.assert_allclose(loss_cached, loss_whole, rtol=1e-5)
    assert loss_cached[-1] != loss_cached[0]
    for (name, a), (_, b) in zip(cached.encoder.state_dict().items(),
                                 whole.encoder.state_dict().items(), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6, msg=name)
