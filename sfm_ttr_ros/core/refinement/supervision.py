"""Stage 3 → 4 of SfM-TTR: the supervision of each registered frame.

After the scale alignment (Sec. 3.2, :mod:`sfm_ttr_ros.core.alignment.scale`) every selected SfM
observation of frame j gives a pixel p_lj, a target depth ŝ·D_sfm(l, j) in the network's units
and the confidence weight exp(−r_lj²) of Eq. (5). This module holds that per-frame record and
Eq. (5) itself (the depth read at those pixels, D_nn(p_lj), is
:func:`~sfm_ttr_ros.core.geometry.sample_depth`), so the refinement
(:mod:`sfm_ttr_ros.core.refinement.encoder`), the pipeline and the checks all read the same numbers.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from sfm_ttr_ros.core.alignment.affine import (
    AffineAlignmentResult,
    FrameAffineAlignment,
    affine_targets,
)
from sfm_ttr_ros.core.alignment.scale import AlignmentResult
from sfm_ttr_ros.core.geometry import normalized_grid, sample_depth
from sfm_ttr_ros.core.sfm.result import SfmResult


@dataclass
class FrameSupervision:
    """Supervision of one registered frame: pixels (OpenCV convention, image resolution),
    target depth ŝ·D_sfm in network units, per-point weights exp(−r²)."""

    name: str
    image: np.ndarray  # H x W x 3 uint8 RGB
    pixels: np.ndarray  # N x 2 (x, y)
    target: np.ndarray  # N
    weights: np.ndarray  # N

    def __len__(self) -> int:
        return int(self.target.shape[0])


def observation_weights(reproj_errors: np.ndarray) -> np.ndarray:
    """Eq. (5)'s confidence weight exp(−r²) of each observation."""
    return np.exp(-np.square(np.asarray(reproj_errors, np.float64)))


def weighted_l1(pred: torch.Tensor, target: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Eq. (5): mean of exp(−r²)·|ŝ·D_sfm − D_nn| over a frame's selected points."""
    return (weights * (pred - target).abs()).mean()


def padded_weighted_l1(pred: torch.Tensor, target: torch.Tensor, weights: torch.Tensor,
                       count: torch.Tensor) -> torch.Tensor:
    """Eq. (5) on a frame's points padded to a window's largest frame (the padding's weights
    0): Σ_l exp(−r²)·|ŝ·D_sfm − D_nn| / |S_j|, ``count`` = |S_j| a tensor (no host value: fit
    for a CUDA graph). :func:`weighted_l1` of the unpadded points up to the order of the sum;
    the gradients are the same (a padded point adds 0)."""
    return (weights * (pred - target).abs()).sum() / count


def frame_loss(depth: np.ndarray, s: FrameSupervision, mode: str = "bilinear") -> float:
    """Eq. (5) for one frame evaluated on a predicted depth map (any resolution), no grad."""
    d = torch.from_numpy(np.ascontiguousarray(depth, np.float32))[None, None]
    h, w = s.image.shape[:2]
    pred = sample_depth(d, normalized_grid(s.pixels, w, h), mode).numpy()
    return float(np.mean(s.weights * np.abs(pred - s.target))) if len(s) else float("nan")


def build_supervision(sfm: SfmResult, registered: Sequence[str],
                      images: dict[str, np.ndarray], align: AlignmentResult,
                      weighting: str = "observation") -> list[FrameSupervision]:
    """Split a window's selected points back into frames: target ŝ·D_sfm (network units; in
    inverse-depth space for an affine fit, :func:`supervision_targets`) and
    the Eq. (5) weight exp(−r²) with r per observation, per track, or w = 1 (``weighting``)."""
    sup, start = [], 0
    for k, n in enumerate(registered):
        obs = sfm.frames[n]
        sel = align.selected[start:start + len(obs)]
        start += len(obs)
        if weighting == "observation":
            w = observation_weights(obs.reproj_errors[sel])
        elif weighting == "track":
            w = observation_weights(obs.track_errors[sel])
        else:
            w = np.ones(int(sel.sum()))
        sup.append(FrameSupervision(n, images[n], obs.pixels[sel],
                                    supervision_targets(align, obs.depths[sel], k), w))
    return sup


def supervision_targets(align: AlignmentResult, d_sfm: np.ndarray, frame: int = 0) -> np.ndarray:
    """The targets of Eq. (5) in the network's output space: ŝ·D_sfm for the paper's scale
    fit; a/D_sfm + b for an affine fit of relative inverse depth
    (:func:`~sfm_ttr_ros.core.alignment.affine.affine_targets`; per-frame fits: frame
    ``frame``'s, none selected where it failed)."""
    if isinstance(align, FrameAffineAlignment):
        if not np.isfinite(align.frame_scale[frame]):
            return np.zeros(0)
        return affine_targets(align.frame(frame), d_sfm)
    if isinstance(align, AffineAlignmentResult):
        return affine_targets(align, d_sfm)
    return align.scale * d_sfm
