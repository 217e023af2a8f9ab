"""Metres for the outputs from the windows' estimates.

Per window w with alignment scale ŝ_w (D_nn ≈ ŝ_w·D_sfm, Eq. (4)) and metres per SfM unit m_w
(:mod:`.ground`, :mod:`.odometry`), the network before the window predicts in units of
k_w = m_w / ŝ_w metres. Two ways to make the outputs metric:

* ``learn`` (the default): the supervision targets become m_w·D_sfm (Eq. (5) with m_w in place
  of ŝ_w, and the photometric poses scaled alike): the network itself learns metres, the
  refined weights predict metres (factor 1) and the live output follows with them. Each window
  that agrees with the stream's anchor re-anchors the scale, so it cannot drift;
* outputs scaled (``learn`` off): the network keeps its own units and the outputs are multiplied
  by the median of the last ``history`` accepted windows' k_w. Measured worse: under the
  ``continue`` policy the network's own scale drifts (nothing anchors it), and a median of past
  windows lags the drift (docs/decisions.md).

Frame-to-frame scale that wanders breaks what consumes the depth (SLAM, odometry, costmaps): the
first estimates are confirmed by agreement between windows before they anchor the rest, a window
that disagrees with the anchor is refined in the anchor's metres (targets ref·ŝ_w·D_sfm) or,
beyond ``max_jump``, refused like a scale jump, and windows that agree with each other and not
with the anchor move it (:mod:`.anchor`). Once metric, the state turns ``stale`` when the source
stops (odometry silent, windows without a ground plane). ``fixed`` uses the user's factor from
the start; ``none`` leaves the network's units (and says so).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from sfm_ttr_ros.core.metric.anchor import Anchor, Verdict
from sfm_ttr_ros.core.metric.ground import cameras, ground_plane
from sfm_ttr_ros.core.metric.metric_config import MetricConfig
from sfm_ttr_ros.core.metric.odometry_track import OdometryTrack, path_length
from sfm_ttr_ros.core.sfm.result import SfmResult


def in_metres(depth: np.ndarray | None, metres_per_unit: float | None) -> np.ndarray | None:
    """A float32 depth map in the outputs' units: times the metric factor when there is one
    (the same array when there is none, or when the factor is 1: the network learnt metres)."""
    if depth is None or metres_per_unit is None or metres_per_unit == 1.0:
        return depth
    return (depth * np.float32(metres_per_unit)).astype(np.float32, copy=False)


@dataclass
class WindowMetric:
    """One window's metric estimate: metres per SfM unit (m), per network unit of the weights
    before the window (k = m / ŝ) and of the weights it leaves (k, or 1 when the network learns
    metres); NaN when there is none, ``reason`` says why; and what the ground plane or the
    odometry measured."""

    source: str
    metres_per_sfm_unit: float = float("nan")  # m
    metres_per_net_unit: float = float("nan")  # k = m / ŝ, of the weights before the window
    metres_per_net_unit_after: float = float("nan")  # of the weights the window leaves
    reason: str = ""
    verdict: str = ""  # against the stream's anchor (core/metric/anchor.py)
    # metres per SfM unit the supervision uses (m, or the anchor's)
    supervision_metres_per_sfm_unit: float = float("nan")
    ground_inliers: int = 0
    height_spread: float = float("nan")
    travel_m: float = float("nan")
    ground_up: np.ndarray | None = None  # camera_height: the ground plane's up (SfM world)

    @property
    def ok(self) -> bool:
        return math.isfinite(self.metres_per_net_unit) and self.metres_per_net_unit > 0


def estimate(cfg: MetricConfig, sfm: SfmResult, registered: Sequence[str],
             stamps: Sequence[float], alignment_scale: float,
             odometry: OdometryTrack | None) -> WindowMetric:
    """The window's metric estimate by ``cfg.source`` (module docstring)."""
    w = WindowMetric(cfg.source)
    if cfg.source in ("none", "fixed"):
        return w
    if cfg.source == "camera_height":
        plane = ground_plane(sfm, registered, cfg)
        w.ground_inliers, w.height_spread = plane.inliers, plane.spread
        if not math.isfinite(plane.height):
            w.reason = f"no ground plane: {plane.reason}"
            return w
        w.metres_per_sfm_unit = cfg.camera_height / plane.height
        w.ground_up = plane.up
    else:
        w.metres_per_sfm_unit, w.travel_m, w.reason = _odometry_scale(cfg, sfm, registered,
                                                                      stamps, odometry)
    if math.isfinite(w.metres_per_sfm_unit) and alignment_scale > 0:
        w.metres_per_net_unit = w.metres_per_sfm_unit / alignment_scale
        w.metres_per_net_unit_after = 1.0 if cfg.learn else w.metres_per_net_unit
        w.supervision_metres_per_sfm_unit = w.metres_per_sfm_unit
    return w


def _odometry_scale(cfg: MetricConfig, sfm: SfmResult, registered: Sequence[str],
                    stamps: Sequence[float], odometry: OdometryTrack | None
                    ) -> tuple[float, float, str]:
    """(m, travelled metres, reason) from the odometry track over the registered frames."""
    if odometry is None or len(odometry) < 2:
        return float("nan"), float("nan"), "no odometry received"
    positions = odometry.positions_at(stamps)
    if positions is None:
        return float("nan"), float("nan"), "odometry does not cover the window's stamps"
    travel = path_length(positions)
    sfm_path = path_length(cameras(sfm, registered)[0])
    if travel < cfg.min_travel or sfm_path <= 0:
        return float("nan"), travel, f"travelled {travel:.2f} m < metric.min_travel"
    return travel / sfm_path, travel, ""


@dataclass
class MetricStatus:
    """What the outputs' units are now (for /diagnostics and the reports): ``state``
    ``not_metric`` (metric.source none), ``waiting`` (no estimate yet), ``confirming`` (the
    depth is in an estimate's metres that other windows have not confirmed yet), ``metric``, or
    ``stale`` (it was metric, but its source stopped: the depth keeps the last metres,
    unchecked); ``reason`` why (core/metric/anchor.py); ``metres_per_unit`` the outputs' factor
    (None = not metric); the relative ``spread`` of the accepted windows' estimates, how many
    there are, the odometry messages taken, refused and its restarts, and the re-anchorings."""

    source: str
    state: str
    metres_per_unit: float | None
    spread: float
    windows: int
    odometry_received: int
    odometry_rejected: int
    reason: str = ""
    odometry_resets: int = 0
    re_anchors: int = 0

    def values(self) -> dict[str, object]:
        """The status as flat values (``metres_per_unit`` NaN when not metric)."""
        k = self.metres_per_unit
        return {"source": self.source, "state": self.state, "reason": self.reason,
                "metres_per_unit": float("nan") if k is None else k,
                "spread": self.spread, "windows": self.windows,
                "odometry_received": self.odometry_received,
                "odometry_rejected": self.odometry_rejected,
                "odometry_resets": self.odometry_resets, "re_anchors": self.re_anchors}


class MetricScale:
    """The metres of a stream's outputs: from its accepted windows' estimates, anchored as
    :mod:`.anchor` says."""

    def __init__(self) -> None:
        self.history: deque[float] = deque()  # k_after of the windows that anchor the scale
        self.start_up: deque[float] = deque()  # their k under reset (the start-up weights')
        self.ratios: deque[float] = deque()  # each accepted window's k over its reference
        self.anchor = Anchor()
        self.without_estimate = 0  # windows in a row measured without an estimate
        self.images_stamp: float | None = None  # the newest stamp of the last window measured

    def note_images(self, stamps) -> None:
        """The stamps of the window being measured: the odometry is stale when its last
        position lags the newest of them by more than ``metric.odometry_timeout_s``."""
        finite = [float(t) for t in stamps if np.isfinite(t)]
        if finite:
            self.images_stamp = max(finite)

    def factor(self, cfg: MetricConfig) -> float | None:
        """Metres per network unit of the outputs now; None = not metric (``none``, or no
        accepted estimate yet). The network that learns metres: 1; scaled outputs: the median
        of the accepted windows' k."""
        if cfg.source == "fixed":
            return float(cfg.factor)
        if cfg.source == "none" or not self.history:
            return None
        return float(np.median(self.history))

    def status(self, cfg: MetricConfig, odometry: OdometryTrack) -> MetricStatus:
        """The outputs' units now (:class:`MetricStatus`), with ``odometry``'s counts."""
        k = self.factor(cfg)
        state, reason = self._state(cfg, k, odometry)
        return MetricStatus(cfg.source, state, k, self.spread(), len(self.history),
                            odometry.received, odometry.rejected, reason, odometry.resets,
                            self.anchor.re_anchors)

    def _state(self, cfg: MetricConfig, k: float | None,
               odometry: OdometryTrack) -> tuple[str, str]:
        """(state, reason) of :class:`MetricStatus`."""
        if cfg.source in ("none", "fixed"):
            return ("not_metric" if cfg.source == "none" else "metric"), ""
        if k is None:
            return "waiting", ""
        if not self.anchor.confirmed:
            return "confirming", self.anchor.reason
        last = odometry.last_stamp
        if cfg.source == "odometry" and last is not None and self.images_stamp is not None:
            behind = self.images_stamp - last
            if behind > cfg.odometry_timeout_s:
                return "stale", (f"no odometry for {behind:.1f} s of images > "
                                 f"{cfg.odometry_timeout_s:g} s")
        if self.without_estimate >= cfg.stale_windows:
            return "stale", f"{self.without_estimate} windows in a row without an estimate"
        return "metric", self.anchor.reason

    def reference(self, cfg: MetricConfig, weight_policy: str) -> float | None:
        """What a window's k should be: the metres per unit of the weights it starts from
        (``continue``: the outputs' factor; ``reset``: the start-up weights', as the windows
        before measured them); None before any."""
        if weight_policy == "reset":
            return float(np.median(self.start_up)) if self.start_up else None
        return self.factor(cfg)

    def spread(self) -> float:
        """How steady the scale is: the standard deviation of the accepted windows' k over
        their reference (0 = every window found the weights as metric as expected; NaN with
        fewer than two)."""
        return float(np.std(self.ratios)) if len(self.ratios) >= 2 else float("nan")

    def judge(self, cfg: MetricConfig, window: WindowMetric, weight_policy: str) -> str:
        """Judge ``window``'s estimate against the anchor (:mod:`.anchor`): its ``verdict``,
        the ``target_m`` its supervision uses (the stream's metres when it disagrees) and its
        ``reason``; returns why it is refused ("" = not refused: beyond ``max_jump`` of a
        confirmed anchor)."""
        if cfg.source in ("none", "fixed"):
            return ""
        if not window.ok:
            self.without_estimate += 1
            return ""
        self.without_estimate = 0
        ref = self.reference(cfg, weight_policy)
        verdict = self.anchor.judge(cfg, window.metres_per_net_unit, ref)
        self.anchor.record(cfg, verdict, window.metres_per_net_unit)
        window.verdict, window.reason = verdict.kind, verdict.refusal or verdict.reason
        if verdict.kind == "disagrees" and ref is not None:
            # ref·ŝ (ŝ = m / k): the stream's metres
            window.supervision_metres_per_sfm_unit = (ref * window.metres_per_sfm_unit
                                                      / window.metres_per_net_unit)
            window.metres_per_net_unit_after = 1.0 if cfg.learn else ref
        return verdict.refusal

    def accept(self, cfg: MetricConfig, window: WindowMetric, weight_policy: str) -> None:
        """An accepted (refined and kept) window's estimate: anchors the scale as its verdict
        says; a window that disagreed leaves it as it was."""
        if not window.ok or cfg.source in ("none", "fixed") or window.verdict == "disagrees":
            return
        if self.anchor.accepted(cfg, Verdict(window.verdict, window.reason)):
            for h in (self.history, self.start_up, self.ratios):
                h.clear()
        ref = self.reference(cfg, weight_policy)
        if ref is not None:
            self.ratios.append(window.metres_per_net_unit / ref)
        if weight_policy == "reset":
            self.start_up.append(window.metres_per_net_unit)
        self.history.append(window.metres_per_net_unit_after)
        for h in (self.history, self.start_up, self.ratios):
            while len(h) > cfg.history:
                h.popleft()
