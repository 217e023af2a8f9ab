"""The window's sparse cloud as an output (``~/points``): every 3D point of the reconstruction
in the optical frame of the newest registered frame, in the depth outputs' units (the window's
fit ŝ: why it sits with the alignment, not the SfM)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from sfm_ttr_ros.core.alignment.affine import AffineAlignmentResult
from sfm_ttr_ros.core.alignment.scale import AlignmentResult
from sfm_ttr_ros.core.sfm.result import SfmResult


def window_cloud(sfm: SfmResult, registered: Sequence[str], fit: AlignmentResult,
                 metres_per_unit: float | None = None) -> tuple[str, np.ndarray, np.ndarray]:
    """(frame, xyz float32 M x 3, per-point reprojection error float32) of the cloud in
    ``registered[-1]``'s optical frame. Depth outputs are in network units (× ŝ) times the
    outputs' ``metres_per_unit`` (core/metric/scale.py ``in_metres``: ``metric.factor`` under
    ``fixed``; None = network units); an affine fit has no depth unit of its own: the cloud
    stays in SfM units, those of affine_to_depth(fit, prediction)."""
    newest = registered[-1]
    scale = 1.0 if isinstance(fit, AffineAlignmentResult) else fit.scale
    if metres_per_unit is not None and not isinstance(fit, AffineAlignmentResult):
        scale *= metres_per_unit
    xyz = sfm.points_in_frame(newest) * scale
    return newest, xyz.astype(np.float32), sfm.points_error.astype(np.float32)
