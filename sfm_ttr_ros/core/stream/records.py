"""What comes out of the stream: each frame's depth (``FrameOutput``), what each window did
(``WindowStats``: the core's :class:`~sfm_ttr_ros.core.pipeline.WindowResult` once, read
through, with what only the stream knows beside it) and the camera's path it extended
(``FramePose``)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sfm_ttr_ros.core.alignment.scale import AlignmentResult
from sfm_ttr_ros.core.camera_path import PathPose
from sfm_ttr_ros.core.frames import Frame
from sfm_ttr_ros.core.outcomes import Unrefined
from sfm_ttr_ros.core.pipeline import WindowResult
from sfm_ttr_ros.core.refinement.encoder import RefinementResult

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


@dataclass(frozen=True)
class FramePose:
    """One frame's pose on the stream's camera path (core/camera_path.py: ``odom_from_camera``,
    covariance, how its window was chained) in the path's ``units`` when it joined ("m", or
    "sfm": the first reconstruction's units), and its ``frame`` without pixels (header and
    stamp: what the pose is stamped with)."""

    frame: Frame = field(repr=False)
    pose: PathPose
    units: str

    @property
    def name(self) -> str:
        return self.pose.name


def unrefined_result(names: list[str], key: Unrefined, reason: str) -> WindowResult:
    """The result of a window the stream itself did not refine (overload, cancelled, failed
    with an error): no depth, no stage ran."""
    return WindowResult(names, {}, {}, refined=False, reason=reason, reason_key=key)


def _read(name: str, doc: str = "") -> property:
    """``WindowStats.<name>``: the result's field of that name."""
    return property(lambda self: getattr(self.result, name), doc=doc)


def _stage(stage: str, read: Callable[[Any], Any], default: Any, doc: str = "") -> property:
    """A figure of one stage's record in the result (``sfm``, ``refinement``, ``check``,
    ``metric``): ``read`` of it, ``default`` when the window did not reach that stage."""
    def get(self: WindowStats) -> Any:
        record = getattr(self.result, stage)
        return default if record is None else read(record)
    return property(get, doc=doc)


def _inliers(a: AlignmentResult | None) -> tuple[float, int]:
    """(RANSAC inlier ratio, supervision points) of an alignment ((NaN, 0): none)."""
    if a is None or not a.ransac_inliers.size:
        return _NAN, 0
    return float(np.mean(a.ransac_inliers)), int(a.selected.sum())


def _step_mode(r: RefinementResult) -> str:
    """How the steps ran: "eager", "static" or "graph", with the reason after a colon when it
    is not "graph" ("" = no step ran)."""
    if not r.steps_done:
        return ""
    return f"{r.step_mode}: {r.step_mode_reason}" if r.step_mode_reason else r.step_mode


@dataclass
class WindowStats:
    """What one window did (diagnostics, the node's cloud, the benchmark's windows).

    ``result`` is the core's record of the window without its depth maps (the history holds
    100 windows: 10 full-size maps each would grow memory for the whole first 100); every
    figure below is read from it, so none is kept twice. Beside it what only the stream knows:
    the window's index, its new frames, the steps configured, when it ran, the frame its
    cloud is in and the poses it added to the stream's camera path."""

    index: int
    new_frames: int
    result: WindowResult = field(repr=False)
    steps: int = 0  # configured refinement steps for this window
    # time.monotonic() when the worker began the window and when its outputs were ready
    started_at: float = _NAN
    finished_at: float = _NAN
    cloud_frame: Frame | None = field(default=None, repr=False)  # header and stamp, no pixels
    # the camera's path: the poses this window added, in stamp (= publish) order (core/stream/
    # path.py); set after its depth outputs
    path_poses: list[FramePose] = field(default_factory=list, repr=False)

    @classmethod
    def of(cls, index: int, new_frames: int, result: WindowResult, *, steps: int,
           started_at: float, cloud_frame: Frame | None = None) -> WindowStats:
        """Built once from the core's ``result``, its depth maps left out (class docstring)."""
        kept = dataclasses.replace(result, depths={}, depths_before={}, depths_candidate={},
                                   timings=dict(result.timings))
        return cls(index, new_frames, kept, steps, started_at, cloud_frame=cloud_frame)

    @property
    def reason_key(self) -> Unrefined | None:
        """What is counted for the window's frames when it was not refined (None when it was)."""
        return None if self.refined else self.result.reason_key

    @property
    def reason(self) -> str:
        """Why the window was not refined, for people ("" when it was)."""
        return "" if self.refined else self.result.reason

    names = _read("names")
    refined = _read("refined")
    ok = _read("refined", "Whether the window was refined.")
    scale = _read("scale", "ŝ of the scale alignment (Eq. 4).")
    loss_before = _read("loss_before")
    loss_after = _read("loss_after")
    timings = _read("timings")
    predictions = _read("predictions", "The predictions before refining: computed, reused "
                        "(the cache), reused_live (the live server's, core/prediction.py).")
    cloud_xyz = _read("cloud_xyz", "The sparse cloud in cloud_frame's optical frame.")
    cloud_error = _read("cloud_error")
    sfm_mapping = _read("sfm_mapping", "sfm.mode streaming: continued or fresh ('' batch).")
    sfm_mapping_reason = _read("sfm_mapping_reason", "Why the window was mapped afresh.")
    registered = _stage("sfm", lambda sfm: sfm.num_registered, 0)
    points = _stage("sfm", lambda sfm: sfm.num_points, 0)
    mapping_attempts = _stage("sfm", lambda sfm: len(sfm.attempts), 0,
                              "Runs of the incremental mapper (sfm.mapping_attempts).")
    reprojection_error = _stage("sfm", lambda sfm: sfm.reprojection_error, _NAN,
                                "Mean, px, of the reconstruction kept.")
    inlier_ratio = property(lambda self: _inliers(self.result.alignment)[0])
    selected_points = property(lambda self: _inliers(self.result.alignment)[1])
    steps_done = _stage("refinement", lambda r: r.steps_done, 0)
    step_mode = _stage("refinement", _step_mode, "", _step_mode.__doc__)
    unsupported_change = _stage("check", lambda c: c.unsupported_change, _NAN,
                                "Share of the unsupported pixels moved (the check after).")
    metric_estimate = _stage("metric", lambda m: m.metres_per_net_unit, _NAN,
                             "Metres per network unit of the window's own estimate (NaN: "
                             "none; metric_reason says why).")
    metric_reason = _stage("metric", lambda m: m.reason, "")
