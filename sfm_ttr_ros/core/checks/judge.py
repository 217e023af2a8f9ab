"""The window checks as one collaborator of the pipeline: when each runs, what it remembers.

:class:`WindowJudge` judges each window with the measures of :mod:`core/checks/measures
<sfm_ttr_ros.core.checks.measures>` (whose docstring gives the checks and their formulas) and keeps
what they compare with across windows: the last accepted window's camera path (the scale jump)
and the unsupported change of the last accepted windows. In the order a window meets them:

1. before refining: the sanity statistics and their verdict (:meth:`WindowJudge.before_refining`);
2. while refining: the interim gate, the unsupported change of interim weights on
   :func:`~sfm_ttr_ros.core.checks.measures.probe_frames` (:meth:`WindowJudge.arm_interim`,
   :meth:`WindowJudge.interim_refusal`);
3. after refining: the rollback reasons (non-finite loss or weights, ``max_loss_ratio``;
   :meth:`WindowJudge.rollback_reason`), then the unsupported change
   (:meth:`WindowJudge.after_refining`);
4. an accepted window becomes the reference of the next (:meth:`WindowJudge.accept`).
"""

from __future__ import annotations

import itertools
import math
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence

import numpy as np
from torch import nn

from sfm_ttr_ros.core.alignment.scale import AlignmentResult
from sfm_ttr_ros.core.checks.measures import (
    REPROJECTION_HISTORY,
    UNSUPPORTED_HISTORY,
    CheckConfig,
    CheckReport,
    PathReference,
    frame_scale_spread,
    parallax,
    path_reference,
    probe_frames,
    reprojection_refusal,
    sanity_check,
    scale_jump,
    track_length,
    unsupported_change,
    unsupported_refusal,
)
from sfm_ttr_ros.core.models.base import finite_state
from sfm_ttr_ros.core.outcomes import Unrefined
from sfm_ttr_ros.core.sfm.result import SfmResult

Depths = Mapping[str, np.ndarray]


class WindowJudge:
    """The checks of a stream's windows and the references they keep across windows."""

    def __init__(self) -> None:
        # the last accepted window's camera path in network units (the scale-jump check)
        self.path: PathReference | None = None
        self._previous: PathReference | None = None  # the reference of the running window
        # U of the last accepted windows: the reference of check.unsupported_change_ratio
        self.unsupported: deque[float] = deque(maxlen=UNSUPPORTED_HISTORY)
        # mean reprojection errors of the last accepted windows (check.max_reprojection_ratio)
        self.reprojection: deque[float] = deque(maxlen=REPROJECTION_HISTORY)
        self._interim: Callable[[], str] | None = None  # see interim_refusal()
        self.interim_unsupported = float("nan")  # U of the last interim weights checked
        self.interim_seconds = 0.0  # the window's time in interim checks (in its "refine")

    def begin_window(self) -> None:
        """A window begins: the scale jump compares with the window just before, when it was
        accepted."""
        self._previous, self.path = self.path, None

    # -- 1. before refining ------------------------------------------------------------------
    def before_refining(self, config: CheckConfig, sfm: SfmResult, registered: list[str],
                        d_sfm: np.ndarray, d_nn: np.ndarray, align: AlignmentResult,
                        scaled: bool) -> CheckReport:
        """The window's statistics and the verdict of the cheap checks
        (:func:`~sfm_ttr_ros.core.checks.measures.sanity_check`); the scale checks only when
        ``scaled`` (depth up to scale)."""
        t0 = time.perf_counter()
        c = CheckReport(reprojection_error=sfm.reprojection_error,
                        track_length=track_length(sfm, registered),
                        parallax=parallax(sfm, registered))
        if align.ransac_inliers.size:
            valid = np.isfinite(d_sfm) & np.isfinite(d_nn) & (d_sfm > 0) & (d_nn > 0)
            c.inlier_ratio = float(align.ransac_inliers.sum() / max(1, int(valid.sum())))
        if scaled:
            bounds = np.cumsum([0] + [len(sfm.frames[n].depths) for n in registered])
            parts = [slice(a, b) for a, b in itertools.pairwise(bounds)]
            c.scale_spread = frame_scale_spread([d_sfm[p] for p in parts],
                                                [d_nn[p] for p in parts])
            c.scale_jump = scale_jump(path_reference(sfm, registered, align.scale),
                                      self._previous)
        sanity_check(config, c)
        if not c.reason_key and (why := reprojection_refusal(config, c.reprojection_error,
                                                             self.reprojection)):
            c.reason_key, c.reason = Unrefined.CHECK_REPROJECTION, why
        c.seconds = time.perf_counter() - t0
        return c

    # -- 2. while refining: interim weights --------------------------------------------------
    def arm_interim(self, config: CheckConfig, before: Depths, images: Mapping[str, np.ndarray],
                    sfm: SfmResult, registered: list[str],
                    predict: Callable[[list[np.ndarray]], list[np.ndarray]],
                    rescale: bool) -> bool:
        """Whether the refining window's interim weights may be offered for serving: unchecked
        when no check runs after refinement, else only when the unsupported change can be
        re-measured on them (then :meth:`interim_refusal` does, with ``predict``: the network's
        depth of images as the weights are now)."""
        self.interim_seconds = 0.0
        self._interim = (self._interim_gate(config, before, images, sfm, registered, predict)
                         if config.after_refinement and rescale else None)
        return not config.after_refinement or self._interim is not None

    def disarm_interim(self) -> float:
        """The window's refinement is over: no interim gate; the seconds it took."""
        self._interim = None
        return self.interim_seconds

    def interim_refusal(self) -> str:
        """Why the refining window's current weights may not be served yet ("" = they may)."""
        gate = self._interim
        return gate() if gate is not None else ""

    def _interim_gate(self, config: CheckConfig, before: Depths, images: Mapping[str, np.ndarray],
                      sfm: SfmResult, registered: list[str],
                      predict: Callable[[list[np.ndarray]], list[np.ndarray]]
                      ) -> Callable[[], str]:
        probe = probe_frames(registered)
        pixels = {n: sfm.frames[n].pixels for n in probe}
        history = tuple(self.unsupported)

        def refusal() -> str:
            t0 = time.perf_counter()
            depths = predict([images[n] for n in probe])
            self.interim_unsupported = unsupported_change(
                before, dict(zip(probe, depths, strict=True)), pixels)
            why = unsupported_refusal(config, self.interim_unsupported, history)
            self.interim_seconds += time.perf_counter() - t0
            return why

        return refusal

    # -- 3. after refining -------------------------------------------------------------------
    @staticmethod
    def rollback_reason(max_loss_ratio: float, loss_history: Sequence[float],
                        loss_before: float, loss_after: float, encoder: nn.Module) -> str:
        """Why a refined window must not be kept ("" when it may): a non-finite loss or
        encoder weight, or a loss after refinement above ``max_loss_ratio`` x the loss before
        (the refinement exploded)."""
        history = np.asarray(loss_history, np.float64)
        bad = np.flatnonzero(~np.isfinite(history))
        if bad.size:
            return f"non-finite loss from step {bad[0] + 1} of {history.size}"
        if not math.isfinite(loss_after):
            return "non-finite loss after refining"
        if not finite_state(encoder.state_dict()):
            return "non-finite weights"
        if max_loss_ratio > 0 and loss_after > max_loss_ratio * loss_before:
            return (f"loss {loss_before:.4g} -> {loss_after:.4g} exceeds "
                    f"max_loss_ratio {max_loss_ratio:g}")
        return ""

    def after_refining(self, config: CheckConfig, check: CheckReport, before: Depths,
                       after: Depths, sfm: SfmResult, registered: list[str],
                       rescale: bool) -> CheckReport:
        """The refined weights' unsupported change (depth up to scale only) and the verdict
        (``check.reason_key``: None = accepted)."""
        t0 = time.perf_counter()
        c = check
        if rescale:
            c.unsupported_change = unsupported_change(
                before, after, {n: sfm.frames[n].pixels for n in registered})
        c.seconds += time.perf_counter() - t0
        if why := unsupported_refusal(config, c.unsupported_change, self.unsupported):
            c.reason_key, c.reason = Unrefined.CHECK_UNSUPPORTED_CHANGE, why
        return c

    # -- 4. the reference of the next window -------------------------------------------------
    def accept(self, check: CheckReport, sfm: SfmResult, registered: list[str], scale: float,
               scaled: bool) -> None:
        """An accepted window: its camera path (``scaled`` only), its unsupported change and its
        mean reprojection error are what the next windows are compared with."""
        self.path = path_reference(sfm, registered, scale) if scaled else None
        if math.isfinite(check.unsupported_change):
            self.unsupported.append(check.unsupported_change)
        if math.isfinite(check.reprojection_error):
            self.reprojection.append(check.reprojection_error)
