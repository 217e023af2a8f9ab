"""What one window takes and gives: the method's options (:class:`TTRConfig`), its outcome
(:class:`WindowResult`) and what its stages hand each other on the way through Fig. 2
(:class:`WindowState`); :class:`~sfm_ttr_ros.core.pipeline.SfmTTR` runs them."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from sfm_ttr_ros.core.alignment.scale import AlignmentConfig
from sfm_ttr_ros.core.checks.measures import CheckConfig
from sfm_ttr_ros.core.errors import InputError, check_choice
from sfm_ttr_ros.core.metric.metric_config import MetricConfig
from sfm_ttr_ros.core.refinement.refinement_config import WEIGHT_POLICIES, RefinementConfig
from sfm_ttr_ros.core.sfm.sfm_config import SfmConfig

if TYPE_CHECKING:  # the stages' results: annotations only (TTRConfig, read by the parameter
    # schema, imports the configs alone)
    from sfm_ttr_ros.core.alignment.scale import AlignmentResult
    from sfm_ttr_ros.core.alignment.window_alignment import WindowAlignment
    from sfm_ttr_ros.core.checks.measures import CheckReport
    from sfm_ttr_ros.core.frames import Frame, Intrinsics
    from sfm_ttr_ros.core.metric.scale import WindowMetric
    from sfm_ttr_ros.core.outcomes import Stop, Unrefined
    from sfm_ttr_ros.core.refinement.encoder import RefinementResult
    from sfm_ttr_ros.core.refinement.supervision import FrameSupervision
    from sfm_ttr_ros.core.sfm.result import SfmResult


@dataclass
class TTRConfig:
    sfm: SfmConfig = field(default_factory=SfmConfig)
    alignment: AlignmentConfig = field(default_factory=AlignmentConfig)
    refinement: RefinementConfig = field(default_factory=RefinementConfig)
    check: CheckConfig = field(default_factory=CheckConfig)  # core/checks/measures.py
    metric: MetricConfig = field(default_factory=MetricConfig)  # core/metric/
    # Weights across windows (WEIGHT_POLICIES): "continue" every window starts from the last
    # ACCEPTED window's weights (a refused or rolled-back window leaves them as they were;
    # measured best on real video: docs/decisions.md); "reset" from the start-up weights (the
    # paper's per-sequence refinement).
    weight_policy: str = "continue"
    # Roll a window back to the weights before it when its loss after refinement exceeds this
    # many times its loss before (or anything is non-finite); 0 = only the non-finite check.
    max_loss_ratio: float = 2.0
    min_supervision_points: int = 50  # fewer selected points in the window: do not refine
    # Frames per forward pass of the window's predictions (why 2 on CPU: docs/decisions.md,
    # "Memory", predictions two at a time).
    predict_batch: int = 2
    # Frames per forward pass when the model is on CUDA (0 = predict_batch): a window's
    # frames in one batched pass there (the GPU is launch-bound at small batches and has the
    # memory); the CPU keeps predict_batch.
    predict_batch_cuda: int = 16
    # Reuse a prediction made with the same weights for the same pixels instead of running the
    # network again (the overlap frames of consecutive windows: the previous window's refined
    # prediction is the next window's "before"). The same numbers as computing it again (up to
    # the last bits a different batch composition gives; bit for bit with predict_batch 1).
    # False: always recompute.
    reuse_predictions: bool = True
    # Take a window's "before" depths from the live server where it served the frame with the
    # very weights the window starts from (under weight_policy continue, after the window
    # before was accepted): core/prediction.py LiveDepths. Bit for bit with equal OpenMP teams
    # and predict_batch 1; ~1e-6 relative with the default teams (the live thread's is torch's,
    # the worker's worker_threads). False: the window predicts them itself.
    reuse_live_predictions: bool = True

    def __post_init__(self) -> None:
        check_choice("weight_policy", self.weight_policy, WEIGHT_POLICIES)
        if self.predict_batch_cuda < 0:
            raise InputError(f"predict_batch_cuda must be >= 0, got {self.predict_batch_cuda}")
        v = float(self.max_loss_ratio)
        if not (math.isfinite(v) and v >= 0):
            raise InputError(f"max_loss_ratio must be a finite number >= 0, got {v}")


@dataclass
class WindowResult:
    """Outcome of one window. ``depths`` are the published depths (refined when ``refined``)."""

    names: list[str]
    depths: dict[str, np.ndarray]
    depths_before: dict[str, np.ndarray]
    refined: bool
    reason: str = ""  # why the window was not refined, for people ("" when it was)
    reason_key: Unrefined | None = None  # what is counted when it was not refined (None: it was)
    check: CheckReport | None = None  # what the window checks measured
    # the refined weights' depths of a window a check refused after refining (for evaluation)
    depths_candidate: dict[str, np.ndarray] = field(default_factory=dict)
    sfm: SfmResult | None = None
    alignment: AlignmentResult | None = None
    refinement: RefinementResult | None = None
    metric: WindowMetric | None = None  # the window's metric estimate (core/metric/)
    scale: float = float("nan")
    loss_before: float = float("nan")
    loss_after: float = float("nan")
    cloud_frame: str = ""  # the registered frame whose optical frame the cloud is in
    cloud_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    cloud_error: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    timings: dict[str, float] = field(default_factory=dict)
    # the predictions before refining: computed, reused (the cache), reused_live (served live)
    predictions: dict[str, int] = field(default_factory=dict)

    @property
    def sfm_mapping(self) -> str:
        """How the window's SfM was mapped (its result's ``mapping``): "continued" (the
        streaming SfM's carried map) or "fresh" (mapped anew); "" in batch mode or before SfM
        ran."""
        return self.sfm.mapping if self.sfm is not None else ""

    @property
    def sfm_mapping_reason(self) -> str:
        """Why a fresh mapping replaced the continuation (its result's ``mapping_reason``)."""
        return self.sfm.mapping_reason if self.sfm is not None else ""

    def summary(self) -> dict:
        """The window's outcome as plain numbers (for JSON reports): ``reason_key`` the
        machine key of why it was not refined (an :class:`Unrefined` value; None when it was),
        ``reason`` the same for people."""
        return {
            "frames": len(self.names),
            "refined": self.refined,
            "reason": self.reason,
            "reason_key": None if self.reason_key is None else str(self.reason_key),
            "registered": self.sfm.num_registered if self.sfm else 0,
            "points": self.sfm.num_points if self.sfm else 0,
            "sfm_mapping": [self.sfm_mapping, self.sfm_mapping_reason],
            "scale": self.scale,
            "loss_before": self.loss_before,
            "loss_after": self.loss_after,
            "step_mode": ([self.refinement.step_mode, self.refinement.step_mode_reason]
                          if self.refinement is not None else None),
            "check": self.check.summary() if self.check else None,
            "predictions": dict(self.predictions),
        }


@dataclass
class WindowState:
    """One window on its way through Fig. 2: what each stage hands the next (the outcome so far
    in ``result``)."""

    frames: Sequence[Frame]
    intrinsics: Intrinsics
    result: WindowResult
    alignment: WindowAlignment | None = None  # the frames SfM registered, D_sfm, D_nn, the fit
    metric: WindowMetric | None = None  # metres per SfM / network unit (core/metric/)
    supervision: list[FrameSupervision] = field(default_factory=list)  # Eq. (5) per frame

    def __post_init__(self) -> None:
        self.images = {f.name: f.image for f in self.frames}

    @property
    def names(self) -> list[str]:
        return self.result.names

    @property
    def before(self) -> dict[str, np.ndarray]:
        """The depths of the weights before the window."""
        return self.result.depths_before

    @property
    def timings(self) -> dict[str, float]:
        return self.result.timings

    @property
    def registered(self) -> list[str]:
        return self.alignment.registered

    @property
    def scaled(self) -> bool:
        """The alignment is the paper's scale fit (depth up to scale)."""
        return self.alignment.scaled


def unrefined(res: WindowResult, stop: Stop,
               depths: dict[str, np.ndarray] | None = None) -> WindowResult:
    """``res`` as a window that is not refined, with why; ``depths`` (the depths before) are
    published instead of the refined weights' when given."""
    res.refined, res.reason, res.reason_key = False, stop.text, stop.key
    if depths is not None:
        res.depths = dict(depths)
    return res
