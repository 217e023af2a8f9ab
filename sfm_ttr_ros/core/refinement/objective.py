"""A refinement step's objective on one frame (``refinement.loss``).

* ``sfm``: the paper's Eq. (5) (Izquierdo & Civera, CVPR 2023, Sec. 3.3),

      L_j = 1/|S_j| Σ_l  exp(−r_lj²) · | ŝ·D_sfm(l, j) − D_nn(p_lj) |;

* ``photometric`` (Ph-TTR): Monodepth2's L_p + w_s·L_s with the window's SfM poses brought into
  network units with ŝ (:mod:`~sfm_ttr_ros.core.refinement.photometric`);
* ``hybrid``: Eq. (5)'s term + λ·(L_p + w_s·L_s), λ = ``photometric_weight`` (the paper's
  future work: photometric gradients where SfM has few points, near the camera); its SfM term
  divided by the target ŝ·D_sfm with ``sfm_residual: relative``.

A frame is prepared once per window (:func:`frame_terms`: the network input or, with frozen
leading encoder stages, their cached output; the sampling grid, targets and weights of its SfM
points); :func:`step_loss` then runs one forward pass and returns the frame's objective.

Precision (``refinement.precision``, not in the paper): with "bf16" the network's forward pass
of a step (and the frozen leading stages' cached output) runs under bfloat16 autocast
(:func:`network_precision`: one context, entered by :func:`objective`, which the eager and the
static / graph step share, and by the frozen stages' cache of :func:`step_input`); the
decoder's output is cast back to fp32 before it becomes depth, so the disparity-to-depth
conversion, Eq. (5), the photometric warp and the loss are fp32, as are the master weights and
Adam. A device without native bf16 runs fp32 instead
(:func:`resolve_precision`: the reason logged once and reported). "fp32" enters no autocast:
the numbers of the step before the option, bit for bit.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.geometry import normalized_grid, sample_depth
from sfm_ttr_ros.core.models.base import DepthModel
from sfm_ttr_ros.core.refinement.photometric import (
    PhotometricConfig,
    PhotometricFrame,
    ScaleOutput,
    photometric_objective,
    scale_outputs,
)
from sfm_ttr_ros.core.refinement.refinement_config import RefinementConfig
from sfm_ttr_ros.core.refinement.supervision import FrameSupervision, weighted_l1

LOG = logging.getLogger(__name__)
_WARNED: set[str] = set()


@dataclass
class FrameTerms:
    """What a step on one frame needs and that does not change between steps: the network
    input ``x`` (with frozen leading stages their (output, features)), the SfM points'
    sampling grid, Eq. (5) targets ŝ·D_sfm and weights, and the frame's photometric term
    (None: Eq. (5) alone)."""

    x: object
    grid: torch.Tensor
    target: torch.Tensor
    weight: torch.Tensor
    photometric: PhotometricFrame | None


def step_weights(s: FrameSupervision, sfm_residual: str = "absolute") -> np.ndarray:
    """The per-point weights of a frame's SfM term in a step: exp(−r²) for Eq. (5)'s absolute
    residual; exp(−r²) / (ŝ·D_sfm) for the relative one, |ŝ·D_sfm − D_nn| / (ŝ·D_sfm) (the
    target is fixed during refinement, so the relative residual is Eq. (5) reweighted)."""
    w = np.asarray(s.weights, np.float64)
    if sfm_residual == "relative":
        return w / np.maximum(np.abs(np.asarray(s.target, np.float64)), 1e-6)
    return w


def frame_terms(model: DepthModel, s: FrameSupervision, frozen_stages: int,
                cfg: RefinementConfig, photometric: PhotometricFrame | None) -> FrameTerms:
    """``s`` prepared for the steps of a window (on the model's device)."""
    device = model.device
    h, w = s.image.shape[:2]
    residual = cfg.sfm_residual if cfg.loss == "hybrid" else "absolute"
    return FrameTerms(
        x=step_input(model, s, frozen_stages, cfg),
        grid=normalized_grid(s.pixels, w, h).to(device),
        target=torch.as_tensor(s.target, dtype=torch.float32, device=device),
        weight=torch.as_tensor(step_weights(s, residual), dtype=torch.float32, device=device),
        photometric=photometric)


def step_input(model: DepthModel, s: FrameSupervision, frozen_stages: int,
               cfg: RefinementConfig | None = None):
    """A frame's network input; with frozen leading stages their (output, features), computed
    without a graph (they never change during a refinement) in the steps' precision."""
    x = model.preprocess(s.image)
    if frozen_stages:
        with torch.no_grad(), network_precision(model, cfg):
            x = model.staged_encoder.forward_stages(x, 0, frozen_stages, [])
    return x


def step_loss(model: DepthModel, terms: FrameTerms, frozen_stages: int, cfg: RefinementConfig,
              photometric_cfg: PhotometricConfig) -> torch.Tensor:
    """One step's objective on one frame (module docstring), from one forward pass of the
    network. A frame without a photometric term (no registered neighbour, or hybrid with
    λ = 0) gets Eq. (5) alone."""
    frame = terms.photometric

    def sfm_term(depth: torch.Tensor) -> torch.Tensor:
        return weighted_l1(sample_depth(depth, terms.grid, cfg.sampling), terms.target,
                           terms.weight)

    def photometric_term(outputs: list[ScaleOutput]) -> torch.Tensor:
        return photometric_objective(outputs, frame.target, frame.sources, frame.K_device,
                                     frame.poses_device, photometric_cfg, frame.identity,
                                     frame.ssim_target, K_inv=frame.K_inv).total

    with_photometric = frame is not None and cfg.loss != "sfm"
    return objective(model, terms.x, frozen_stages, cfg, photometric_cfg,
                     sfm_term if cfg.loss != "photometric" else None,
                     photometric_term if with_photometric else None)


def objective(model: DepthModel, x, frozen_stages: int, cfg: RefinementConfig,
              photometric_cfg: PhotometricConfig,
              sfm_term: Callable[[torch.Tensor], torch.Tensor] | None,
              photometric_term: Callable[[list[ScaleOutput]], torch.Tensor] | None,
              has_photometric: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. (5), Ph-TTR or Eq. (5) + λ·Ph-TTR (module docstring) from one forward pass:
    ``sfm_term(depth)`` Eq. (5) of the frame's points, ``photometric_term(outputs)`` its
    Ph-TTR total (None: the term is absent); ``has_photometric`` (0 or 1, a tensor) gates the
    photometric term of the hybrid without a host value (the step captured as a graph,
    core/refinement/graph_step.py). Shared by the eager and the captured step; the forward
    pass in ``cfg.precision`` (:func:`network_precision`), the terms in fp32."""
    if photometric_term is None:
        with network_precision(model, cfg):
            depth = forward(model, x, frozen_stages)
        return sfm_term(depth.float())
    with network_precision(model, cfg):
        outputs = network_outputs(model, x, frozen_stages, photometric_cfg.scales)
    outputs = [ScaleOutput(o.scale, o.depth.float(), o.disp.float()) for o in outputs]
    ph = photometric_term(outputs)
    if sfm_term is None:
        return ph
    if has_photometric is not None:
        ph = has_photometric * ph
    return sfm_term(outputs[0].depth) + cfg.photometric_weight * ph


def network_outputs(model: DepthModel, x, frozen_stages: int,
                   scales: Sequence[int]) -> list[ScaleOutput]:
    """The photometric loss's depth / disparity per output scale from one forward pass; a
    model with its own ``forward`` (not encoder → decoder, e.g. a transformers model) gives
    its one output with disparity 1 / depth."""
    if type(model).forward is DepthModel.forward:
        return scale_outputs(model, encode(model, x, frozen_stages), scales)
    if tuple(scales) != (0,):
        raise InputError(f"{type(model).__name__} has a single output scale, got {scales}")
    depth = forward(model, x, frozen_stages)
    return [ScaleOutput(0, depth, 1.0 / depth)]


def encode(model: DepthModel, x, frozen_stages: int):
    """g(I); with frozen leading stages ``x`` is their cached (output, features)."""
    if not frozen_stages:
        return model.encoder(x)
    enc = model.staged_encoder
    return enc.forward_stages(x[0], frozen_stages, enc.num_stages, x[1])[1]


def forward(model: DepthModel, x, frozen_stages: int) -> torch.Tensor:
    """D_nn = h(g(I)); with frozen leading stages ``x`` is their cached (output, features)."""
    if not frozen_stages:
        return model(x)
    return model.depth_from_features(encode(model, x, frozen_stages))


def bf16_unsupported(device: torch.device) -> str:
    """Why ``device`` cannot run a bf16 forward pass natively ("" = it can): on the CPU, torch
    must report AVX-512 BF16 or AMX (without them bf16 is emulated, far slower than fp32:
    docs/decisions.md, "Refinement"); on CUDA, ``torch.cuda.is_bf16_supported``."""
    if device.type == "cuda":
        return "" if torch.cuda.is_bf16_supported() else "this GPU has no native bf16"
    if device.type != "cpu":
        return f"no bf16 autocast on {device.type}"
    cpu = getattr(torch, "cpu", None)
    native = [name for name in ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
              if getattr(cpu, name, lambda: False)()]
    if native:
        return ""
    return (f"this CPU has neither AVX-512 BF16 nor AMX (torch's CPU capability: "
            f"{torch.backends.cpu.get_cpu_capability()}): bf16 would be emulated, slower than fp32")


def resolve_precision(cfg: RefinementConfig, device: torch.device
                      ) -> tuple[RefinementConfig, str]:
    """(``cfg`` with the precision the steps run in, the reason it is not the one asked for:
    "" = as asked). "bf16" on a device without native bf16 becomes "fp32", with one logged
    warning per reason."""
    if cfg.precision != "bf16" or not (why := bf16_unsupported(device)):
        return cfg, ""
    reason = f"precision bf16 runs as fp32: {why}"
    if reason not in _WARNED:
        _WARNED.add(reason)
        LOG.warning(reason)
    return dataclasses.replace(cfg, precision="fp32"), reason


def _as_fp32(output):
    """A decoder's output (a tensor, or a dict / sequence of them) in fp32."""
    if torch.is_tensor(output):
        return output.float() if output.is_floating_point() else output
    if isinstance(output, dict):
        return {k: _as_fp32(v) for k, v in output.items()}
    if isinstance(output, list | tuple):
        return type(output)(_as_fp32(v) for v in output)
    return output


@contextlib.contextmanager
def network_precision(model: DepthModel, cfg: RefinementConfig | None) -> Iterator[None]:
    """The network's forward pass in ``cfg.precision`` (module docstring): "bf16" under
    bfloat16 autocast on the model's device (its cache off: a CUDA graph may capture the step),
    the decoder's output cast back to fp32 (the disparity-to-depth conversion in fp32); "fp32"
    (or None) leaves everything as it is. The caller resolved the precision
    (:func:`resolve_precision`)."""
    if cfg is None or cfg.precision != "bf16":
        yield
        return
    hook = model.decoder.register_forward_hook(lambda _m, _i, out: _as_fp32(out))
    try:
        with torch.autocast(model.device.type, dtype=torch.bfloat16, cache_enabled=False):
            yield
    finally:
        hook.remove()
