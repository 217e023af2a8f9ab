"""Stage 3 for one window (Sec. 3.2): the network's depth at the SfM keypoints of every
registered frame and one fit for the whole window (Eq. (4): the paper's scale, or scale and
shift in inverse depth for an affine-invariant network)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from sfm_ttr_ros.core.alignment.affine import AffineAlignmentResult, align_output, is_affine_output
from sfm_ttr_ros.core.alignment.scale import AlignmentConfig, AlignmentResult
from sfm_ttr_ros.core.geometry import sample_at
from sfm_ttr_ros.core.sfm.result import SfmResult


@dataclass
class WindowAlignment:
    """What the alignment of a window found."""

    registered: list[str]  # the frames SfM registered, in window order
    d_sfm: np.ndarray  # their D_sfm, concatenated
    d_nn: np.ndarray  # D_nn at the same pixels
    fit: AlignmentResult  # the scale fit, or an AffineAlignmentResult
    scaled: bool  # the paper's scale fit (depth up to scale): the scale checks' precondition


def align_window(sfm: SfmResult, names: Sequence[str], before: Mapping[str, np.ndarray],
                 model, config: AlignmentConfig, sampling: str) -> WindowAlignment:
    """D_nn(p_lj) of the depths ``before`` (sampled as ``sampling``) against D_sfm of the
    registered frames of ``names``, fitted as ``model``'s output needs (``output_kind``)."""
    reg = [n for n in names if n in sfm.frames]
    d_sfm = np.concatenate([sfm.frames[n].depths for n in reg])
    d_nn = np.concatenate([sample_at(before[n], sfm.frames[n].pixels, sampling) for n in reg])
    # The paper's scale fit; an affine fit in inverse depth for relative inverse-depth
    # networks (the targets are then in the network's own output space).
    fit = align_output(d_sfm, d_nn, getattr(model, "output_kind", ""), config,
                       [len(sfm.frames[n].depths) for n in reg])
    scaled = not isinstance(fit, AffineAlignmentResult) and not is_affine_output(model)
    return WindowAlignment(reg, d_sfm, d_nn, fit, scaled)
