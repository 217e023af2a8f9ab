"""The refinement's settings: :class:`RefinementConfig` (the node's ``refinement.*``
parameters) and how the ``auto`` objective becomes concrete for a model."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from sfm_ttr_ros.core.alignment.affine import is_affine_output
from sfm_ttr_ros.core.errors import InputError, check_choice
from sfm_ttr_ros.core.models.base import DepthModel
from sfm_ttr_ros.core.refinement.photometric import (
    ALPHA,
    SMOOTHNESS_WEIGHT,
    PhotometricConfig,
    parse_offsets,
)
from sfm_ttr_ros.core.refinement.trainable import TRAINABLE_MODES

BN_MODES = ("frozen", "train")
#: Where each window's weights start (``TTRConfig.weight_policy``, core/refinement/weights.py).
WEIGHT_POLICIES = ("reset", "continue")
WEIGHTINGS = ("observation", "track", "none")
SAMPLINGS = ("bilinear", "nearest")
#: A step's objective (core/refinement/objective.py): Eq. (5), Ph-TTR, or Eq. (5) + λ·Ph-TTR.
LOSSES = ("auto", "sfm", "photometric", "hybrid")
#: How the hybrid loss's SfM term measures a point's residual: "absolute" |ŝ·D_sfm − D_nn|
#: (Eq. (5)) or "relative" |ŝ·D_sfm − D_nn| / (ŝ·D_sfm), the same at 2 m and at 60 m.
SFM_RESIDUALS = ("absolute", "relative")
#: How a step runs (core/refinement/graph_step.py): "auto" = captured once per window as one
#: CUDA graph and replayed when the model is on CUDA and the capture works, else "eager";
#: "eager" = today's loop (the reference: one launch per op, the loss read back every step);
#: "static" = the step of the graph on static, padded buffers, run without capture (what a
#: graph replays, on any device: the numbers of "eager" up to the order of a sum).
STEP_MODES = ("auto", "eager", "static")
#: The number format of a step's forward pass (core/refinement/objective.py): "fp32"; "bf16" =
#: the network's forward under bfloat16 autocast (the loss, the weights and Adam stay fp32),
#: where the device computes bf16 natively, else fp32 with the reason (``bf16_unsupported``).
PRECISIONS = ("fp32", "bf16")
MAX_FROZEN_LEVELS = 4  # of an encoder's 5 feature maps (1/2 … 1/32): the 1/32 stages train


@dataclass
class RefinementConfig:
    steps: int = 70
    lr: float = 1e-4
    bn_mode: str = "frozen"
    weighting: str = "observation"  # exp(−r²) with r per observation, per track, or w = 1
    sampling: str = "bilinear"  # how D_nn is read at the keypoints (the release: nearest)
    min_points: int = 10  # frames with fewer selected points are not used for training
    frozen_encoder_levels: int = 2  # 1..4: encoder fixed up to its 1/2^L feature map (speed)
    # Which parameters a step trains (core/refinement/trainable.py): "encoder" (the paper),
    # "norm" (normalisation affine weights only) or "lora" (adapters of rank lora_rank on the
    # attention projections, merged into the encoder when the refinement ends);
    # trainable_blocks > 0: only inside the encoder's last N transformer blocks.
    trainable: str = "encoder"
    lora_rank: int = 8
    trainable_blocks: int = 0
    seed: int = 0
    # A step's objective (core/refinement/objective.py): "sfm" Eq. (5); "photometric"
    # Monodepth2's photometric + smoothness loss with the window's SfM poses (Ph-TTR);
    # "hybrid" Eq. (5) + photometric_weight · (photometric + smoothness); "auto" (the default)
    # = "hybrid", or "sfm" for a network whose output is affine-invariant (no depth scale to
    # warp with): resolve_loss. The photometric loss's α, smoothness weight and source frames
    # (offsets in the window, "-1,1" = t-1 and t+1) follow.
    loss: str = "auto"
    photometric_weight: float = 10.0  # λ
    photometric_alpha: float = ALPHA
    smoothness_weight: float = SMOOTHNESS_WEIGHT
    photometric_sources: str = "-1,1"
    # hybrid only: its SfM term's residual (SFM_RESIDUALS): "relative" divides each point's
    # Eq. (5) term by its target ŝ·D_sfm, so that λ weighs the SfM and the photometric terms
    # alike near and far (Eq. (5)'s term is in depth units and grows with depth); "absolute"
    # = Eq. (5) as it is. Loss "sfm" is always the paper's Eq. (5).
    sfm_residual: str = "relative"
    # How a step runs (STEP_MODES; a config field, not a node parameter): "auto" = one CUDA
    # graph per window on CUDA (eagerly the host launches every kernel of a step:
    # core/refinement/graph_step.py), eager elsewhere.
    step_mode: str = "auto"
    # The forward pass's number format (PRECISIONS): "bf16" runs the network under bfloat16
    # autocast in the eager and the static / graph step alike; fp32 where the device lacks it.
    precision: str = "fp32"

    def __post_init__(self) -> None:
        for name, value, allowed in (("bn_mode", self.bn_mode, BN_MODES),
                                     ("weighting", self.weighting, WEIGHTINGS),
                                     ("sampling", self.sampling, SAMPLINGS),
                                     ("loss", self.loss, LOSSES),
                                     ("sfm_residual", self.sfm_residual, SFM_RESIDUALS),
                                     ("step_mode", self.step_mode, STEP_MODES),
                                     ("precision", self.precision, PRECISIONS),
                                     ("trainable", self.trainable, TRAINABLE_MODES)):
            check_choice(name, value, allowed)
        if not (np.isfinite(self.photometric_weight) and self.photometric_weight >= 0):
            raise InputError(f"photometric_weight must be a finite number >= 0, got "
                             f"{self.photometric_weight}")
        self.photometric_config()  # InputError on a bad alpha, smoothness weight or sources
        if self.steps < 0:
            raise InputError(f"steps must be >= 0, got {self.steps}")
        if self.lora_rank < 1 or self.trainable_blocks < 0:
            raise InputError(f"lora_rank must be >= 1 and trainable_blocks >= 0, got "
                             f"{self.lora_rank}, {self.trainable_blocks}")
        if not 0 <= self.frozen_encoder_levels <= MAX_FROZEN_LEVELS:
            raise InputError(f"frozen_encoder_levels must lie in 0..{MAX_FROZEN_LEVELS}, got "
                             f"{self.frozen_encoder_levels}")
        if not (self.lr > 0 and np.isfinite(self.lr)):
            raise InputError(f"lr must be a positive number, got {self.lr}")

    def photometric_config(self) -> PhotometricConfig:
        """The photometric loss's settings (:class:`PhotometricConfig`) these fields give."""
        return PhotometricConfig(alpha=self.photometric_alpha,
                                 smoothness_weight=self.smoothness_weight,
                                 source_offsets=parse_offsets(self.photometric_sources),
                                 seed=self.seed)

    @property
    def uses_photometric(self) -> bool:
        """Whether a step needs the window's photometric frames: ``photometric``, or
        ``hybrid`` with λ > 0 (λ = 0 is Eq. (5) alone, bit for bit)."""
        return self.loss == "photometric" or (self.loss == "hybrid"
                                              and self.photometric_weight > 0)


def resolve_loss(config: RefinementConfig, model: DepthModel,
                 photometric_frames: bool = True) -> RefinementConfig:
    """``config`` with ``loss`` "auto" made concrete: "hybrid" (Eq. (5)'s SfM term with
    ``sfm_residual`` + λ·photometric) for a network that predicts depth up to scale, "sfm"
    (Eq. (5)) for one whose output is affine-invariant inverse depth (the photometric warp needs
    depth) or when no photometric frames are at hand (``photometric_frames`` False:
    :func:`~sfm_ttr_ros.core.refinement.encoder.refine_encoder` called with supervision
    alone); ``config`` itself when its loss is not "auto"."""
    if config.loss != "auto":
        return config
    photometric = photometric_frames and not is_affine_output(model)
    return dataclasses.replace(config, loss="hybrid" if photometric else "sfm")
