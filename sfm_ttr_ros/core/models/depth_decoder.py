"""Monodepth2's depth decoder, with the module layout of its published ``depth.pth`` files.

In Monodepth2 the ``OrderedDict`` of convolutions is registered as
``self.decoder = nn.ModuleList(list(self.convs.values()))``, so the state-dict keys are
``decoder.0`` … ``decoder.9`` for the ConvBlocks (4,0), (4,1), (3,0), (3,1), …, (0,0), (0,1)
(``decoder.N.conv.conv.{weight,bias}``) and ``decoder.10`` … ``decoder.13`` for the sigmoid
disparity heads of scales 0 … 3 (``decoder.N.conv.{weight,bias}``). This module reproduces that
order exactly; the lookup table from (kind, level) to index is a plain dict, not a module.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import torch
import torch.nn.functional as F
from torch import nn

from sfm_ttr_ros.core.models.base import ModelLoadError

DEFAULT_DECODER_CHANNELS = (16, 32, 64, 128, 256)
#: The decoder file's entry that records a ``finest_scale`` > 0 (absent: 0, Monodepth2's).
FINEST_SCALE_KEY = "finest_scale"


class Conv3x3(nn.Module):
    """Reflection-padded (or zero-padded) 3×3 convolution (Monodepth2's ``Conv3x3``)."""

    def __init__(self, in_channels: int, out_channels: int, use_refl: bool = True):
        super().__init__()
        self.pad = nn.ReflectionPad2d(1) if use_refl else nn.ZeroPad2d(1)
        self.conv = nn.Conv2d(int(in_channels), int(out_channels), 3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(self.pad(x))


class ConvBlock(nn.Module):
    """Conv3x3 followed by ELU (Monodepth2's ``ConvBlock``)."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        self.conv = Conv3x3(in_channels, out_channels)
        self.nonlin = nn.ELU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.nonlin(self.conv(x))


class DepthDecoder(nn.Module):
    """Monodepth2's ``DepthDecoder``.

    ``num_ch_enc``: channels of the encoder's 5 feature maps (1/2 … 1/32 of the input).
    ``scales``: the disparity heads that exist (Monodepth2: ``range(4)``; keep all four so that
    published weights load). ``num_ch_dec``: decoder widths per level (Monodepth2: 16 … 256).

    ``forward(features, scales=None)`` returns ``{("disp", s): sigmoid N x C x h_s x w_s}`` for the
    scales in ``scales`` or, when ``None``, in :attr:`output_scales` (defaults to every head).
    SfM-TTR needs scale 0 only: setting ``output_scales = (0,)`` skips the other heads.

    ``finest_scale`` > 0 (not Monodepth2's, which is 0): the decoder stops at that level and its
    ``("disp", 0)`` is the level's disparity bilinearly upsampled 2^finest_scale times (the
    full-resolution convolutions, the costliest per weight, are skipped; the level-0 modules
    stay in the layout, unused, so the file keeps Monodepth2's keys). Saved as the decoder
    file's ``finest_scale`` entry (:data:`FINEST_SCALE_KEY`).
    """

    def __init__(self, num_ch_enc: Sequence[int], scales: Iterable[int] = range(4),
                 num_output_channels: int = 1, use_skips: bool = True,
                 num_ch_dec: Sequence[int] = DEFAULT_DECODER_CHANNELS, finest_scale: int = 0):
        super().__init__()
        self.num_ch_enc = [int(c) for c in num_ch_enc]
        self.num_ch_dec = [int(c) for c in num_ch_dec]
        if len(self.num_ch_enc) != 5 or len(self.num_ch_dec) != 5:
            raise ValueError("DepthDecoder needs 5 encoder and 5 decoder channel counts, got "
                             f"{self.num_ch_enc} and {self.num_ch_dec}")
        self.scales = sorted(int(s) for s in scales)
        if any(s not in range(5) for s in self.scales):
            raise ValueError(f"decoder scales must lie in 0..4, got {self.scales}")
        self.num_output_channels = int(num_output_channels)
        self.use_skips = bool(use_skips)
        self.output_scales: tuple[int, ...] = tuple(self.scales)
        self.finest_scale = int(finest_scale)
        if self.finest_scale not in self.scales:
            raise ValueError(f"finest_scale {self.finest_scale} has no disparity head "
                             f"(scales {self.scales})")

        modules: list[nn.Module] = []
        self._index: dict[tuple[str, int, int], int] = {}
        for i in range(4, -1, -1):
            c_in = self.num_ch_enc[-1] if i == 4 else self.num_ch_dec[i + 1]
            self._index[("upconv", i, 0)] = len(modules)
            modules.append(ConvBlock(c_in, self.num_ch_dec[i]))
            c_in = self.num_ch_dec[i]
            if self.use_skips and i > 0:
                c_in += self.num_ch_enc[i - 1]
            self._index[("upconv", i, 1)] = len(modules)
            modules.append(ConvBlock(c_in, self.num_ch_dec[i]))
        for s in self.scales:
            self._index[("dispconv", s, 0)] = len(modules)
            modules.append(Conv3x3(self.num_ch_dec[s], self.num_output_channels))
        self.decoder = nn.ModuleList(modules)
        self.sigmoid = nn.Sigmoid()

    def forward(self, input_features: Sequence[torch.Tensor],
                scales: Iterable[int] | None = None) -> dict[tuple[str, int], torch.Tensor]:
        wanted = set(self.output_scales if scales is None else scales)
        unknown = wanted.difference(self.scales)
        if unknown:
            raise ValueError(f"no disparity head for scales {sorted(unknown)}; "
                             f"this decoder has {self.scales}")
        finest = self.finest_scale
        below = sorted(s for s in wanted if 0 < s < finest)
        if below:
            raise ValueError(f"scales {below} lie below this decoder's finest_scale {finest}")
        outputs: dict[tuple[str, int], torch.Tensor] = {}
        x = input_features[-1]
        for i in range(4, finest - 1, -1):
            x = self.decoder[self._index[("upconv", i, 0)]](x)
            x = [F.interpolate(x, scale_factor=2, mode="nearest")]
            if self.use_skips and i > 0:
                x.append(input_features[i - 1])
            x = torch.cat(x, 1)
            x = self.decoder[self._index[("upconv", i, 1)]](x)
            if i in wanted or (i == finest and 0 in wanted):
                disp = self.sigmoid(self.decoder[self._index[("dispconv", i, 0)]](x))
                if i in wanted:
                    outputs[("disp", i)] = disp
                if i == finest and finest > 0 and 0 in wanted:
                    outputs[("disp", 0)] = F.interpolate(disp, scale_factor=2 ** finest,
                                                         mode="bilinear", align_corners=False)
        return outputs


def finest_scale_from_state(state: dict) -> int:
    """The ``finest_scale`` a decoder file records (:data:`FINEST_SCALE_KEY`; absent: 0, a
    Monodepth2 file): every loader reads it here, so no layout drops it."""
    value = state.get(FINEST_SCALE_KEY, 0)
    if isinstance(value, torch.Tensor):
        value = value.item()
    if int(value) != value or not 0 <= int(value) <= 3:
        raise ModelLoadError(f"decoder file entry {FINEST_SCALE_KEY!r} must be 0..3, got "
                             f"{value!r}")
    return int(value)


def decoder_channels_from_state(state: dict[str, torch.Tensor]) -> tuple[int, ...] | None:
    """Decoder widths (level 0 … 4) of a Monodepth2-layout decoder state dict, or ``None``."""
    out = []
    for i in range(5):
        w = state.get(f"decoder.{2 * (4 - i)}.conv.conv.weight")
        if w is None or w.ndim != 4:
            return None
        out.append(int(w.shape[0]))
    return tuple(out)
