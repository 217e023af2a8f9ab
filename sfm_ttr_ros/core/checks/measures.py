"""Trust, but verify, each window: sanity checks before refining, the unsupported change after.

The paper names SfM-TTR's weak spots (Sec. 6): dynamic objects, low parallax and drastic
appearance change make SfM wrong, and SfM-TTR then teaches the network the wrong scene. pycolmap
may report success on such a window. With live serving and the ``continue`` policy a bad window
would reach every frame after it, so each window has to pass the checks before its weights are
served or kept. Not in the paper.

1. Sanity checks (cheap, before any refinement step; :func:`sanity_check`), each with a threshold
   in :class:`CheckConfig` (0 = off) and a key of :class:`~sfm_ttr_ros.core.outcomes.Unrefined`:

   * mean reprojection error of the window's observations  r̄ = mean r_lj  ≤ max (px), and
     relative to the stream (``max_reprojection_ratio`` k > 0, :func:`reprojection_refusal`):
     r̄ ≤ k · median r̄ of its last REPROJECTION_HISTORY accepted windows (at least
     REPROJECTION_MIN_HISTORY of them): a reconstruction that stays wrong after the mapper's
     retries fits its observations worse than the stream's right ones (docs/decisions.md,
     "Window checks"), and refined on it the network gets worse, while the window's frames keep
     the weights before it;
   * parallax: the diameter of the registered camera centres over the median SfM depth,
     max_jk ‖C_j − C_k‖ / median D_sfm  ≥ min (scale-free; the paper's low-parallax weak spot:
     a creeping or turning camera triangulates depth from a baseline far shorter than the scene,
     and SfM may still "succeed" with consistent but wrong depth);
   * the scale jump against the previous accepted window on the frames both registered:
     the camera path between the first and last shared frame in network units, ŝ·‖C_a − C_b‖,
     must agree within the factor max (a jump means one of the two reconstructions is wrong).
     Windows side by side (``window_stride == window_size``) share no frame: no jump check.

   Scale-based checks need depth up to scale: for affine-invariant (relative inverse depth)
   outputs they are skipped. Measured and reported, without a threshold (each was tried as a
   check and left off: harmful and helpful windows overlapped, docs/decisions.md): the mean
   track length, the alignment's RANSAC inlier ratio and the spread of per-frame scales
   max_j max(s_j/s̃, s̃/s_j), s_j = median over frame j's valid points of D_nn/D_sfm.

2. Unsupported change (after refining; :func:`unsupported_change`): no statistic of the SfM
   points can see a region that has no points, e.g. a vehicle moving with the camera (its
   features are static in the image, so SfM triangulates none on it) while the static street
   around it is reconstructed right. Refined on the street, the network may still move that
   region far away (docs/decisions.md, "Window checks"). Per
   registered frame j, with L(p) = log(D_after(p) / D_before(p)) and the frame's change at its
   own SfM observations g_j = median_l L(p_lj) (a global scale change is no error: the depth is
   up to scale),

       U_j = |{p : dist(p, {p_lj}) > ρ·W  and  |L(p) − g_j| > log τ}| / |{p}|

   the share of the frame's pixels farther than ρ·W from every observation (W the width) whose
   depth moved by more than the factor τ against the supported change; the window's U is the
   mean over its frames, refused above ``max_unsupported_change``. Refinement should move the
   scene where SfM supervises it; a large change where it says nothing is a guess.

   How much depth may move far from the points depends on the scene and on how wrong the
   network is there (an indoor video's bare walls carry no point; docs/decisions.md, "Window
   checks"), so with
   ``unsupported_change_ratio`` k > 0 the threshold is relative to this stream's own accepted
   windows: refused when

       U > max(max_unsupported_change, k · median U of the last UNSUPPORTED_HISTORY accepted)

   and a window with fewer than UNSUPPORTED_MIN_HISTORY accepted predecessors (no reference
   yet: the median of one or two windows is one window's accident) is not refused by U. While a
   window refines, interim weights (``serve_every_steps``) are checked the same way on
   INTERIM_PROBE_FRAMES of its registered frames before they are served
   (:func:`probe_frames`).

"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.geometry import camera_centre
from sfm_ttr_ros.core.outcomes import Unrefined
from sfm_ttr_ros.core.sfm.result import SfmResult

#: ρ and τ of :func:`unsupported_change` (module docstring, 2.)
UNSUPPORTED_RADIUS = 0.05
UNSUPPORTED_FACTOR = 1.5
#: the depth maps are read on every STEP-th pixel (the share is a ratio of pixel counts)
UNSUPPORTED_STEP = 4
#: accepted windows whose U forms the reference of ``unsupported_change_ratio``
UNSUPPORTED_HISTORY = 10
#: accepted windows the ratio needs before it refuses any (one window's U is no reference:
#: docs/decisions.md, "Window checks")
UNSUPPORTED_MIN_HISTORY = 3
#: accepted windows whose mean reprojection error is the reference of max_reprojection_ratio
REPROJECTION_HISTORY = 10
#: accepted windows that reference needs before the ratio refuses any
REPROJECTION_MIN_HISTORY = 2
#: registered frames on which interim weights are checked before they are served (one network
#: forward each per preview: 2 x 7 previews x ~45 ms on one core, ~6 % of a KITTI window)
INTERIM_PROBE_FRAMES = 2


@dataclass
class CheckConfig:
    """Thresholds of the window checks (the node's ``check.*`` parameters); 0 turns one off."""

    max_reprojection_error: float = 2.0  # px, mean over the window's observations
    max_reprojection_ratio: float = 1.25  # x the median error of the stream's accepted windows
    min_parallax: float = 0.1  # camera-centre diameter / median SfM depth
    max_scale_jump: float = 2.0  # shared-frame path within [1/x, x] of the previous window's
    max_unsupported_change: float = 0.025  # share of pixels moved > τ far from any SfM point
    unsupported_change_ratio: float = 5.0  # refuse U above k x the stream's accepted median

    def __post_init__(self) -> None:
        for name in ("max_reprojection_error", "max_reprojection_ratio", "min_parallax",
                     "max_scale_jump", "max_unsupported_change", "unsupported_change_ratio"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v >= 0):
                raise InputError(f"check.{name} must be a finite number >= 0, got {v}")
        if self.max_unsupported_change > 1:
            raise InputError(f"check.max_unsupported_change is a share in [0, 1], got "
                             f"{self.max_unsupported_change}")
        for name in ("max_scale_jump", "unsupported_change_ratio", "max_reprojection_ratio"):
            v = float(getattr(self, name))
            if 0 < v < 1:
                raise InputError(f"check.{name} is a factor >= 1 (or 0 = off), got {v}")

    @property
    def after_refinement(self) -> bool:
        """Whether a check runs on the refined weights (the unsupported change) and may still
        refuse the window once its steps are done; interim weights are then checked the same
        way before they are served."""
        return self.max_unsupported_change > 0


@dataclass
class CheckReport:
    """What the checks measured on one window (NaN: not measured) and their verdict."""

    reprojection_error: float = float("nan")
    track_length: float = float("nan")
    parallax: float = float("nan")
    inlier_ratio: float = float("nan")
    scale_spread: float = float("nan")
    scale_jump: float = float("nan")
    unsupported_change: float = float("nan")
    reason_key: Unrefined | None = None  # the check that refused the window
    reason: str = ""
    seconds: float = 0.0

    def summary(self) -> dict:
        return dataclasses.asdict(self)


@dataclass
class PathReference:
    """A window's camera centres in network units (ŝ·C_j) by frame name, for the jump check."""

    centres: dict[str, np.ndarray] = field(default_factory=dict)


# -- 1. sanity checks ------------------------------------------------------------------------
def path_reference(sfm: SfmResult, registered: Sequence[str], scale: float) -> PathReference:
    """The registered frames' camera centres times ŝ (network units)."""
    return PathReference({n: camera_centre(sfm.frames[n].cam_from_world) * scale
                          for n in registered})


def scale_jump(current: PathReference, previous: PathReference | None) -> float:
    """max(ρ, 1/ρ) with ρ the ratio of the paths between the first and last frame both windows
    registered (current over previous, network units); NaN when they share fewer than two frames
    or either path is too short to measure (under 1e-6 units: a static camera)."""
    if previous is None:
        return float("nan")
    shared = [n for n in current.centres if n in previous.centres]
    if len(shared) < 2:
        return float("nan")
    a, b = shared[0], shared[-1]
    now = float(np.linalg.norm(current.centres[a] - current.centres[b]))
    before = float(np.linalg.norm(previous.centres[a] - previous.centres[b]))
    if now < 1e-6 or before < 1e-6:
        return float("nan")
    rho = now / before
    return max(rho, 1.0 / rho)


def frame_scale_spread(d_sfm: Sequence[np.ndarray], d_nn: Sequence[np.ndarray],
                       min_points: int = 10) -> float:
    """max_j max(s_j/s̃, s̃/s_j), s_j = median(D_nn/D_sfm) over frame j's valid points (frames
    with ≥ ``min_points`` of them), s̃ = median_j s_j. NaN with fewer than two such frames."""
    scales = []
    for ds, dn in zip(d_sfm, d_nn, strict=True):
        ds, dn = np.asarray(ds, np.float64), np.asarray(dn, np.float64)
        ok = np.isfinite(ds) & np.isfinite(dn) & (ds > 0) & (dn > 0)
        if int(ok.sum()) >= min_points:
            scales.append(float(np.median(dn[ok] / ds[ok])))
    if len(scales) < 2:
        return float("nan")
    s = np.asarray(scales)
    ref = float(np.median(s))
    return float(np.max(np.maximum(s / ref, ref / s)))


def track_length(sfm: SfmResult, registered: Sequence[str]) -> float:
    """Mean number of the window's registered frames that observe each 3D point."""
    ids = [sfm.frames[n].point_ids for n in registered]
    if not ids or not sum(len(i) for i in ids):
        return float("nan")
    _, counts = np.unique(np.concatenate(ids), return_counts=True)
    return float(counts.mean())


def parallax(sfm: SfmResult, registered: Sequence[str]) -> float:
    """max_jk ‖C_j − C_k‖ / median D_sfm over the registered frames (scale-free); NaN with
    fewer than two frames or no depth."""
    if len(registered) < 2:
        return float("nan")
    c = np.stack([camera_centre(sfm.frames[n].cam_from_world) for n in registered])
    diameter = float(np.max(np.linalg.norm(c[:, None] - c[None], axis=-1)))
    depths = np.concatenate([sfm.frames[n].depths for n in registered])
    depths = depths[np.isfinite(depths) & (depths > 0)]
    return diameter / float(np.median(depths)) if depths.size else float("nan")


def sanity_check(config: CheckConfig, check: CheckReport) -> CheckReport:
    """Fill ``check.reason_key`` / ``reason`` from the measured statistics (the first failing
    check, in this order); a NaN statistic passes (nothing to judge)."""
    tests = (
        (Unrefined.CHECK_REPROJECTION, check.reprojection_error, config.max_reprojection_error,
         ">", "mean reprojection error {v:.3g} px > check.max_reprojection_error {t:g}"),
        (Unrefined.CHECK_PARALLAX, check.parallax, config.min_parallax, "<",
         "parallax {v:.3g} (camera path / median depth) < check.min_parallax {t:g}"),
        (Unrefined.CHECK_SCALE_JUMP, check.scale_jump, config.max_scale_jump, ">",
         "scale jumped {v:.3g}x against the previous window > check.max_scale_jump {t:g}"),
    )
    for key, value, threshold, op, text in tests:
        if threshold <= 0 or not math.isfinite(value):
            continue
        if (value > threshold) if op == ">" else (value < threshold):
            check.reason_key, check.reason = key, text.format(v=value, t=threshold)
            break
    return check


# -- 2. unsupported change -------------------------------------------------------------------
def frame_unsupported_change(before: np.ndarray, after: np.ndarray, pixels: np.ndarray,
                             radius: float | None = None, factor: float | None = None,
                             step: int = UNSUPPORTED_STEP) -> float:
    """U_j of one frame (module docstring, 2.): the share of its pixels farther than
    ``radius``·W from every observation in ``pixels`` (N x 2, x y) whose depth changed by more
    than ``factor`` against the median change at the observations (None: UNSUPPORTED_RADIUS,
    UNSUPPORTED_FACTOR). NaN without an observation or a valid depth at one."""
    radius = UNSUPPORTED_RADIUS if radius is None else radius
    factor = UNSUPPORTED_FACTOR if factor is None else factor
    b = np.asarray(before, np.float64)[::step, ::step]
    a = np.asarray(after, np.float64)[::step, ::step]
    h, w = b.shape
    px = np.asarray(pixels, np.float64).reshape(-1, 2) / step
    if px.size == 0 or h == 0 or w == 0:
        return float("nan")
    valid = np.isfinite(a) & np.isfinite(b) & (a > 0) & (b > 0)
    change = np.zeros_like(b)
    change[valid] = np.log(a[valid] / b[valid])
    xi = np.clip(np.floor(px[:, 0]).astype(np.int64), 0, w - 1)
    yi = np.clip(np.floor(px[:, 1]).astype(np.int64), 0, h - 1)
    at_points = valid[yi, xi]
    if not at_points.any():
        return float("nan")
    g = float(np.median(change[yi[at_points], xi[at_points]]))
    seeds = np.full((h, w), 255, np.uint8)
    seeds[yi, xi] = 0
    dist = cv2.distanceTransform(seeds, cv2.DIST_L2, 3)
    far = dist > radius * w
    moved = valid & (np.abs(change - g) > math.log(factor))
    return float(np.count_nonzero(far & moved) / (h * w))


def unsupported_change(before: Mapping[str, np.ndarray], after: Mapping[str, np.ndarray],
                       pixels: Mapping[str, np.ndarray], **kwargs) -> float:
    """The window's U: the mean of :func:`frame_unsupported_change` over the frames in
    ``pixels`` (the registered frames' SfM observations); NaN when no frame can be measured."""
    values = [frame_unsupported_change(before[n], after[n], p, **kwargs)
              for n, p in pixels.items() if n in before and n in after]
    values = [v for v in values if math.isfinite(v)]
    return float(np.mean(values)) if values else float("nan")


def stream_reference(history: Sequence[float], min_history: int) -> tuple[float, int]:
    """(the median of the finite values of ``history``, a statistic of the stream's last
    accepted windows; how many there are): the median is NaN with fewer than ``min_history``
    of them (no reference yet)."""
    past = [v for v in history if math.isfinite(v)]
    n = len(past)
    return (float(np.median(past)) if past and n >= min_history else float("nan")), n


def reprojection_refusal(config: CheckConfig, value: float,
                         history: Sequence[float] = ()) -> str:
    """Why the window's mean reprojection error ``value`` refuses it against the stream ("" =
    accepted): above ``max_reprojection_ratio`` x the median of ``history``, the errors of the
    stream's last accepted windows; nothing is refused with the ratio 0, a NaN value or fewer
    than REPROJECTION_MIN_HISTORY of them."""
    k = config.max_reprojection_ratio
    reference, n = stream_reference(history, REPROJECTION_MIN_HISTORY)
    if k <= 0 or not (value > k * reference):  # NaN value or no reference: not refused
        return ""
    return (f"mean reprojection error {value:.3g} px > check.max_reprojection_ratio {k:g} x "
            f"{reference:.3g} px (the median of the last {n} accepted windows)")


def unsupported_refusal(config: CheckConfig, value: float,
                        history: Sequence[float] = ()) -> str:
    """Why the window's unsupported change ``value`` refuses it ("" = accepted; a NaN value or
    ``max_unsupported_change`` 0 accepts). ``history``: U of this stream's last accepted
    windows, the reference of ``unsupported_change_ratio`` (module docstring, 2.); with a ratio
    and fewer than UNSUPPORTED_MIN_HISTORY of them nothing is refused."""
    t = config.max_unsupported_change
    if t <= 0 or not math.isfinite(value) or value <= t:
        return ""
    why = (f"{value:.3g} of the pixels moved by more than {UNSUPPORTED_FACTOR:g}x far from "
           f"every SfM point > check.max_unsupported_change {t:g}")
    k = config.unsupported_change_ratio
    if k <= 0:
        return why
    reference, n = stream_reference(history, UNSUPPORTED_MIN_HISTORY)
    if not (value > k * reference):  # no reference yet: not refused
        return ""
    return (f"{why} and > check.unsupported_change_ratio {k:g} x {reference:.3g} (the median "
            f"of the last {n} accepted windows)")


def probe_frames(registered: Sequence[str], count: int = INTERIM_PROBE_FRAMES) -> list[str]:
    """Up to ``count`` of the registered frames, at the centres of ``count`` equal parts of the
    window: where interim weights are checked before they are served."""
    n = len(registered)
    if not n or count <= 0:
        return []
    idx = sorted({int((k + 0.5) * n / count) for k in range(min(count, n))})
    return [registered[i] for i in idx]
