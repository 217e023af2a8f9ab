"""The camera's path: the windows' SfM camera poses chained into one path in an ``odom`` frame
(the stream keeps one: core/stream/path.py).

Every window's reconstruction (Sec. 3.1) holds the pose ``cam_from_world`` of each registered
frame in its own world frame. :class:`CameraPath` maps each window's world into ``odom`` with a
similarity S = (s, R, t) (an odom point x_o = s·R·x_w + t), chosen by how the window was mapped:

* the first window defines ``odom``: its first registered frame at the origin, ``odom``'s axes
  that camera's body axes by REP 103 (x forward, y left, z up: :data:`BODY_FROM_OPTICAL`);
* ``continued`` (``sfm.mode: streaming``, the carried map: one world, one scale): the same S as
  the window before, chained directly; on a metre path its scale is the median of the map's
  windows' metres per SfM unit so far, re-anchored at the path's newest frame (no jump);
* ``fresh`` (a new mapping) or a batch window (each its own reconstruction): S fitted to the
  frames it shares with the path (:func:`fit_similarity`): R the chordal mean of R_path·R_windowᵀ
  over the shared frames, s the metres per SfM unit when known (else the least-squares scale of
  the shared camera centres, which needs two distinct ones), t from the centres' means;
* no shared frames (or too few for the fit): a **break**, counted. The window's first frame is
  put where the path's last velocity carries it by its stamp (constant velocity, the last
  orientation kept) and, without metres, its scale makes its first step as long as that velocity
  says; the covariance grows by the square of the guessed displacement (it says "a guess"),
  or, with no velocity yet (a path of one frame), by :data:`UNKNOWN_VARIANCE` and a heading
  unknown within ±90°.

Units: those of the stream's depth (:func:`metres_per_sfm_unit`): metres when the window's
depth outputs are in metres, its metres per SfM unit their factor k times the ŝ of the depth
(D_nn ≈ ŝ·D_sfm, Eq. (4)); otherwise the first reconstruction's SfM units (``units`` says
which). A path in SfM units turns metric at the first window in metres: the window is chained
as before (its scale fitted, or its map's), and the path until then is scaled by the metres
per path unit that gives (the origin and the axes stay); from then on it stays in metres.

Covariance (what it is): per frame, isotropic, in the path's units. From the reconstruction, a
frame j with n_j observations, RMS reprojection error r_j (px), focal f (px) and median
observed depth d_j: the angle of one observation is uncertain by r_j/f, so the rotation's
variance is (r_j/f)²/n_j and the position's (d_j·r_j/f)²/n_j (scaled by s²). To that each window
adds a base carried along the path: the mean variance of the shared frames it was fitted to plus
the fit's mean squared residual (centres, and angles for the rotation), or at a break the
guessed displacement squared. It is the reconstruction's local precision plus what chaining
added, not a bound on the drift (measured: tools/benchmark ``path``).

What a continuous odometry needs (core/stream/base_odometry.py): a window chained by ``shared``
fits its own poses to the path's only in the least-squares sense, so its frames may start off
the path's end. The first frame it adds (the path's next, when it adds none) carries that
``jump``: J = P_k·S(T_k)⁻¹, P_k the path's pose of the newest frame the window shares, S(T_k)
the window's of it (J·S(T) is the window's pose continuing the path). A window whose metres
came from the ground plane (``metric.source: camera_height``) gives each of its frames the
plane's up in odom's axes (``ground_up``: R of S times the normal).

Only frames newer than the path's last stamp join it (an odometry stream goes forward in
time); a frame seen again in a later window is used for the fit, never re-published.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.geometry import Similarity, camera_centre, fit_similarity
from sfm_ttr_ros.core.sfm.result import SfmResult
from sfm_ttr_ros.core.window_io import WindowResult

#: REP 103 body axes (x forward, y left, z up) from a camera's optical axes (z forward, x right,
#: y down): odom is the first camera's body frame.
BODY_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
#: Position variance (units²) of a break with no velocity to guess from: unknown.
UNKNOWN_VARIANCE = 1e6
UNKNOWN_ROTATION_VARIANCE = (math.pi / 2) ** 2  # rad²: a heading unknown within ±90°
#: How the path's windows were chained (the counters' keys).
CHAINS = ("first", "continued", "shared", "break")


@dataclass
class WindowPoses:
    """What the path takes of one window: ``cam_from_world`` (4x4, SfM units) and stamp (s) per
    registered frame, how it was mapped (``continued``, ``fresh``, "" in batch), its metres per
    SfM unit (None: unknown), each frame's variances in SfM units (module docstring) and its
    ground plane's up in its SfM world (None: not measured)."""

    poses: dict[str, np.ndarray]
    stamps: dict[str, float]
    mapping: str = ""
    metres_per_sfm_unit: float | None = None
    position_var: dict[str, float] = field(default_factory=dict)
    rotation_var: dict[str, float] = field(default_factory=dict)
    ground_up: np.ndarray | None = None


@dataclass
class PathPose:
    """One frame on the path: ``odom_from_camera`` (4x4, the path's units), its variances
    (position in units², rotation in rad²), its window and how the window was chained; the
    ground's up in odom's axes when its window measured it, and on the first frame a window
    chained by a fit adds, the ``jump`` J that makes it continue the path (module docstring)."""

    name: str
    stamp: float
    odom_from_camera: np.ndarray
    position_var: float
    rotation_var: float
    window: int
    chain: str
    ground_up: np.ndarray | None = None
    jump: np.ndarray | None = None

    @property
    def position(self) -> np.ndarray:
        return self.odom_from_camera[:3, 3]

    def covariance(self) -> np.ndarray:
        """The 6x6 covariance (x, y, z, rotation about x, y, z), row-major as nav_msgs wants."""
        return np.diag([self.position_var] * 3 + [self.rotation_var] * 3)


def window_poses(sfm: SfmResult, stamps: Mapping[str, float], mapping: str = "",
                 metres_per_sfm_unit: float | None = None) -> WindowPoses:
    """The registered frames of ``sfm`` and its anchors (frames before the window mapped with
    it: :attr:`SfmResult.anchors`, what a fresh map shares with the path) with their stamps
    (frames without a stamp left out) and the reconstruction's variances per frame (module
    docstring)."""
    f = 1.0
    if sfm.intrinsics is not None:
        f = max(1e-9, 0.5 * (sfm.intrinsics.fx + sfm.intrinsics.fy))
    out = WindowPoses({}, {}, mapping, metres_per_sfm_unit)
    for name, obs in {**sfm.anchors, **sfm.frames}.items():
        if name not in stamps or len(obs) == 0:
            continue
        out.poses[name] = np.asarray(obs.cam_from_world, np.float64)
        out.stamps[name] = float(stamps[name])
        angle2 = float(np.mean(np.square(obs.reproj_errors))) / (f * f) / len(obs)
        depth = float(np.median(np.abs(obs.depths)))
        out.rotation_var[name] = angle2
        out.position_var[name] = depth * depth * angle2
    return out


def metres_per_sfm_unit(result: WindowResult, metres_per_unit: float | None) -> float | None:
    """The metres per SfM unit of the window's depth outputs: their factor ``metres_per_unit``
    (metres per network unit, core/metric/scale.py) times the ŝ the depth is in units of
    (D_nn ≈ ŝ·D_sfm, Eq. (4)): for a refined window that measured its metres the ŝ its
    supervision used (Eq. (5); with ``metric.learn`` the window's metres, the factor then 1),
    under ``metric.source: fixed`` the alignment's. None when the depth is not in metres, or
    in metres the window did not measure (the path keeps its own scale)."""
    metric = result.metric
    if (metres_per_unit is None or not math.isfinite(metres_per_unit) or metres_per_unit <= 0
            or metric is None or not (math.isfinite(result.scale) and result.scale > 0)):
        return None
    if metric.source == "fixed" or (result.refined and metric.ok):
        return float(metres_per_unit * result.scale)
    return None


def result_poses(result: WindowResult, stamps: Mapping[str, float],
                 metres_per_unit: float | None = None) -> WindowPoses | None:
    """What the path takes of a window's result (None: it has no reconstruction)."""
    if result.sfm is None or not result.sfm.frames:
        return None
    poses = window_poses(result.sfm, stamps, result.sfm_mapping,
                         metres_per_sfm_unit(result, metres_per_unit))
    if result.metric is not None:
        poses.ground_up = result.metric.ground_up
    return poses


@dataclass
class _Segment:
    """The similarity of the current map's world, the base variances its frames carry, the
    metres per SfM unit of its windows (a metre path) and its newest frame (its odom position
    and world centre: where a new scale is anchored)."""

    S: Similarity
    position_base: float
    rotation_base: float
    metres: list[float] = field(default_factory=list)
    anchor: tuple[np.ndarray, np.ndarray] | None = None

    def rescale(self, metres: float | None) -> None:
        """A continued window's metres per SfM unit: the segment's scale becomes the median
        of its windows' (one map, one scale: the median of their estimates), re-anchored at
        its newest frame so the path stays continuous."""
        if metres is None or self.anchor is None:
            return
        self.metres.append(metres)
        s = float(np.median(self.metres))
        position, centre = self.anchor
        self.S = Similarity(s, self.S.R, position - s * self.S.R @ centre,
                            self.S.position_res2, self.S.rotation_res2)


class CameraPath:
    """The windows' camera poses chained into one path in ``odom`` (module docstring)."""

    def __init__(self, max_poses: int = 100_000):
        if max_poses < 2:
            raise InputError(f"a camera path keeps at least 2 poses, got {max_poses}")
        self.max_poses = int(max_poses)
        self.poses: dict[str, PathPose] = {}  # insertion (= stamp) order, the oldest dropped
        self.units = ""  # "m" or "sfm" once the first window set them
        self.chains: Counter[str] = Counter()
        self._segment: _Segment | None = None
        self._windows = 0
        self._jump: np.ndarray | None = None  # for the next frame added (module docstring)

    @property
    def breaks(self) -> int:
        return self.chains["break"]

    @property
    def last(self) -> PathPose | None:
        return next(reversed(self.poses.values()), None)

    def add(self, window: WindowPoses) -> list[PathPose]:
        """Chain one window; its frames newer than the path's end, in stamp order (possibly
        none: a window with no registered frame adds nothing and counts nothing)."""
        if not window.poses:
            return []
        m = window.metres_per_sfm_unit
        metres = m if m is not None and math.isfinite(m) and m > 0 else None
        if not self.units:
            self.units = "m" if metres is not None else "sfm"
        scale = metres if self.units == "m" else None
        chain, segment = self._chain(window, scale)
        if metres is not None and self.units == "sfm":
            self._to_metres(metres / segment.S.s, segment)
            scale = metres
        if chain == "continued":
            segment.rescale(scale)
        elif scale is not None:
            segment.metres = [scale]
        self._segment = segment
        self.chains[chain] += 1
        index, self._windows = self._windows, self._windows + 1
        if chain in ("shared", "break"):  # a jump waits for the first frame the path adds
            self._jump = self._fit_jump(window, segment) if chain == "shared" else None
        return self._append(window, segment, chain, index)

    def _to_metres(self, factor: float, segment: _Segment) -> None:
        """A path in SfM units turned metric: every pose and ``segment`` (the window's, its
        scale fitted in the path's units) scaled by ``factor`` metres per path unit about the
        origin, the variances by its square (module docstring). The poses are new objects:
        the ones handed out before keep the units they were published in."""
        f2 = factor * factor
        for name, pose in self.poses.items():
            T = pose.odom_from_camera.copy()
            T[:3, 3] *= factor
            jump = None if pose.jump is None else pose.jump.copy()
            if jump is not None:
                jump[:3, 3] *= factor
            self.poses[name] = replace(pose, odom_from_camera=T, jump=jump,
                                       position_var=pose.position_var * f2)
        if self._jump is not None:
            self._jump[:3, 3] *= factor
        S = segment.S
        segment.S = Similarity(S.s * factor, S.R, S.t * factor, S.position_res2 * f2,
                               S.rotation_res2)
        segment.position_base *= f2
        if segment.anchor is not None:
            segment.anchor = (segment.anchor[0] * factor, segment.anchor[1])
        self.units = "m"

    def _chain(self, window: WindowPoses, scale: float | None) -> tuple[str, _Segment]:
        """How the window joins the path, and its segment."""
        if self._segment is None:
            return "first", self._first(window, scale)
        if window.mapping == "continued":
            return "continued", self._segment
        shared = [n for n in window.poses if n in self.poses]
        S = fit_similarity([self.poses[n].odom_from_camera for n in shared],
                           [window.poses[n] for n in shared], scale)
        if S is None:
            return "break", self._guess(window, scale)
        pv = float(np.mean([self.poses[n].position_var for n in shared]))
        rv = float(np.mean([self.poses[n].rotation_var for n in shared]))
        return "shared", _Segment(S, pv + S.position_res2, rv + S.rotation_res2)

    @staticmethod
    def _first(window: WindowPoses, scale: float | None) -> _Segment:
        """The first window: its earliest frame at the origin, on odom's REP 103 axes."""
        first = min(window.poses, key=window.stamps.__getitem__)
        T = window.poses[first]
        R = BODY_FROM_OPTICAL @ T[:3, :3]
        s = 1.0 if scale is None else scale
        return _Segment(Similarity(s, R, -s * R @ camera_centre(T)), 0.0, 0.0)

    def _guess(self, window: WindowPoses, scale: float | None) -> _Segment:
        """A break: the window's earliest frame where the last velocity carries the path's end
        (module docstring)."""
        order = sorted(window.poses, key=window.stamps.__getitem__)
        end = self.last
        velocity = self._velocity()
        dt = window.stamps[order[0]] - end.stamp
        step = np.zeros(3) if velocity is None else velocity * dt
        s = scale
        if s is None:
            s = self._segment.S.s
            if velocity is not None and len(order) > 1:
                a, b = (camera_centre(window.poses[n]) for n in order[:2])
                seconds = window.stamps[order[1]] - window.stamps[order[0]]
                length = float(np.linalg.norm(b - a))
                if length > 1e-12 and seconds > 0:
                    s = float(np.linalg.norm(velocity)) * seconds / length
        T = window.poses[order[0]]
        R = end.odom_from_camera[:3, :3] @ T[:3, :3]
        t = end.position + step - s * R @ camera_centre(T)
        if velocity is None:  # nothing to guess from: position and heading unknown
            return _Segment(Similarity(s, R, t), end.position_var + UNKNOWN_VARIANCE,
                            end.rotation_var + UNKNOWN_ROTATION_VARIANCE)
        return _Segment(Similarity(s, R, t), end.position_var + float(step @ step),
                        end.rotation_var)

    def _velocity(self) -> np.ndarray | None:
        """The path's last velocity (units per second) from its last two poses; None without."""
        if len(self.poses) < 2:
            return None
        *_, a, b = self.poses.values()
        dt = b.stamp - a.stamp
        return None if dt <= 0 else (b.position - a.position) / dt

    def _fit_jump(self, window: WindowPoses, segment: _Segment) -> np.ndarray:
        """J = P_k·S(T_k)⁻¹ at the newest frame k the window shares with the path (module
        docstring): what takes the window's poses onto the path where it left it."""
        k = max((n for n in window.poses if n in self.poses), key=lambda n: self.poses[n].stamp)
        return self.poses[k].odom_from_camera @ np.linalg.inv(segment.S.apply(window.poses[k]))

    def _append(self, window: WindowPoses, segment: _Segment, chain: str,
                index: int) -> list[PathPose]:
        end = self.last
        after = -math.inf if end is None else end.stamp
        new = sorted((n for n in window.poses
                      if n not in self.poses and window.stamps[n] > after),
                     key=window.stamps.__getitem__)
        s2 = segment.S.s ** 2
        up = None if window.ground_up is None else segment.S.R @ window.ground_up
        added = []
        for name in new:
            pose = PathPose(name, window.stamps[name], segment.S.apply(window.poses[name]),
                            segment.position_base + s2 * window.position_var.get(name, 0.0),
                            segment.rotation_base + window.rotation_var.get(name, 0.0),
                            index, chain, up, self._jump)
            self._jump = None
            self.poses[name] = pose
            added.append(pose)
            segment.anchor = (pose.position.copy(), camera_centre(window.poses[name]))
        while len(self.poses) > self.max_poses:
            del self.poses[next(iter(self.poses))]
        return added

    def summary(self) -> dict[str, object]:
        """Plain numbers: the units, poses, windows by how they were chained, breaks."""
        return {"units": self.units, "poses": len(self.poses), "windows": self._windows,
                "chains": {k: self.chains[k] for k in CHAINS}, "breaks": self.breaks}
