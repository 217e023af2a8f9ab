"""Stage 4 of SfM-TTR: test-time refinement of the encoder on aligned sparse SfM depth.

Izquierdo & Civera, CVPR 2023, Sec. 3.3, Eq. (5): for a frame j with selected points l,

    L_j = 1/|S_j| Σ_l  exp(−r_lj²) · | ŝ·D_sfm(l, j) − D_nn(p_lj) |

minimised with Adam (lr 1e-4, 200 steps, one frame per step, frames shuffled) over the
ENCODER g only; the decoder h is frozen. Frames SfM did not register carry no supervision and
are never used for training (they are still predicted by the refined network afterwards).

BatchNorm is an explicit choice (``bn_mode``): ``"frozen"`` keeps the running statistics and
normalises with them (modules in eval mode, affine parameters still trained); ``"train"`` puts
the encoder in train mode, so each single-image step normalises with its own statistics and
updates the running ones, as the authors' release most likely did.

Speed option (not in the paper): ``frozen_encoder_levels = L`` keeps the encoder fixed up to
and including its L-th feature map as well (L = 2: everything that produces the 1/2 and 1/4
maps; at most 4, so that the 1/32 stages always train). Those outputs (the image's early
features and skip connections) then do not change between steps, so they are computed once per
frame and each step runs only the remaining stages, the decoder and the backward pass through
them: at high resolution these are the costliest layers of a step. ``L = 0`` (the default) is
the paper's whole-encoder refinement. The encoder must implement the staged-encoder protocol
(``num_stages``, ``level_stages``, ``stage_modules(i)``, ``forward_stages(x, start, stop,
features)``), as the MobileNetV2 and ResNet encoders here do. With ``bn_mode="train"`` the
frozen stages normalise with the frame's own statistics once (their running statistics are
updated once per frame, not once per step).
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from sfm_ttr_ros.core.frames import InputError
from sfm_ttr_ros.core.models.base import DepthModel
from sfm_ttr_ros.core.supervision import (  # noqa: F401 - frame_loss: part of this stage's API
    FrameSupervision,
    frame_loss,
    normalized_grid,
    sample_depth,
    weighted_l1,
)

BN_MODES = ("frozen", "train")
WEIGHTINGS = ("observation", "track", "none")
SAMPLINGS = ("bilinear", "nearest")
MAX_FROZEN_LEVELS = 4  # of an encoder's 5 feature maps (1/2 … 1/32): the 1/32 stages train


@dataclass
class RefinementConfig:
    steps: int = 200
    lr: float = 1e-4
    bn_mode: str = "frozen"
    weighting: str = "observation"  # exp(−r²) with r per observation, per track, or w = 1
    sampling: str = "bilinear"  # how D_nn is read at the keypoints (the release: nearest)
    min_points: int = 10  # frames with fewer selected points are not used for training
    early_stop_patience: int = 0  # >0: stop when the running loss has not improved for N steps
    frozen_encoder_levels: int = 0  # 1..4: encoder fixed up to its 1/2^L feature map (speed)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.steps < 0:
            raise InputError(f"steps must be >= 0, got {self.steps}")
        if not 0 <= self.frozen_encoder_levels <= MAX_FROZEN_LEVELS:
            raise InputError(f"frozen_encoder_levels must lie in 0..{MAX_FROZEN_LEVELS}, got "
                             f"{self.frozen_encoder_levels}")
        if not (self.lr > 0 and np.isfinite(self.lr)):
            raise InputError(f"lr must be a positive number, got {self.lr}")
        for name, value, allowed in (("bn_mode", self.bn_mode, BN_MODES),
                                     ("weighting", self.weighting, WEIGHTINGS),
                                     ("sampling", self.sampling, SAMPLINGS)):
            if value not in allowed:
                raise InputError(f"{name} must be one of {allowed}, got {value!r}")


@dataclass
class RefinementResult:
    loss_history: list[float] = field(default_factory=list)
    steps_done: int = 0
    cancelled: bool = False
    early_stopped: bool = False
    frames_used: int = 0
    seconds: float = 0.0


def set_bn_mode(model: DepthModel, bn_mode: str) -> None:
    """Encoder train/eval per ``bn_mode``; the decoder is always in eval mode."""
    model.eval()
    if bn_mode == "train":
        model.encoder.train()


def trainable_parameters(model: DepthModel, frozen_stages: int = 0) -> list[torch.nn.Parameter]:
    """The encoder's parameters minus those of its first ``frozen_stages`` stages, with
    requires_grad on exactly them (no gradients are computed for the decoder or frozen stages)."""
    frozen = {id(p) for i in range(frozen_stages)
              for module in model.encoder.stage_modules(i) for p in module.parameters()}
    for p in model.decoder.parameters():
        p.requires_grad_(False)
    params = []
    for p in model.encoder.parameters():
        p.requires_grad_(id(p) not in frozen)
        if p.requires_grad:
            params.append(p)
    return params


def frozen_stage_count(encoder: torch.nn.Module, frozen_levels: int) -> int:
    """The number of leading encoder stages that ``frozen_levels`` feature maps need (0 for 0).

    Raises :class:`InputError` when the encoder does not implement the staged-encoder protocol
    or would have no stage left to train."""
    if not frozen_levels:
        return 0
    missing = [a for a in ("num_stages", "level_stages", "stage_modules", "forward_stages")
               if not hasattr(encoder, a)]
    if missing:
        raise InputError(f"frozen_encoder_levels = {frozen_levels} needs an encoder with "
                         f"{', '.join(missing)} (the staged-encoder protocol); "
                         f"{type(encoder).__name__} lacks it: use 0")
    levels = tuple(int(k) for k in encoder.level_stages)
    if not 0 < frozen_levels < len(levels):
        raise InputError(f"frozen_encoder_levels must be below the encoder's {len(levels)} "
                         f"feature maps, got {frozen_levels}")
    stages = levels[frozen_levels - 1]
    if not 0 < stages < int(encoder.num_stages):
        raise InputError(f"{type(encoder).__name__}.level_stages {levels} does not leave a "
                         f"stage of its {encoder.num_stages} to train")
    return stages


def refine_encoder(model: DepthModel, supervision: Sequence[FrameSupervision],
                   config: RefinementConfig | None = None,
                   should_stop: Callable[[], bool] | None = None,
                   optimizer_state: dict | None = None) -> RefinementResult:
    """Run SfM-TTR's refinement in place on ``model``'s encoder; returns the loss history.

    ``should_stop`` is polled between steps (cancellation). Deterministic for a seed on CPU.
    """
    cfg = config or RefinementConfig()
    result = RefinementResult()
    usable = [s for s in supervision if len(s) >= cfg.min_points]
    result.frames_used = len(usable)
    if not usable or cfg.steps == 0:
        return result
    t0 = time.perf_counter()
    device = model.device
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)

    frozen = frozen_stage_count(model.encoder, cfg.frozen_encoder_levels)
    params = trainable_parameters(model, frozen)
    set_bn_mode(model, cfg.bn_mode)
    # Everything per frame that does not change between steps is prepared once: the input, the
    # sampling grid, targets, weights and, with frozen leading stages, their outputs.
    inputs, grids, targets, weights = [], [], [], []
    for s in usable:
        h, w = s.image.shape[:2]
        x = model.preprocess(s.image)
        if frozen:
            with torch.no_grad():
                x = model.encoder.forward_stages(x, 0, frozen, [])
        inputs.append(x)
        grids.append(normalized_grid(s.pixels, w, h).to(device))
        targets.append(torch.as_tensor(s.target, dtype=torch.float32, device=device))
        weights.append(torch.as_tensor(s.weights, dtype=torch.float32, device=device))

    optimizer = torch.optim.Adam(params, lr=cfg.lr)
    if optimizer_state:
        optimizer.load_state_dict(optimizer_state)
    order: list[int] = []
    best, since_best, running = float("inf"), 0, None
    try:
        for _ in range(cfg.steps):
            if should_stop is not None and should_stop():
                result.cancelled = True
                break
            if not order:
                order = list(rng.permutation(len(usable)))
            j = order.pop()
            depth = _forward(model, inputs[j], frozen)
            pred = sample_depth(depth, grids[j], cfg.sampling)
            loss = weighted_l1(pred, targets[j], weights[j])
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            value = float(loss.detach())
            result.loss_history.append(value)
            result.steps_done += 1
            if cfg.early_stop_patience > 0:
                running = value if running is None else 0.9 * running + 0.1 * value
                if running < best * 0.999:
                    best, since_best = running, 0
                else:
                    since_best += 1
                    if since_best >= cfg.early_stop_patience:
                        result.early_stopped = True
                        break
    finally:
        model.eval()
        for p in model.parameters():
            p.requires_grad_(False)
    result.seconds = time.perf_counter() - t0
    return result


def _forward(model: DepthModel, x, frozen_stages: int) -> torch.Tensor:
    """D_nn = h(g(I)); with frozen leading stages ``x`` is their cached (output, features)."""
    if not frozen_stages:
        return model(x)
    enc = model.encoder
    return model.depth_from_features(enc.forward_stages(x[0], frozen_stages, enc.num_stages,
                                                        x[1])[1])


def snapshot_encoder(model: DepthModel) -> dict[str, torch.Tensor]:
    """A copy of the encoder's weights (and BN buffers) to reset to later."""
    return copy.deepcopy(model.encoder.state_dict())


def restore_encoder(model: DepthModel, state: dict[str, torch.Tensor]) -> None:
    model.encoder.load_state_dict(state)
