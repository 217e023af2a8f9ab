"""Build a depth network from a small config: Monodepth2 files, the compact MobileNet network,
the embedded default weights, or any user factory (``"python:pkg.module:factory"``)."""

from __future__ import annotations

import importlib
import importlib.resources
import logging
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.models.base import DepthModel, ModelLoadError
from sfm_ttr_ros.core.models.mobilenet import (
    MobileDepthNet,
    is_mobilenet_state,
    load_mobile_depth_net,
)
from sfm_ttr_ros.core.models.monodepth2 import (
    Monodepth2,
    check_input_size,
    load_monodepth2,
    read_state_file,
)

log = logging.getLogger(__name__)

MODEL_TYPES = ("default", "monodepth2", "mobilenet", "hf", "python:<module>:<factory>")
DEFAULT_WEIGHTS_PACKAGE = "sfm_ttr_ros.core.models"
DEFAULT_ENCODER_FILE = "default_encoder.pth"
DEFAULT_DECODER_FILE = "default_depth.pth"


@dataclass
class ModelConfig:
    """Which network to run.

    ``type``: ``"default"`` (embedded trained weights), ``"monodepth2"`` (published
    ``encoder.pth`` / ``depth.pth`` in ``encoder_path`` / ``decoder_path``, or random weights
    when both are empty), ``"mobilenet"`` (MobileDepthNet from a pair written by
    ``save_monodepth2``, or random), ``"hf"`` (a transformers depth-estimation model, see
    :mod:`sfm_ttr_ros.core.models.hf`), or a plug-in ``"python:some.module:factory"`` (also
    plain ``"some.module:factory"``): ``factory(config)`` must return a ``DepthModel``.
    ``model_path``: for ``"hf"``, a directory written by ``save_pretrained`` or a hub id (its own
    field: ``encoder_path`` / ``decoder_path`` are state-dict files of two halves, a transformers
    model is one directory). ``output_kind``: for ``"hf"``, "" detects it from the model's
    config, else ``metric_depth``, ``relative_depth`` or ``relative_inverse_depth``.
    ``num_layers``: ResNet depth for a randomly initialised Monodepth2 (files say their own).
    ``input_height`` / ``input_width``: 0 keeps the model's own input size.
    ``device``: ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or ``"auto"`` (cuda when available).
    ``channels_last``: keep the 4-D weights in channels-last memory format, so that convolutions
    run channels-last (on 2 CPU cores ~13 % less time per refinement step; the outputs agree
    with the default format to ~1e-5 relative, not bit for bit).
    """

    type: str = "default"
    encoder_path: str = ""
    decoder_path: str = ""
    num_layers: int = 18
    input_height: int = 0
    input_width: int = 0
    device: str = "cpu"
    channels_last: bool = True
    model_path: str = ""
    output_kind: str = ""


def resolve_device(name: str) -> torch.device:
    """``"auto"`` → cuda if available else cpu; unknown or unavailable devices → InputError."""
    name = (name or "cpu").strip().lower()
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError) as exc:
        raise InputError(f"unknown device {name!r} (use cpu, cuda, cuda:N or auto)") from exc
    if device.type == "cuda" and not torch.cuda.is_available():
        raise InputError(f"device {name!r} requested but CUDA is not available "
                         "(use cpu or auto)")
    if device.type not in ("cpu", "cuda"):
        raise InputError(f"unsupported device {name!r} (use cpu, cuda, cuda:N or auto)")
    return device


def load_model_files(encoder_path: str | Path, decoder_path: str | Path,
                     map_location="cpu") -> DepthModel:
    """A Monodepth2-layout pair of files → :class:`Monodepth2` (ResNet keys ``encoder.*``) or
    :class:`MobileDepthNet` (MobileNetV2 keys ``features.*``), told apart by the keys."""
    state = read_state_file(encoder_path, "encoder", "cpu")
    if is_mobilenet_state(state):
        return load_mobile_depth_net(encoder_path, decoder_path, map_location)
    if "encoder.conv1.weight" in state:
        return load_monodepth2(encoder_path, decoder_path, map_location=map_location)
    sample = [k for k in state if k not in ("height", "width", "use_stereo")][:4]
    raise ModelLoadError(f"{encoder_path}: neither a Monodepth2 ResNet encoder nor a MobileNetV2 "
                         f"encoder state dict (keys e.g. {sample})")


def default_weights_available() -> bool:
    ref = importlib.resources.files(DEFAULT_WEIGHTS_PACKAGE) / "weights"
    return (ref / DEFAULT_ENCODER_FILE).is_file() and (ref / DEFAULT_DECODER_FILE).is_file()


def load_default_model(map_location="cpu") -> DepthModel:
    """The embedded trained default network (``sfm_ttr_ros/core/models/weights/default_*.pth``),
    read through ``importlib.resources`` so it works from an installed package."""
    ref = importlib.resources.files(DEFAULT_WEIGHTS_PACKAGE) / "weights"
    enc, dec = ref / DEFAULT_ENCODER_FILE, ref / DEFAULT_DECODER_FILE
    missing = [f"weights/{r.name}" for r in (enc, dec) if not r.is_file()]
    if missing:
        raise ModelLoadError(
            f"the embedded default model's weights are not installed ({', '.join(missing)} "
            f"missing from package {DEFAULT_WEIGHTS_PACKAGE}); train them first or choose "
            "model type 'monodepth2' / 'mobilenet' with encoder_path and decoder_path")
    with importlib.resources.as_file(enc) as enc_path, \
            importlib.resources.as_file(dec) as dec_path:
        return load_model_files(enc_path, dec_path, map_location)


def _paths(config: ModelConfig) -> tuple[str, str] | None:
    enc = str(config.encoder_path or "").strip()
    dec = str(config.decoder_path or "").strip()
    if bool(enc) != bool(dec):
        raise InputError("give both encoder_path and decoder_path, or neither "
                         f"(got encoder_path={enc!r}, decoder_path={dec!r})")
    return (enc, dec) if enc else None


def _load_plugin(config: ModelConfig) -> DepthModel:
    spec = config.type[len("python:"):] if config.type.startswith("python:") else config.type
    module_name, _, attr = spec.rpartition(":")
    if not module_name or not attr:
        raise ModelLoadError(f"plug-in model type must be 'python:<module>:<factory>', "
                             f"got {config.type!r}")
    try:
        module = importlib.import_module(module_name)
    except Exception as exc:
        raise ModelLoadError(f"cannot import plug-in module {module_name!r} "
                             f"({type(exc).__name__}: {exc})") from exc
    factory = getattr(module, attr, None)
    if not callable(factory):
        raise ModelLoadError(f"plug-in module {module_name!r} has no callable {attr!r}")
    model = factory(config)
    if not isinstance(model, DepthModel):
        raise ModelLoadError(f"plug-in factory {spec!r} returned {type(model).__name__}, not a "
                             "sfm_ttr_ros.core.models.base.DepthModel")
    for part in ("encoder", "decoder"):
        if not isinstance(getattr(model, part, None), nn.Module):
            raise ModelLoadError(f"plug-in model from {spec!r} has no nn.Module {part!r}")
    size = getattr(model, "input_size", None)
    if not (isinstance(size, tuple | list) and len(size) == 2
            and all(int(v) > 0 for v in size)):
        raise ModelLoadError(f"plug-in model from {spec!r} has no valid input_size "
                             f"(height, width): {size!r}")
    return model


def build_model(config: ModelConfig | None = None) -> DepthModel:
    """The network described by ``config``, on its device, in eval mode."""
    config = ModelConfig() if config is None else config
    device = resolve_device(config.device)
    kind = (config.type or "").strip()
    if ":" in kind:
        model = _load_plugin(config)
    elif kind.lower() == "default":
        model = load_default_model()
    elif kind.lower() == "monodepth2":
        paths = _paths(config)
        if paths:
            model = load_monodepth2(*paths)
            if model.num_layers != config.num_layers:
                log.info("num_layers=%d ignored: %s holds a ResNet-%d encoder",
                         config.num_layers, paths[0], model.num_layers)
        else:
            warnings.warn("model type 'monodepth2' without encoder_path/decoder_path: the "
                          "network has RANDOM weights", UserWarning, stacklevel=2)
            model = Monodepth2(config.num_layers)
    elif kind.lower() == "mobilenet":
        paths = _paths(config)
        if paths:
            model = load_mobile_depth_net(*paths)
        else:
            warnings.warn("model type 'mobilenet' without encoder_path/decoder_path: the "
                          "network has RANDOM weights", UserWarning, stacklevel=2)
            model = MobileDepthNet()
    elif kind.lower() == "hf":
        from sfm_ttr_ros.core.models.hf import from_config  # transformers only when asked for

        model = from_config(config)
    else:
        raise InputError(f"unknown model type {config.type!r}; choose one of {MODEL_TYPES}")

    h, w = int(config.input_height or 0), int(config.input_width or 0)
    if h or w:
        if not (h and w):
            raise InputError("set both input_height and input_width, or neither "
                             f"(got {h} x {w})")
        if isinstance(model, Monodepth2 | MobileDepthNet):
            model.input_size = check_input_size((h, w))
        else:
            model.input_size = (h, w)
    if config.channels_last:
        model = model.to(memory_format=torch.channels_last)
    return model.to(device).eval()
