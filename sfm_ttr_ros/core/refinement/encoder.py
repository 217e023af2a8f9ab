"""Stage 4 of SfM-TTR: test-time refinement of the encoder on aligned sparse SfM depth.

Izquierdo & Civera, CVPR 2023, Sec. 3.3: Adam (lr 1e-4, 200 steps, one frame per step, frames
shuffled) over the ENCODER g only, the decoder h frozen, minimising each step's objective on
one frame (:mod:`~sfm_ttr_ros.core.refinement.objective`: Eq. (5), Ph-TTR or the hybrid).
Frames SfM did not register carry no supervision and are never used for training (they are still
predicted by the refined network afterwards). ``loss_history`` records each step's objective.

BatchNorm is an explicit choice (``bn_mode``): ``"frozen"`` keeps the running statistics and
normalises with them (modules in eval mode, affine parameters still trained); ``"train"`` puts
the encoder in train mode, so each single-image step normalises with its own statistics and
updates the running ones, as the authors' release most likely did.

Speed option (not in the paper): ``frozen_encoder_levels = L`` keeps the encoder fixed up to
and including its L-th feature map as well (L = 2: everything that produces the 1/2 and 1/4
maps; at most 4, so that the 1/32 stages always train). Those outputs (the image's early
features and skip connections) then do not change between steps, so they are computed once per
frame and each step runs only the remaining stages, the decoder and the backward pass through
them: at high resolution these are the costliest layers of a step. ``L = 0`` is the paper's
whole-encoder refinement (the default is 2, the real-footage setting). Stages are cached
through the model's ``staged_encoder`` when it implements the staged-encoder protocol
(``num_stages``, ``level_stages``, ``stage_modules(i)``, ``forward_stages(x, start, stop,
features)``), as the MobileNetV2 and ResNet encoders here do, and Depth Anything's DINOv2
backbone through :mod:`~sfm_ttr_ros.core.models.hf_stages` (its stages: the patch embedding,
then one per transformer block). There, ``trainable_blocks = N`` caches every block before the
last N the same way (:func:`block_prefix_stages`). With
``bn_mode="train"`` the frozen stages normalise with the frame's own statistics once (their
running statistics are updated once per frame, not once per step). An encoder without the
protocol (a plug-in, a transformer without stages) has no levels to keep fixed: with L > 0 its
whole encoder trains, as with L = 0, and :func:`unstaged_reason` says why (logged once per model,
kept in ``RefinementResult.frozen_levels_reason``); a value out of range for an encoder that has
stages is refused.
"""

from __future__ import annotations

import copy
import logging
import time
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Intrinsics
from sfm_ttr_ros.core.models.base import DepthModel, warm_up_image
from sfm_ttr_ros.core.refinement.graph_step import (
    GRAPH_WARM_UP_STEPS,
    StaticStepRunner,
    plan_step_mode,
)
from sfm_ttr_ros.core.refinement.objective import frame_terms, resolve_precision, step_loss
from sfm_ttr_ros.core.refinement.photometric import PhotometricFrame, prepare_frames
from sfm_ttr_ros.core.refinement.refinement_config import RefinementConfig, resolve_loss
from sfm_ttr_ros.core.refinement.supervision import FrameSupervision
from sfm_ttr_ros.core.refinement.trainable import merge_lora, select_trainable

LOG = logging.getLogger(__name__)
#: The staged-encoder protocol: what an encoder needs for ``frozen_encoder_levels`` to apply.
STAGED_ENCODER_PROTOCOL = ("num_stages", "level_stages", "stage_modules", "forward_stages")
_UNSTAGED_WARNED: weakref.WeakSet = weakref.WeakSet()  # models already told (once per model)


@dataclass
class RefinementResult:
    loss_history: list[float] = field(default_factory=list)  # each step's objective
    steps_done: int = 0
    cancelled: bool = False
    frames_used: int = 0
    seconds: float = 0.0
    # how the steps ran (core/refinement/graph_step.py): "eager", "static" or "graph"; and why
    # not "graph" when it is not ("" = captured; e.g. "not on CUDA (cpu)", "capture failed: ...")
    step_mode: str = ""
    step_mode_reason: str = ""
    # graph: host seconds spent capturing the step this window (re-arming an earlier window's
    # graph: ~0) and whether the graph was an earlier window's (core/refinement/graph_cache.py)
    capture_s: float = 0.0
    graph_reused: bool = False
    # the forward pass's number format that ran ("fp32" or "bf16", core/refinement/objective.py)
    # and why it is not refinement.precision ("" = as asked; bf16 on a device without it)
    precision: str = ""
    precision_reason: str = ""
    # why refinement.frozen_encoder_levels did not apply ("" = it did, or it is 0): an encoder
    # without encoder stages trains whole (unstaged_reason)
    frozen_levels_reason: str = ""


def set_bn_mode(model: DepthModel, bn_mode: str) -> None:
    """Encoder train/eval per ``bn_mode``; the decoder is always in eval mode."""
    model.eval()
    if bn_mode == "train":
        model.encoder.train()


def unstaged_reason(encoder: torch.nn.Module, frozen_levels: int) -> str:
    """Why ``frozen_levels`` does not apply to ``encoder`` ("" = it does, or it is 0): the
    encoder lacks the staged-encoder protocol, so it has no stages to keep fixed and trains
    whole."""
    missing = [a for a in STAGED_ENCODER_PROTOCOL if not hasattr(encoder, a)]
    if not frozen_levels or not missing:
        return ""
    return (f"frozen_encoder_levels = {frozen_levels} does not apply: "
            f"{type(encoder).__name__} has no encoder stages (it lacks {', '.join(missing)} "
            "of the staged-encoder protocol); its whole encoder trains")


def frozen_stage_count(encoder: torch.nn.Module, frozen_levels: int) -> int:
    """The number of leading encoder stages that ``frozen_levels`` feature maps need (0 for 0,
    and 0 for an encoder without the staged-encoder protocol: :func:`unstaged_reason`).

    Raises :class:`InputError` when a staged encoder has fewer feature maps than
    ``frozen_levels`` or would have no stage left to train."""
    if not frozen_levels or unstaged_reason(encoder, frozen_levels):
        return 0
    levels = tuple(int(k) for k in encoder.level_stages)
    if not 0 < frozen_levels < len(levels):
        raise InputError(f"frozen_encoder_levels must be below the encoder's {len(levels)} "
                         f"feature maps, got {frozen_levels}")
    stages = levels[frozen_levels - 1]
    if not 0 < stages < int(encoder.num_stages):
        raise InputError(f"{type(encoder).__name__}.level_stages {levels} does not leave a "
                         f"stage of its {encoder.num_stages} to train")
    return stages


def _say_unstaged_once(model: DepthModel, reason: str) -> None:
    """Log ``reason`` (:func:`unstaged_reason`) the first time ``model`` refines with it."""
    if reason and model not in _UNSTAGED_WARNED:
        _UNSTAGED_WARNED.add(model)
        LOG.warning(reason)


def block_prefix_stages(model: DepthModel, blocks: int) -> int:
    """With ``trainable_blocks = N`` on a staged transformer encoder (one with
    ``stages_before_last_blocks``, e.g. :class:`~sfm_ttr_ros.core.models.hf_stages.Dinov2Stages`)
    the leading stages that hold no trained parameter: computed once per frame, as frozen
    encoder levels are (the same weights after every step, less work per step); 0 otherwise."""
    staged = model.staged_encoder
    if not blocks or not hasattr(staged, "stages_before_last_blocks"):
        return 0
    return int(staged.stages_before_last_blocks(blocks))


def refine_encoder(model: DepthModel, supervision: Sequence[FrameSupervision],
                   config: RefinementConfig | None = None,
                   should_stop: Callable[[], bool] | None = None, *,
                   photometric: Sequence[PhotometricFrame] = (),
                   on_step: Callable[[int], None] | None = None) -> RefinementResult:
    """Run SfM-TTR's refinement in place on ``model``'s encoder (module docstring).

    ``config.loss`` picks a step's objective; ``photometric`` holds the window's
    :class:`~sfm_ttr_ros.core.refinement.photometric.PhotometricFrame` s (prepared once per
    window with the SfM poses), used by ``photometric`` and ``hybrid``. ``should_stop`` is
    polled between steps (cancellation); ``on_step(steps_done)`` is called after each step (the
    live server's interim weights). ``config.step_mode`` says how a step runs: eagerly, or on
    static buffers captured as one CUDA graph (:mod:`~sfm_ttr_ros.core.refinement.graph_step`;
    ``result.step_mode`` says which ran); ``config.precision`` the forward pass's number format
    (``result.precision`` what ran, fp32 where the device lacks bf16). Deterministic for a seed
    on CPU."""
    cfg = resolve_loss(config or RefinementConfig(), model, bool(photometric))
    cfg, precision_reason = resolve_precision(cfg, model.device)
    result = RefinementResult(precision=cfg.precision, precision_reason=precision_reason,
                              frozen_levels_reason=unstaged_reason(model.staged_encoder,
                                                                   cfg.frozen_encoder_levels))
    usable = _training_frames(supervision, photometric, cfg)
    result.frames_used = len(usable)
    if not usable or cfg.steps == 0:
        return result
    t0 = time.perf_counter()
    _say_unstaged_once(model, result.frozen_levels_reason)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    frozen = max(frozen_stage_count(model.staged_encoder, cfg.frozen_encoder_levels),
                 block_prefix_stages(model, cfg.trainable_blocks))
    params = select_trainable(model, cfg.trainable, cfg.lora_rank, frozen,
                              blocks=cfg.trainable_blocks)
    set_bn_mode(model, cfg.bn_mode)
    by_name = {f.name: f for f in photometric} if cfg.uses_photometric else {}
    # everything per frame that does not change between steps, prepared once
    frames = [frame_terms(model, s, frozen, cfg, by_name.get(s.name)) for s in usable]
    result.step_mode, result.step_mode_reason = plan_step_mode(model, frames, cfg)
    runner = None
    eager_losses: list[torch.Tensor] = []
    try:
        if result.step_mode == "eager":
            step = _eager_step(model, frames, params, frozen, cfg, eager_losses)
        else:
            runner = StaticStepRunner(model, frames, params, cfg, frozen,
                                      capture=result.step_mode == "graph")
            step = runner.step
        _run_steps(step, len(frames), cfg.steps, rng, result, should_stop, on_step)
    finally:
        if eager_losses:  # read back once: no host synchronisation inside the loop
            result.loss_history = torch.stack(eager_losses).tolist()
        if runner is not None:
            result.loss_history = runner.losses(result.steps_done)
            if runner.reason:  # the capture failed: the same step ran eagerly
                result.step_mode, result.step_mode_reason = runner.mode, runner.reason
            result.capture_s, result.graph_reused = runner.capture_s, runner.reused
            runner.close()
        model.eval()
        merge_lora(model)  # the encoder leaves with its own module tree and state_dict keys
        for p in model.parameters():
            p.requires_grad_(False)
    result.seconds = time.perf_counter() - t0
    return result


def _eager_step(model: DepthModel, frames: Sequence, params, frozen: int,
                cfg: RefinementConfig, losses: list[torch.Tensor]) -> Callable[[int], None]:
    """The eager step (the reference): one frame's objective, backward, Adam; each step's
    loss kept on its device in ``losses``."""
    photometric_cfg = cfg.photometric_config()
    optimizer = torch.optim.Adam(params, lr=cfg.lr)

    def step(frame: int) -> None:
        loss = step_loss(model, frames[frame], frozen, cfg, photometric_cfg)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        losses.append(loss.detach())

    return step


def _run_steps(step: Callable[[int], None], n_frames: int, steps: int,
               rng: np.random.Generator, result: RefinementResult,
               should_stop: Callable[[], bool] | None,
               on_step: Callable[[int], None] | None) -> None:
    """Sec. 3.3's loop: ``steps`` steps, one frame each, the frames shuffled per pass (seeded);
    cancellation polled between steps; ``on_step(steps_done)`` after each."""
    order: list[int] = []
    for _ in range(steps):
        if should_stop is not None and should_stop():
            result.cancelled = True
            break
        if not order:
            order = list(rng.permutation(n_frames))
        step(order.pop())
        result.steps_done += 1
        if on_step is not None:
            on_step(result.steps_done)


def _training_frames(supervision: Sequence[FrameSupervision],
                     photometric: Sequence[PhotometricFrame],
                     cfg: RefinementConfig) -> list[FrameSupervision]:
    """The window's frames a step may train on: with ``sfm`` and ``hybrid`` those with at least
    ``min_points`` selected SfM points (hybrid adds the photometric term where the frame has
    one); with ``photometric`` those with a photometric term (a registered neighbour)."""
    if cfg.loss == "photometric":
        names = {f.name for f in photometric}
        return [s for s in supervision if s.name in names]
    return [s for s in supervision if len(s) >= cfg.min_points]


def warm_up_optimiser() -> None:
    """Pay torch's one-time costs of the refinement path now, on a throw-away parameter.

    The first ``torch.optim`` step imports ``torch._dynamo`` and with it sympy (~800 modules,
    ~0.9 s of Python holding the GIL on these machines). Paid inside the refinement worker, that
    import stalls every other thread: live frames waited up to 0.6 s behind it. Call this before
    the worker and the live server start
    (:meth:`~sfm_ttr_ros.core.stream.refiner.StreamRefiner.start`); later calls are cheap. No
    model's weights are touched.
    """
    param = torch.nn.Parameter(torch.zeros(1, 1, 3, 3))
    optimizer = torch.optim.Adam([param], lr=1e-4)
    torch.nn.functional.conv2d(torch.zeros(1, 1, 8, 8), param).sum().backward()
    optimizer.step()
    optimizer.zero_grad(set_to_none=True)


#: Steps of :func:`warm_up_refinement`: the first loads the kernels, the second Adam's with state.
WARM_UP_STEPS = 2

def warm_up_refinement(model: DepthModel, config: RefinementConfig) -> float:
    """Pay the refinement's one-time costs on ``model``'s device in the CALLING thread, on a
    throw-away copy of ``model``; returns the seconds it took.

    On CUDA the first refinement of a process loads its kernels and each thread makes its own
    cuDNN and cuBLAS handles: on an H200 the first window took 9.9 s against 3.1–3.5 s for the
    next ones, and while it ran the live frames stalled for 1.5 s (BENCHMARKS.md "GPU"). Run by
    the window worker before it takes frames, these costs are paid at start-up. Two frames of
    grey at the network's input size, 1 unit apart sideways, a grid of SfM points at depth 1:
    :data:`WARM_UP_STEPS` steps of ``config``'s objective (Eq. (5), with the photometric term
    when ``config`` uses it); on CUDA ``GRAPH_WARM_UP_STEPS`` more
    (:mod:`~sfm_ttr_ros.core.refinement.graph_step`), so that the step's capture as a CUDA
    graph is paid too. ``model`` itself is not touched."""
    t0 = time.perf_counter()
    twin = copy.deepcopy(model)
    image = warm_up_image(twin)
    h, w = image.shape[:2]
    ys, xs = np.mgrid[h // 8:h:h // 4, w // 8:w:w // 4]
    pixels = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
    ones = np.ones(len(pixels), np.float64)
    frames = [FrameSupervision(name, image, pixels, ones, ones) for name in ("a", "b")]
    poses = {"a": np.eye(4), "b": np.eye(4)}
    poses["b"][0, 3] = -1.0
    cfg = copy.deepcopy(config)
    cfg.steps, cfg.min_points = WARM_UP_STEPS, 1
    if unstaged_reason(twin.staged_encoder, cfg.frozen_encoder_levels):
        cfg.frozen_encoder_levels = 0  # what the windows run; said by model's first window
    if twin.device.type == "cuda":  # past the eager steps before a capture: the graph's too
        cfg.steps += GRAPH_WARM_UP_STEPS
    photometric = (prepare_frames(twin, ["a", "b"], {"a": image, "b": image}, poses, 1.0,
                                  Intrinsics(w, w, (w - 1) / 2, (h - 1) / 2, w, h),
                                  cfg.photometric_config())
                   if cfg.uses_photometric else [])
    refine_encoder(twin, frames, cfg, photometric=photometric)
    if twin.device.type == "cuda":
        torch.cuda.synchronize(twin.device)
    return time.perf_counter() - t0


def snapshot_encoder(model: DepthModel) -> dict[str, torch.Tensor]:
    """A copy of the encoder's weights (and BN buffers) to reset to later."""
    return copy.deepcopy(model.encoder.state_dict())


def restore_encoder(model: DepthModel, state: dict[str, torch.Tensor]) -> None:
    model.encoder.load_state_dict(state)
