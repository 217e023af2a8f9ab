"""What comes out of the stream: each frame's depth (``FrameOutput``) and what each window did
(``WindowStats``: the core's :class:`~sfm_ttr_ros.core.pipeline.WindowResult` once, read
through, with what only the stream knows beside it)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from sfm_ttr_ros.core.frames import Frame
from sfm_ttr_ros.core.outcomes import Unrefined
from sfm_ttr_ros.core.pipeline import WindowResult

_NAN = float("nan")


@dataclass
class FrameOutput:
    """One frame out of the stream: its depth (network units, image size) and whether it was
    refined. ``depth`` is None for an unrefined frame the live output already served when
    ``StreamSettings.republish_unrefined`` is off (:attr:`live_only`): nothing to publish again."""

    frame: Frame
    depth: np.ndarray | None
    refined: bool
    reason_key: Unrefined | None = None
    reason: str = ""
    window: int | None = None  # index of the window that produced it
    # metres per network unit ``depth`` was multiplied by (core/metric/); None: network units
    metres_per_unit: float | None = None

    @property
    def live_only(self) -> bool:
        """Unrefined and not predicted again: its depth went out on the live output only."""
        return self.depth is None


def unrefined_result(names: list[str], key: Unrefined, reason: str) -> WindowResult:
    """The result of a window the stream itself did not refine (overload, cancelled, failed
    with an error): no depth, no stage ran."""
    return WindowResult(names, {}, {}, refined=False, reason=reason, reason_key=key)


@dataclass
class WindowStats:
    """What one window did (diagnostics, the node's cloud, the benchmark's windows).

    ``result`` is the core's record of the window without its depth maps (the history holds
    100 windows: 10 full-size maps each would grow memory for the whole first 100); every
    figure below is read from it, so none is kept twice. Beside it what only the stream knows:
    the window's index, its new frames, the steps configured, when it ran and the frame its
    cloud is in."""

    index: int
    new_frames: int
    result: WindowResult = field(repr=False)
    steps: int = 0  # configured refinement steps for this window
    # time.monotonic() when the worker began the window and when its outputs were ready
    started_at: float = _NAN
    finished_at: float = _NAN
    cloud_frame: Frame | None = field(default=None, repr=False)  # header and stamp, no pixels

    @classmethod
    def of(cls, index: int, new_frames: int, result: WindowResult, *, steps: int,
           started_at: float, cloud_frame: Frame | None = None) -> WindowStats:
        """Built once from the core's ``result``, its depth maps left out (class docstring)."""
        kept = dataclasses.replace(result, depths={}, depths_before={}, depths_candidate={},
                                   timings=dict(result.timings))
        return cls(index, new_frames, kept, steps, started_at, cloud_frame=cloud_frame)

    # -- the outcome ---------------------------------------------------------------------------
    @property
    def names(self) -> list[str]:
        return self.result.names

    @property
    def refined(self) -> bool:
        return self.result.refined

    @property
    def ok(self) -> bool:
        return self.refined

    @property
    def reason_key(self) -> Unrefined | None:
        """What is counted for the window's frames when it was not refined (None when it was)."""
        return None if self.refined else self.result.reason_key

    @property
    def reason(self) -> str:
        """Why the window was not refined, for people ("" when it was)."""
        return "" if self.refined else self.result.reason

    # -- SfM -----------------------------------------------------------------------------------
    @property
    def registered(self) -> int:
        return self.result.sfm.num_registered if self.result.sfm is not None else 0

    @property
    def points(self) -> int:
        return self.result.sfm.num_points if self.result.sfm is not None else 0

    @property
    def mapping_attempts(self) -> int:
        """Runs of the incremental mapper (``sfm.mapping_attempts``)."""
        return len(self.result.sfm.attempts) if self.result.sfm is not None else 0

    @property
    def reprojection_error(self) -> float:
        """Mean, px, of the reconstruction kept."""
        return self.result.sfm.reprojection_error if self.result.sfm is not None else _NAN

    # -- alignment and refinement --------------------------------------------------------------
    @property
    def inlier_ratio(self) -> float:
        a = self.result.alignment
        return float(np.mean(a.ransac_inliers)) if a is not None and a.ransac_inliers.size \
            else _NAN

    @property
    def selected_points(self) -> int:
        a = self.result.alignment
        return int(a.selected.sum()) if a is not None and a.ransac_inliers.size else 0

    @property
    def scale(self) -> float:
        return self.result.scale

    @property
    def loss_before(self) -> float:
        return self.result.loss_before

    @property
    def loss_after(self) -> float:
        return self.result.loss_after

    @property
    def steps_done(self) -> int:
        r = self.result.refinement
        return r.steps_done if r is not None else 0

    @property
    def step_mode(self) -> str:
        """How the steps ran (``RefinementResult.step_mode``): "eager", "static" or "graph",
        with the reason after a colon when it is not "graph" ("" = no step ran)."""
        r = self.result.refinement
        if r is None or not r.steps_done:
            return ""
        return f"{r.step_mode}: {r.step_mode_reason}" if r.step_mode_reason else r.step_mode

    # -- checks, metric scale, timings, cloud --------------------------------------------------
    @property
    def unsupported_change(self) -> float:
        """Share of the unsupported pixels moved (the check after refining)."""
        return self.result.check.unsupported_change if self.result.check is not None else _NAN

    @property
    def metric_estimate(self) -> float:
        """Metres per network unit of the window's own estimate (NaN: none; metric_reason
        says why)."""
        return self.result.metric.k if self.result.metric is not None else _NAN

    @property
    def metric_reason(self) -> str:
        return self.result.metric.reason if self.result.metric is not None else ""

    @property
    def timings(self) -> dict[str, float]:
        return self.result.timings

    @property
    def cloud_xyz(self) -> np.ndarray:
        """The sparse cloud in :attr:`cloud_frame`'s optical frame, network units."""
        return self.result.cloud_xyz

    @property
    def cloud_error(self) -> np.ndarray:
        return self.result.cloud_error
