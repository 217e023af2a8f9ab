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
the paper's whole-encoder refinement. The model's ``staged_encoder`` must implement the
staged-encoder protocol (``num_stages``, ``level_stages``, ``stage_modules(i)``,
``forward_stages(x, start, stop, features)``), as the MobileNetV2 and ResNet encoders here do,
and Depth Anything's DINOv2 backbone through :mod:`~sfm_ttr_ros.core.models.hf_stages` (its
stages: the patch embedding, then one per transformer block). There, ``trainable_blocks = N``
caches every block before the last N the same way (:func:`block_prefix_stages`). With
``bn_mode="train"`` the frozen stages normalise with the frame's own statistics once (their
running statistics are updated once per frame, not once per step).

The objective (``loss``; not in the paper, whose Sec. 5-6 and Fig. 4 compare against
it): ``sfm`` is Eq. (5); ``photometric`` is photometric test-time refinement (Ph-TTR) with
Monodepth2's self-supervised loss, the poses taken from the window's SfM and brought into network
units with ŝ (:mod:`sfm_ttr_ros.core.refinement.photometric`); ``hybrid`` adds λ times that loss to
Eq. (5) (the paper's future work: photometric gradients where SfM has few points, near the camera).
``loss_history`` records the step objective (without any anchor term).
"""

from __future__ import annotations

import copy
import dataclasses
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from sfm_ttr_ros.core.alignment.affine import is_affine_output
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Intrinsics
from sfm_ttr_ros.core.models.base import DepthModel, warm_up_image
from sfm_ttr_ros.core.refinement.photometric import (
    PhotometricConfig,
    PhotometricFrame,
    ScaleOutput,
    parse_offsets,
    photometric_objective,
    prepare_frames,
    scale_outputs,
)
from sfm_ttr_ros.core.refinement.supervision import (  # noqa: F401 - frame_loss: part of this stage's API
    FrameSupervision,
    frame_loss,
    normalized_grid,
    sample_depth,
    weighted_l1,
)
from sfm_ttr_ros.core.refinement.trainable import TRAINABLE_MODES, merge_lora, select_trainable

BN_MODES = ("frozen", "train")
WEIGHTINGS = ("observation", "track", "none")
SAMPLINGS = ("bilinear", "nearest")
LOSSES = ("auto", "sfm", "photometric", "hybrid")  # a step's objective, see _step_loss
#: How the hybrid loss's SfM term measures a point's residual: "absolute" |ŝ·D_sfm − D_nn|
#: (Eq. (5)) or "relative" |ŝ·D_sfm − D_nn| / (ŝ·D_sfm), the same at 2 m and at 60 m.
SFM_RESIDUALS = ("absolute", "relative")
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
    # Which parameters a step trains (core/refinement/trainable.py): "encoder" (the paper),
    # "norm" (normalisation affine weights only) or "lora" (adapters of rank lora_rank on the
    # attention projections, merged into the encoder when the refinement ends);
    # trainable_blocks > 0: only inside the encoder's last N transformer blocks.
    trainable: str = "encoder"
    lora_rank: int = 8
    trainable_blocks: int = 0
    seed: int = 0
    # A step's objective (see _step_loss): "sfm" Eq. (5); "photometric" Monodepth2's
    # photometric + smoothness loss with the window's SfM poses (Ph-TTR); "hybrid" Eq. (5) +
    # photometric_weight · (photometric + smoothness); "auto" (the default) = "hybrid" with
    # the relative SfM residual and no parallax gate (the defaults below), measured best on
    # real video and sound on generated drives (BENCHMARKS.md), or "sfm" for a network whose
    # output is affine-invariant (no depth scale to warp with): resolve_loss.
    # params/paper.yaml holds the paper's Eq. (5). The photometric loss's α, smoothness weight
    # and source frames (offsets in the window, "-1,1" = t-1 and t+1) follow.
    loss: str = "auto"
    photometric_weight: float = 10.0  # λ: measured on the generated drive (BENCHMARKS.md)
    photometric_alpha: float = 0.85
    smoothness_weight: float = 1e-3
    photometric_sources: str = "-1,1"
    # hybrid only: the parallax gate of its photometric term (core/refinement/photometric.py), px
    # at the network's size, 0 = off; Ph-TTR (loss "photometric") stays Monodepth2's loss, ungated.
    hybrid_min_parallax: float = 0.0
    # hybrid only: its SfM term's residual (SFM_RESIDUALS): "relative" divides each point's
    # Eq. (5) term by its target ŝ·D_sfm, so that λ weighs the SfM and the photometric terms
    # alike near and far (Eq. (5)'s term is in depth units and grows with depth); "absolute"
    # = Eq. (5) as it is. Loss "sfm" is always the paper's Eq. (5).
    sfm_residual: str = "relative"

    def __post_init__(self) -> None:
        if self.sfm_residual not in SFM_RESIDUALS:
            raise InputError(f"sfm_residual must be one of {SFM_RESIDUALS}, got "
                             f"{self.sfm_residual!r}")
        if self.loss not in LOSSES:
            raise InputError(f"loss must be one of {LOSSES}, got {self.loss!r}")
        if not (np.isfinite(self.photometric_weight) and self.photometric_weight >= 0):
            raise InputError(f"photometric_weight must be a finite number >= 0, got "
                             f"{self.photometric_weight}")
        self.photometric_config()  # InputError on a bad alpha, smoothness weight or sources
        if self.steps < 0:
            raise InputError(f"steps must be >= 0, got {self.steps}")
        if self.trainable not in TRAINABLE_MODES:
            raise InputError(f"trainable must be one of {TRAINABLE_MODES}, got "
                             f"{self.trainable!r}")
        if self.lora_rank < 1 or self.trainable_blocks < 0:
            raise InputError(f"lora_rank must be >= 1 and trainable_blocks >= 0, got "
                             f"{self.lora_rank}, {self.trainable_blocks}")
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

    def photometric_config(self) -> PhotometricConfig:
        """The photometric loss's settings (:class:`PhotometricConfig`) these fields give; the
        parallax gate only for ``hybrid`` (``photometric`` is Monodepth2's loss as published)."""
        gate = self.hybrid_min_parallax if self.loss == "hybrid" else 0.0
        return PhotometricConfig(alpha=self.photometric_alpha,
                                 smoothness_weight=self.smoothness_weight,
                                 source_offsets=parse_offsets(self.photometric_sources),
                                 seed=self.seed, min_parallax=gate)

    @property
    def uses_photometric(self) -> bool:
        """Whether a step needs the window's photometric frames: ``photometric``, or
        ``hybrid`` with λ > 0 (λ = 0 is Eq. (5) alone, bit for bit)."""
        return self.loss == "photometric" or (self.loss == "hybrid"
                                              and self.photometric_weight > 0)


@dataclass
class RefinementResult:
    loss_history: list[float] = field(default_factory=list)
    steps_done: int = 0
    cancelled: bool = False
    early_stopped: bool = False
    frames_used: int = 0
    seconds: float = 0.0


def resolve_loss(config: RefinementConfig, model: DepthModel,
                 photometric_frames: bool = True) -> RefinementConfig:
    """``config`` with ``loss`` "auto" made concrete: "hybrid" (Eq. (5)'s SfM term with
    ``sfm_residual`` + λ·photometric) for a network that predicts depth up to scale, "sfm"
    (Eq. (5)) for one whose output is affine-invariant inverse depth (the photometric warp needs
    depth) or when no photometric frames are at hand (``photometric_frames`` False:
    :func:`refine_encoder` called with supervision alone); ``config`` itself when its loss is
    not "auto"."""
    if config.loss != "auto":
        return config
    photometric = photometric_frames and not is_affine_output(model)
    return dataclasses.replace(config, loss="hybrid" if photometric else "sfm")


def set_bn_mode(model: DepthModel, bn_mode: str) -> None:
    """Encoder train/eval per ``bn_mode``; the decoder is always in eval mode."""
    model.eval()
    if bn_mode == "train":
        model.encoder.train()


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
                   should_stop: Callable[[], bool] | None = None,
                   optimizer_state: dict | None = None, *,
                   replay: Sequence[FrameSupervision] = (), replay_ratio: float = 0.5,
                   anchor: dict[str, torch.Tensor] | None = None,
                   anchor_weight: float = 0.0,
                   photometric: Sequence[PhotometricFrame] = (),
                   on_step: Callable[[int], None] | None = None) -> RefinementResult:
    """Run SfM-TTR's refinement in place on ``model``'s encoder; returns the loss history.

    ``config.loss`` picks a step's objective (:func:`_step_loss`); ``photometric`` holds the
    window's :class:`~sfm_ttr_ros.core.refinement.photometric.PhotometricFrame` s (prepared once per
    window with the SfM poses, :func:`~sfm_ttr_ros.core.refinement.photometric.prepare_frames`),
    used by ``photometric`` and ``hybrid``.

    ``should_stop`` is polled between steps (cancellation); ``on_step(steps_done)`` is called
    after each step (the live server's interim weights). Deterministic for a seed on CPU.

    Continual refinement (not in the paper): with ``replay`` (frames of earlier windows) a step
    trains on a replayed frame with probability ``replay_ratio``, else on one of this window's;
    with ``anchor`` (an encoder state dict, the start-up weights θ₀) every step adds
    ``anchor_weight``·Σ‖θ − θ₀‖² over the trainable encoder parameters (L2-SP), so the weights
    drift from θ₀ only as far as the scene asks. ``loss_history`` records Eq. (5) alone.
    """
    cfg = resolve_loss(config or RefinementConfig(), model, bool(photometric))
    result = RefinementResult()
    usable = _training_frames(supervision, photometric, cfg)
    by_name = {f.name: f for f in photometric} if cfg.uses_photometric else {}
    photometric_cfg = cfg.photometric_config()
    result.frames_used = len(usable)
    if not usable or cfg.steps == 0:
        return result
    n_own = len(usable)
    usable += [s for s in replay if len(s) >= cfg.min_points]
    t0 = time.perf_counter()
    device = model.device
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)

    frozen = max(frozen_stage_count(model.staged_encoder, cfg.frozen_encoder_levels),
                 block_prefix_stages(model, cfg.trainable_blocks))
    params = select_trainable(model, cfg.trainable, cfg.lora_rank, frozen,
                              blocks=cfg.trainable_blocks)
    set_bn_mode(model, cfg.bn_mode)
    # Everything per frame that does not change between steps is prepared once: the sampling
    # grid, targets, weights and, for this window's frames, the input (with frozen leading
    # stages, their outputs). A replayed frame's input is made when a step draws it: with
    # replay_ratio 0.5 about half of 3 windows' frames are drawn, and caching all of them held
    # ~0.85 MB each (at 416x128) for the whole window.
    inputs, grids, targets, weights = [], [], [], []
    for k, s in enumerate(usable):
        h, w = s.image.shape[:2]
        inputs.append(_step_input(model, s, frozen) if k < n_own else None)
        grids.append(normalized_grid(s.pixels, w, h).to(device))
        targets.append(torch.as_tensor(s.target, dtype=torch.float32, device=device))
        residual = cfg.sfm_residual if cfg.loss == "hybrid" else "absolute"
        weights.append(torch.as_tensor(step_weights(s, residual), dtype=torch.float32,
                                       device=device))

    pull = _anchor_pairs(model, params, anchor) if anchor is not None and anchor_weight > 0 \
        else []
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
            if len(usable) > n_own and rng.random() < replay_ratio:
                j = int(rng.integers(n_own, len(usable)))
            else:
                if not order:
                    order = list(rng.permutation(n_own))
                j = order.pop()
            x = inputs[j] if inputs[j] is not None else _step_input(model, usable[j], frozen)
            loss = _step_loss(model, x, frozen, (grids[j], targets[j], weights[j]),
                              by_name.get(usable[j].name), cfg, photometric_cfg)
            total = loss
            if pull:
                total = loss + anchor_weight * sum(((p - p0) ** 2).sum() for p, p0 in pull)
            optimizer.zero_grad(set_to_none=True)
            total.backward()
            optimizer.step()
            value = float(loss.detach())
            result.loss_history.append(value)
            result.steps_done += 1
            if on_step is not None:
                on_step(result.steps_done)
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
        merge_lora(model)  # the encoder leaves with its own module tree and state_dict keys
        for p in model.parameters():
            p.requires_grad_(False)
    result.seconds = time.perf_counter() - t0
    return result


def step_weights(s: FrameSupervision, sfm_residual: str = "absolute") -> np.ndarray:
    """The per-point weights of a frame's SfM term in a step: exp(−r²) for Eq. (5)'s absolute
    residual; exp(−r²) / (ŝ·D_sfm) for the relative one, |ŝ·D_sfm − D_nn| / (ŝ·D_sfm) (the
    target is fixed during refinement, so the relative residual is Eq. (5) reweighted)."""
    w = np.asarray(s.weights, np.float64)
    if sfm_residual == "relative":
        return w / np.maximum(np.abs(np.asarray(s.target, np.float64)), 1e-6)
    return w


def _step_input(model: DepthModel, s: FrameSupervision, frozen_stages: int):
    """A frame's network input; with frozen leading stages their (output, features), computed
    without a graph (they never change during a refinement)."""
    x = model.preprocess(s.image)
    if frozen_stages:
        with torch.no_grad():
            x = model.staged_encoder.forward_stages(x, 0, frozen_stages, [])
    return x


def _anchor_pairs(model: DepthModel, params: Sequence[torch.nn.Parameter],
                  anchor: dict[str, torch.Tensor]) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """(θ, θ₀) for every trainable encoder parameter that ``anchor`` holds."""
    wanted = {id(p) for p in params}
    return [(p, anchor[name].to(p.device, p.dtype))
            for name, p in model.encoder.named_parameters()
            if id(p) in wanted and name in anchor]


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


def _step_loss(model: DepthModel, x, frozen_stages: int,
               sfm_term: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
               frame: PhotometricFrame | None, cfg: RefinementConfig,
               photometric_cfg: PhotometricConfig) -> torch.Tensor:
    """One step's objective on one frame, from one forward pass of the network:

    * ``sfm``: Eq. (5), L_j = mean_l exp(−r_lj²)·|ŝ·D_sfm(l, j) − D_nn(p_lj)| (``sfm_term`` =
      the frame's sampling grid, targets and weights);
    * ``photometric`` (Ph-TTR): Monodepth2's L_p + w_s·L_s
      (:mod:`~sfm_ttr_ros.core.refinement.photometric`) with the window's SfM poses scaled by ŝ;
    * ``hybrid``: Eq. (5) + λ·(L_p + w_s·L_s), λ = ``photometric_weight``.

    A frame without a photometric term (``frame`` None: no registered neighbour, a replayed
    frame of an earlier window, or hybrid with λ = 0) gets Eq. (5) alone."""
    grid, target, weight = sfm_term
    if frame is None or cfg.loss == "sfm":
        return weighted_l1(sample_depth(_forward(model, x, frozen_stages), grid, cfg.sampling),
                           target, weight)
    outputs = _scale_outputs(model, x, frozen_stages, photometric_cfg.scales)
    ph = photometric_objective(outputs, frame.target, frame.sources, frame.K, frame.poses,
                               photometric_cfg, frame.identity, frame.ssim_target).total
    if cfg.loss == "photometric":
        return ph
    sfm = weighted_l1(sample_depth(outputs[0].depth, grid, cfg.sampling), target, weight)
    return sfm + cfg.photometric_weight * ph


def _scale_outputs(model: DepthModel, x, frozen_stages: int,
                   scales: Sequence[int]) -> list[ScaleOutput]:
    """The photometric loss's depth / disparity per output scale from one forward pass; a
    model with its own ``forward`` (not encoder → decoder, e.g. a transformers model) gives
    its one output with disparity 1 / depth."""
    if type(model).forward is DepthModel.forward:
        return scale_outputs(model, _encode(model, x, frozen_stages), scales)
    if tuple(scales) != (0,):
        raise InputError(f"{type(model).__name__} has a single output scale, got {scales}")
    depth = _forward(model, x, frozen_stages)
    return [ScaleOutput(0, depth, 1.0 / depth)]


def _encode(model: DepthModel, x, frozen_stages: int):
    """g(I); with frozen leading stages ``x`` is their cached (output, features)."""
    if not frozen_stages:
        return model.encoder(x)
    enc = model.staged_encoder
    return enc.forward_stages(x[0], frozen_stages, enc.num_stages, x[1])[1]


def _forward(model: DepthModel, x, frozen_stages: int) -> torch.Tensor:
    """D_nn = h(g(I)); with frozen leading stages ``x`` is their cached (output, features)."""
    if not frozen_stages:
        return model(x)
    return model.depth_from_features(_encode(model, x, frozen_stages))


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
    when ``config`` uses it). ``model`` itself is not touched."""
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
    cfg.steps, cfg.min_points, cfg.early_stop_patience = WARM_UP_STEPS, 1, 0
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
