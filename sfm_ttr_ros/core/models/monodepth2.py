"""Monodepth2 (Godard et al., ICCV 2019): ResNet encoder + depth decoder, loading the published
``encoder.pth`` / ``depth.pth`` pair unchanged.

File layout (also what :func:`save_monodepth2` writes, for any :class:`EncoderDecoder`):

* ``encoder.pth``: the encoder's state dict (``encoder.conv1.weight`` …, including the unused
  ``encoder.fc.*``) plus three plain entries ``height``, ``width`` and ``use_stereo``;
* ``depth.pth``: the decoder's state dict (``decoder.0.conv.conv.weight`` …).

Loading keeps only the model's own keys, as Monodepth2's own loader does.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import torch

from sfm_ttr_ros.core.models.base import EncoderDecoder, ModelLoadError
from sfm_ttr_ros.core.models.depth_decoder import (
    FINEST_SCALE_KEY,
    DepthDecoder,
    finest_scale_from_state,
)
from sfm_ttr_ros.core.models.resnet import RESNET_SPECS, ResnetEncoder

DEFAULT_INPUT_SIZE = (192, 640)
EXTRA_ENCODER_KEYS = ("height", "width", "use_stereo")


def check_input_size(input_size, multiple: int = 32) -> tuple[int, int]:
    """(height, width) as ints, both multiples of ``multiple`` and at least ``2 * multiple``
    (the decoder's reflection padding needs a 1/32 feature map of 2 x 2 or more)."""
    try:
        h, w = (int(v) for v in input_size)
    except (TypeError, ValueError) as exc:
        raise ModelLoadError(f"input_size must be (height, width), got {input_size!r}") from exc
    if h < 2 * multiple or w < 2 * multiple or h % multiple or w % multiple:
        raise ModelLoadError(f"input size {h}x{w} (h x w): both must be multiples of {multiple} "
                             f"and at least {2 * multiple} for this encoder-decoder")
    return h, w


class Monodepth2(EncoderDecoder):
    """Monodepth2's depth network (ResNet-``num_layers`` encoder, standard decoder).

    The decoder keeps all four disparity heads (so published weights load) but computes only
    scale 0 by default (``decoder.output_scales = (0,)``); set ``(0, 1, 2, 3)`` for multi-scale
    training.
    """

    def __init__(self, num_layers: int = 18, input_size: tuple[int, int] = DEFAULT_INPUT_SIZE,
                 pretrained: bool | str | Path = False):
        encoder = ResnetEncoder(num_layers, pretrained=pretrained)
        decoder = DepthDecoder(encoder.num_ch_enc, scales=range(4))
        decoder.output_scales = (0,)
        super().__init__(encoder, decoder, check_input_size(input_size))
        self.num_layers = int(num_layers)


# -- checkpoint files ---------------------------------------------------------------------------
def read_state_file(path: str | Path, what: str, map_location="cpu") -> dict:
    """``torch.load`` a state-dict file (tensors and plain numbers only), with clear errors."""
    path = Path(path)
    if not str(path) or not path.is_file():
        raise ModelLoadError(f"{what} file not found: {path}")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # truncated, corrupted, or not a torch file at all
        raise ModelLoadError(f"cannot read {what} file {path}: {type(exc).__name__}: "
                             f"{str(exc).splitlines()[0] if str(exc) else ''}") from exc
    if not isinstance(state, Mapping):
        raise ModelLoadError(f"{what} file {path} does not hold a state dict "
                             f"(got {type(state).__name__})")
    return dict(state)


def load_matching_state(module: torch.nn.Module, state: Mapping, what: str,
                        path: str | Path = "") -> None:
    """Load ``state`` into ``module`` keeping only the module's own keys; every module key must be
    present (``num_batches_tracked`` counters may be absent) with the same shape."""
    own = module.state_dict()
    where = f" ({path})" if path else ""
    missing = [k for k in own if k not in state and not k.endswith("num_batches_tracked")]
    if missing:
        unexpected = [k for k in state if k not in own and k not in EXTRA_ENCODER_KEYS]
        raise ModelLoadError(
            f"{what}{where} does not match the model's layout: {len(missing)} missing keys "
            f"(e.g. {missing[:4]}), {len(unexpected)} unexpected keys (e.g. {unexpected[:4]})")
    filtered = {}
    bad = []
    for k, v in state.items():
        if k not in own:
            continue
        if not isinstance(v, torch.Tensor):
            raise ModelLoadError(f"{what}{where}: entry {k!r} is not a tensor")
        if tuple(v.shape) != tuple(own[k].shape):
            bad.append(f"{k}: file {tuple(v.shape)} vs model {tuple(own[k].shape)}")
        filtered[k] = v
    if bad:
        raise ModelLoadError(f"{what}{where}: shape mismatch for {len(bad)} tensors, e.g. "
                             + "; ".join(bad[:4]))
    module.load_state_dict(filtered, strict=False)


def input_size_from_state(state: Mapping, default=DEFAULT_INPUT_SIZE) -> tuple[int, int]:
    """(height, width) stored in an ``encoder.pth``, or ``default`` when absent."""
    if "height" in state and "width" in state:
        return check_input_size((_plain_int(state["height"]), _plain_int(state["width"])))
    return check_input_size(default)


def _plain_int(v) -> int:
    if isinstance(v, torch.Tensor):
        v = v.item()
    return int(v)


def resnet_depth_from_state(state: Mapping) -> int:
    """ResNet depth (18, 34, 50, 101, 152) of a Monodepth2 encoder state dict."""
    if "encoder.conv1.weight" not in state:
        sample = [k for k in state if k not in EXTRA_ENCODER_KEYS][:4]
        raise ModelLoadError("not a Monodepth2 ResNet encoder state dict: no "
                             f"'encoder.conv1.weight' (keys e.g. {sample})")
    bottleneck = "encoder.layer1.0.conv3.weight" in state
    n3 = 0
    while f"encoder.layer3.{n3}.conv1.weight" in state:
        n3 += 1
    for depth, (blocks, kind) in RESNET_SPECS.items():
        if (kind == "bottleneck") == bottleneck and blocks[2] == n3:
            return depth
    raise ModelLoadError(f"cannot tell the ResNet depth: layer3 has {n3} "
                         f"{'bottleneck' if bottleneck else 'basic'} blocks")


def load_monodepth2(encoder_path: str | Path, decoder_path: str | Path,
                    num_layers: int | None = None, map_location="cpu") -> Monodepth2:
    """A :class:`Monodepth2` with the published ``encoder.pth`` / ``depth.pth`` weights.

    ``num_layers`` is read from the file when ``None``; ``input_size`` is the file's
    (height, width). The model comes back in eval mode on ``map_location``.
    """
    enc_state = read_state_file(encoder_path, "Monodepth2 encoder", map_location)
    dec_state = read_state_file(decoder_path, "Monodepth2 decoder", map_location)
    inferred = resnet_depth_from_state(enc_state)
    if num_layers is not None and int(num_layers) != inferred:
        raise ModelLoadError(f"{encoder_path} holds a ResNet-{inferred} encoder, "
                             f"not ResNet-{num_layers}")
    model = Monodepth2(inferred, input_size_from_state(enc_state))
    load_matching_state(model.encoder, enc_state, "Monodepth2 encoder", encoder_path)
    load_matching_state(model.decoder, dec_state, "Monodepth2 decoder", decoder_path)
    model.decoder.finest_scale = finest_scale_from_state(dec_state)
    if isinstance(map_location, str | torch.device):
        model = model.to(map_location)
    return model.eval()


def save_monodepth2(model: EncoderDecoder, encoder_path: str | Path,
                    decoder_path: str | Path) -> None:
    """Write ``model`` as a Monodepth2-layout pair: encoder state dict + height, width,
    use_stereo=False; decoder state dict. Works for any :class:`EncoderDecoder` (Monodepth2,
    MobileDepthNet)."""
    enc = {k: v.detach().cpu() for k, v in model.encoder.state_dict().items()}
    h, w = model.input_size
    enc.update(height=int(h), width=int(w), use_stereo=False)
    dec = {k: v.detach().cpu() for k, v in model.decoder.state_dict().items()}
    finest = int(getattr(model.decoder, "finest_scale", 0))
    if finest:
        dec[FINEST_SCALE_KEY] = finest
    for path, state in ((encoder_path, enc), (decoder_path, dec)):
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        torch.save(state, path)
