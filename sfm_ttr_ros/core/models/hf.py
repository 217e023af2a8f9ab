"""Any Hugging Face ``transformers`` depth-estimation model as a :class:`DepthModel`.

``AutoModelForDepthEstimation`` (Depth Anything V1/V2, DPT, GLPN, ZoeDepth, ...) loads from a
local directory written by ``save_pretrained`` or from a hub id through the normal
``from_pretrained`` cache (a local directory never touches the network; ``HF_HUB_OFFLINE=1``
makes hub ids cache-only too). The adapter gives it what SfM-TTR needs (Izquierdo & Civera,
CVPR 2023, Sec. 3.3: refine the encoder ``g``, keep the decoder ``h``):

* ``encoder``: the backbone (``backbone`` for Depth Anything / DPT-with-backbone / ZoeDepth, the
  base model for the others: ``dpt`` for plain-ViT DPT, ``glpn`` for GLPN), or the submodule named
  by ``encoder_module``. ``decoder``: every other module (neck, head).
* ``output_kind``: ``"metric_depth"`` (depth in metres), ``"relative_depth"`` (depth up to scale)
  or ``"relative_inverse_depth"`` (inverse depth up to scale AND shift: MiDaS / DPT / Depth
  Anything relative heads, aligned by :mod:`sfm_ttr_ros.core.alignment.affine`). Detected from
  the config (:func:`detect_output_kind`), or given. ``forward`` / ``predict`` return the raw
  prediction in that space (depth for the first two, affine inverse depth for the third).
* Preprocessing in torch (differentiable, no PIL): the model's image-processor rule read from its
  ``preprocessor_config.json`` (:class:`Preprocessing`): DPT-style resize to a target size, with
  ``keep_aspect_ratio`` (the factor closer to 1 for both sides) and sides rounded to the nearest
  ``ensure_multiple_of`` (Depth Anything: 518, keep aspect, 14), or GLPN's floor to a multiple of
  ``size_divisor``; rescale, then mean/std normalisation (ImageNet for Depth Anything).

``transformers`` is imported only when a model is loaded (extra ``hf``).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.models.base import DepthModel, ModelLoadError
from sfm_ttr_ros.core.models.hf_stages import Dinov2Stages, dinov2_stages

log = logging.getLogger(__name__)

OUTPUT_KINDS = ("metric_depth", "relative_depth", "relative_inverse_depth")
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
IMAGENET_STANDARD = (0.5, 0.5, 0.5)  # transformers' IMAGENET_STANDARD_MEAN / _STD (DPT default)
#: Model types whose depth checkpoints are MiDaS-style relative inverse depth.
RELATIVE_INVERSE_MODEL_TYPES = ("dpt",)
#: Model types that predict metric depth.
METRIC_MODEL_TYPES = ("glpn", "zoedepth", "depth_pro")
PROCESSOR_FILE = "preprocessor_config.json"
# PIL resampling codes → torch interpolation (Lanczos, box, Hamming: bicubic is the closest).
_RESAMPLE = {0: "nearest", 2: "bilinear", 3: "bicubic"}


@dataclass(frozen=True)
class Preprocessing:
    """An image processor's resize and normalisation, reproduced in torch.

    ``size``: the resize target (h, w); None keeps the image's own size (GLPN). ``multiple``:
    sides are rounded to it (to the nearest, as DPT's ``constrain_to_multiple_of``, or down with
    ``round_down``, as GLPN's ``size_divisor``). ``pixel_scale``: a [0, 1] pixel times this is
    the processor's rescaled value (255·rescale_factor; 255 when it does not rescale)."""

    size: tuple[int, int] | None = (518, 518)
    keep_aspect_ratio: bool = True
    multiple: int = 14
    round_down: bool = False
    mode: str = "bicubic"
    mean: tuple[float, ...] | None = IMAGENET_MEAN
    std: tuple[float, ...] | None = IMAGENET_STD
    pixel_scale: float = 1.0

    def output_size(self, height: int, width: int) -> tuple[int, int]:
        """The network's input size for an image of height x width (DPT / GLPN rule)."""
        if self.size is None:
            sh = sw = 1.0
        else:
            sh, sw = self.size[0] / height, self.size[1] / width
            if self.keep_aspect_ratio:  # scale as little as possible
                sh = sw = sw if abs(1 - sw) < abs(1 - sh) else sh
        return self._to_multiple(sh * height), self._to_multiple(sw * width)

    def _to_multiple(self, value: float) -> int:
        m = max(1, int(self.multiple))
        steps = math.floor(value / m) if self.round_down else round(value / m)
        return max(1, int(steps)) * m  # never 0 for a tiny image

    @classmethod
    def from_processor(cls, proc: dict) -> Preprocessing:
        """From a ``preprocessor_config.json`` dict (missing keys: the processor class's
        defaults: DPTImageProcessor's, or GLPNImageProcessor's for GLPN)."""
        glpn = "glpn" in str(proc.get("image_processor_type", "")).lower()
        mode = _RESAMPLE.get(int(proc.get("resample", 2 if glpn else 3)), "bicubic")
        if proc.get("do_pad"):
            log.warning("the image processor pads (do_pad); the adapter does not reproduce it")
        if proc.get("do_rescale", True):
            scale = 255.0 * float(proc.get("rescale_factor", 1 / 255))
        else:
            scale = 255.0
        mean = std = None
        if proc.get("do_normalize", not glpn):
            mean = _triple(proc.get("image_mean", IMAGENET_STANDARD))
            std = _triple(proc.get("image_std", IMAGENET_STANDARD))
        if not proc.get("do_resize", True):
            return cls(None, False, 1, False, mode, mean, std, scale)
        if glpn:
            return cls(None, False, int(proc.get("size_divisor", 32)), True, mode, mean, std,
                       scale)
        size = proc.get("size") or {"height": 384, "width": 384}
        if "height" not in size or "width" not in size:
            raise ModelLoadError(f"image processor size {size} is not supported (needs height "
                                 "and width)")
        return cls((int(size["height"]), int(size["width"])),
                   bool(proc.get("keep_aspect_ratio", False)),
                   int(proc.get("ensure_multiple_of", 1) or 1), False, mode, mean, std, scale)


def _triple(value) -> tuple[float, ...]:
    values = [float(v) for v in (value if isinstance(value, list | tuple) else [value])]
    return tuple(values * 3) if len(values) == 1 else tuple(values)


def default_preprocessing(config) -> Preprocessing:
    """No ``preprocessor_config.json``: Depth Anything V2's conversion settings (518, keep aspect,
    multiple of the patch size, bicubic, ImageNet mean/std), GLPN's floor to 32, or a square
    ``image_size`` input for plain-ViT DPT (its neck reshapes tokens to a square grid)."""
    model_type = getattr(config, "model_type", "")
    if model_type == "glpn":
        return Preprocessing(None, False, 32, True, "bilinear", None, None)
    patch = getattr(config, "patch_size", None)
    if not isinstance(patch, int):
        patch = getattr(getattr(config, "backbone_config", None), "patch_size", 14)
    if model_type == "dpt" and getattr(config, "backbone_config", None) is None:
        side = int(getattr(config, "image_size", 384))
        return Preprocessing((side, side), False, int(patch))
    return Preprocessing((518, 518), True, int(patch) if isinstance(patch, int) else 14)


def detect_output_kind(config) -> str:
    """What a transformers depth model predicts, from its config: ``depth_estimation_type``
    (Depth Anything: relative → affine inverse depth, metric → metres), the model type (DPT:
    MiDaS-style relative inverse depth; GLPN / ZoeDepth / Depth Pro: metric), or a numeric
    ``max_depth`` (a sigmoid·max_depth metric head). Anything else: :class:`ModelLoadError`
    asking for an explicit ``output_kind``."""
    estimation = getattr(config, "depth_estimation_type", None)
    if estimation == "relative":
        return "relative_inverse_depth"
    if estimation == "metric":
        return "metric_depth"
    model_type = getattr(config, "model_type", "")
    if model_type in RELATIVE_INVERSE_MODEL_TYPES:
        return "relative_inverse_depth"
    max_depth = getattr(config, "max_depth", None)
    if model_type in METRIC_MODEL_TYPES or (isinstance(max_depth, int | float)
                                            and not isinstance(max_depth, bool)):
        return "metric_depth"
    raise ModelLoadError(f"cannot tell what a {model_type!r} model predicts; set output_kind to "
                         f"one of {OUTPUT_KINDS}")


class _ModuleGroup(nn.Module):
    """Several modules of one network seen as one (the adapter's ``decoder``): for
    ``parameters()``, ``train()`` / ``eval()`` and ``state_dict()``; it is not run."""

    def __init__(self, modules: dict[str, nn.Module]):
        super().__init__()
        for name, module in modules.items():
            self.add_module(name.replace(".", "__"), module)

    def forward(self, *args, **kwargs):
        raise InputError("the decoder of a transformers model runs only inside the model's own "
                         "forward")


def _encoder_name(net: nn.Module, encoder_module: str) -> str:
    if encoder_module:
        name = encoder_module
    elif isinstance(getattr(net, "backbone", None), nn.Module):
        name = "backbone"
    else:
        name = getattr(net, "base_model_prefix", "")
        if not (name and isinstance(getattr(net, name, None), nn.Module)):
            raise ModelLoadError(f"cannot tell which part of {type(net).__name__} is the "
                                 "encoder; name its submodule with encoder_module")
    try:
        encoder = net.get_submodule(name)
    except AttributeError as exc:
        children = [n for n, _ in net.named_children()]
        raise ModelLoadError(f"{type(net).__name__} has no submodule {name!r} (top level: "
                             f"{children})") from exc
    if encoder is net or not any(True for _ in encoder.parameters()):
        raise ModelLoadError(f"encoder {name!r} of {type(net).__name__} must be a proper "
                             "submodule with parameters")
    return name


def _other_modules(net: nn.Module, encoder_name: str) -> dict[str, nn.Module]:
    """Every module that is not on the path to the encoder nor inside it."""
    parts = encoder_name.split(".")
    rest, parent = {}, net
    for depth, part in enumerate(parts):
        for name, child in parent.named_children():
            if name != part:
                rest[".".join([*parts[:depth], name])] = child
        parent = getattr(parent, part)
    return rest


class HFDepthModel(DepthModel):
    """A transformers depth-estimation model (``net``) behind the :class:`DepthModel` interface.

    ``input_size`` is the resize target of :attr:`preprocessing` (``()`` when the processor
    keeps the image's size); setting it changes the target, the processor's other rules (aspect
    ratio, multiple) still apply, so the network runs at ``preprocessing.output_size(H, W)``."""

    def __init__(self, net: nn.Module, preprocessing: Preprocessing, output_kind: str,
                 encoder_module: str = ""):
        super().__init__()
        if output_kind not in OUTPUT_KINDS:
            raise InputError(f"output_kind must be one of {OUTPUT_KINDS}, got {output_kind!r}")
        self.net = net
        self.output_kind = output_kind
        self.preprocessing = preprocessing
        # the processor's mean / std as buffers (not in the state dict): they move with the
        # model, and a forward copies nothing from the host (a CUDA graph capture refuses that)
        self.register_buffer("pixel_mean", _channels(preprocessing.mean), persistent=False)
        self.register_buffer("pixel_std", _channels(preprocessing.std), persistent=False)
        self._normalised_by = (preprocessing.mean, preprocessing.std)  # the buffers' values
        self.encoder_name = _encoder_name(net, encoder_module)
        # Not registered: its modules are net's own (one set of state_dict keys).
        object.__setattr__(self, "_decoder", _ModuleGroup(_other_modules(net,
                                                                          self.encoder_name)))
        self._stages: Dinov2Stages | bool | None = None  # built on first use

    @property
    def encoder(self) -> nn.Module:
        return self.net.get_submodule(self.encoder_name)

    @property
    def decoder(self) -> nn.Module:
        return self._decoder

    @property
    def input_size(self) -> tuple[int, ...]:
        return tuple(self.preprocessing.size or ())

    @input_size.setter
    def input_size(self, size) -> None:
        try:
            h, w = (int(v) for v in size)
        except (TypeError, ValueError) as exc:
            raise InputError(f"input_size must be (height, width), got {size!r}") from exc
        if h <= 0 or w <= 0:
            raise InputError(f"input_size must be positive, got {h} x {w}")
        self.preprocessing = replace(self.preprocessing, size=(h, w))

    def preprocess(self, images: np.ndarray | list[np.ndarray]) -> torch.Tensor:
        """uint8 RGB H x W x 3 image(s) of one size → N x 3 x h x w in [0, 1] at the processor's
        size (torch interpolation with antialiasing, clamped to [0, 1] like an 8-bit image)."""
        if isinstance(images, np.ndarray) and images.ndim == 3:
            images = [images]
        shapes = {tuple(np.shape(im)) for im in images}
        if len(shapes) != 1 or len(next(iter(shapes))) != 3 or next(iter(shapes))[2] != 3:
            raise InputError(f"images must be H x W x 3 RGB of one size, got shapes {shapes}")
        height, width = next(iter(shapes))[:2]
        x = torch.stack([torch.from_numpy(np.ascontiguousarray(im)).permute(2, 0, 1)
                         for im in images]).to(self.device, torch.float32) / 255.0
        size = self.preprocessing.output_size(height, width)
        if size != (height, width):
            mode = self.preprocessing.mode
            if mode == "nearest":
                x = F.interpolate(x, size=size, mode=mode)
            else:
                x = F.interpolate(x, size=size, mode=mode, align_corners=False, antialias=True)
                x = x.clamp(0.0, 1.0)
        return x

    def normalise(self, x: torch.Tensor) -> torch.Tensor:
        """A [0, 1] batch → the network's pixel values (the processor's rescale and
        mean/std normalisation)."""
        prep = self.preprocessing
        pixels = x * prep.pixel_scale if prep.pixel_scale != 1.0 else x
        if prep.mean is not None:
            if self._normalised_by != (prep.mean, prep.std):
                # the preprocessing was replaced with other constants: new buffers, once
                self.pixel_mean = _channels(prep.mean).to(x.device)
                self.pixel_std = _channels(prep.std).to(x.device)
                self._normalised_by = (prep.mean, prep.std)
            pixels = (pixels - self.pixel_mean.to(x.dtype)) / self.pixel_std.to(x.dtype)
        return pixels

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """The raw prediction N x 1 x h x w (in :attr:`output_kind`'s space) for a [0, 1] batch
        already at the network's size: rescale and normalise as the processor, run ``net``."""
        out = self.net(pixel_values=self.normalise(x), return_dict=True).predicted_depth
        return _at_size(out, tuple(x.shape[-2:]))

    def output_to_depth(self, output) -> torch.Tensor:
        return output

    @property
    def staged_encoder(self):
        """Depth Anything on a DINOv2 backbone: its blocks as stages
        (:class:`~sfm_ttr_ros.core.models.hf_stages.Dinov2Stages`); other models: the backbone
        itself, which lacks the staged-encoder protocol."""
        if self._stages is None:
            self._stages = dinov2_stages(self.net, self.normalise) or False
        return self._stages or self.encoder

    def depth_from_features(self, features) -> torch.Tensor:
        """The raw prediction from the staged features of :attr:`staged_encoder`."""
        stages = self.staged_encoder
        if not isinstance(stages, Dinov2Stages):
            raise InputError(f"{type(self.net).__name__} runs as one forward: "
                             "frozen_encoder_levels does not apply to it (use 0)")
        grid = features[0]
        return _at_size(stages.decode(features), (grid.height, grid.width))


def _channels(values: Sequence[float] | None) -> torch.Tensor | None:
    """Per-channel constants as a 1 x C x 1 x 1 float32 tensor (None stays None)."""
    if values is None:
        return None
    return torch.tensor(tuple(values), dtype=torch.float32).view(1, -1, 1, 1)


def _at_size(out: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """A model's N x h x w or N x 1 x h x w output as N x 1 x H x W (bilinear when resized)."""
    if out.dim() == 3:
        out = out.unsqueeze(1)
    if tuple(out.shape[-2:]) != tuple(size):
        out = F.interpolate(out, size=tuple(size), mode="bilinear", align_corners=False)
    return out


def read_processor_config(path: str, local_only: bool) -> dict | None:
    """The model's ``preprocessor_config.json`` as a dict, or None when it has none."""
    from transformers.utils import cached_file

    try:
        file = cached_file(path, PROCESSOR_FILE, local_files_only=local_only,
                           _raise_exceptions_for_missing_entries=False)
    except OSError:
        return None
    if not file:
        return None
    try:
        return json.loads(Path(file).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ModelLoadError(f"{file}: unreadable image processor config ({exc})") from exc


def load_hf_model(model_path: str, output_kind: str = "",
                  encoder_module: str = "") -> HFDepthModel:
    """A transformers depth model from a local directory or a hub id, as an
    :class:`HFDepthModel` in eval mode (float32, CPU). ``output_kind`` "" detects it."""
    path = str(model_path or "").strip()
    if not path:
        raise InputError("model type 'hf' needs model_path: a directory written by "
                         "save_pretrained or a hub id (e.g. "
                         "depth-anything/Depth-Anything-V2-Small-hf)")
    if output_kind and output_kind not in OUTPUT_KINDS:
        raise InputError(f"output_kind must be one of {OUTPUT_KINDS} or empty, got "
                         f"{output_kind!r}")
    try:
        from transformers import AutoModelForDepthEstimation
    except ImportError as exc:
        raise ModelLoadError("model type 'hf' needs transformers: pip install "
                             "'sfm_ttr_ros[hf]'") from exc
    local = Path(path).expanduser()
    if local.is_file():
        raise InputError(f"model_path {path!r} is a file: give the directory that holds "
                         "config.json and the weights")
    if local.is_dir():
        path = str(local)
    try:
        net = AutoModelForDepthEstimation.from_pretrained(path, local_files_only=local.is_dir(),
                                                          dtype=torch.float32)
    except (OSError, ValueError, KeyError) as exc:
        raise ModelLoadError(f"cannot load transformers depth model {path!r} "
                             f"({type(exc).__name__}: {exc}); nothing is downloaded when "
                             "offline: give a local directory or a hub id already in the "
                             "cache") from exc
    proc = read_processor_config(path, local.is_dir())
    if proc is None:
        prep = default_preprocessing(net.config)
        log.warning("%s has no %s: using %s", path, PROCESSOR_FILE, prep)
    else:
        prep = Preprocessing.from_processor(proc)
    kind = output_kind or detect_output_kind(net.config)
    return HFDepthModel(net.float().eval(), prep, kind, encoder_module)


def from_config(config) -> HFDepthModel:
    """Factory for ``build_model`` (``type: hf``) and for the plug-in form
    ``python:sfm_ttr_ros.core.models.hf:from_config``: ``config`` is a
    :class:`~sfm_ttr_ros.core.models.registry.ModelConfig` (not imported here: registry imports
    this module, and the import graph stays acyclic)."""
    return load_hf_model(config.model_path, getattr(config, "output_kind", ""))
