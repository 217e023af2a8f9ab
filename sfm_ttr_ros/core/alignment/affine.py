"""Stage 3 of SfM-TTR for networks whose output is affine-invariant inverse depth.

MiDaS / DPT / Depth Anything relative heads predict ``p ≈ a·(1/D) + b``: inverse depth up to an
unknown scale ``a > 0`` AND shift ``b``. The paper's one-point scale RANSAC (Izquierdo & Civera,
CVPR 2023, Sec. 3.2; :mod:`sfm_ttr_ros.core.alignment.scale`) assumes ``D_nn = s·D_sfm`` and, with a
shift, picks the wrong points and the wrong targets. This module fits

    p = a·u + b,    u = 1/D_sfm,

with the paper's three steps carried over:

1. RANSAC over two-point models (seeded, ``ransac_iterations`` trials). A point is an inlier
   when its heteroscedastic residual, the model's error normalised by the model's shift-free
   value ``a·u`` (as the paper normalises by ``s·D_sfm``),

       e = |a·u + b − p| / (a·u)  =  |c·p + d − u| / u,     c = 1/a,  d = −b/a,

   is ≤ ``tau``. ``e`` is the relative error of the network's inverse depth brought into SfM
   units, so it is invariant to the network's arbitrary output scale AND shift (the paper's
   test is not scale invariant; with an arbitrary scale per network, 2.6 for Depth Anything V2
   Small vs ~160 for Large, a unit-dependent test could not have one default).
2. Weighted least squares over the inliers of the same residual, ``min Σ (c·q + d·r − 1)²``
   with ``q = p·D_sfm``, ``r = D_sfm``: a 2 x 2 closed form. With ``b = 0`` it is exactly the
   paper's ``ŝ = Σq / Σq²`` (``q = D_sfm/D_nn`` for ``p = 1/D_nn``), so this generalises Eq.'s
   weights ``1/D_nn²`` rather than replacing them.
3. A relaxed second pass over ALL valid points, ``e < relaxed_tau``, selects the supervision.

The refinement then compares like with like in the network's own output space: targets
``a/D_sfm + b`` (:func:`affine_targets`) against the raw prediction ``p``. The paper's
scale-only path (:func:`sfm_ttr_ros.core.alignment.scale.align_scale`) is untouched and stays the
one for depth outputs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sfm_ttr_ros.core.alignment.scale import (
    AlignmentConfig,
    AlignmentResult,
    _check,
    _valid,
    align_scale,
)
from sfm_ttr_ros.core.errors import InputError

#: Relative spread of SfM inverse depth below which (scale, shift) cannot be told apart.
MIN_INVERSE_DEPTH_SPREAD = 1e-6


@dataclass
class AffineAlignmentConfig:
    ransac_iterations: int = 200  # two-point samples: AlignmentConfig.affine_ransac_iterations
    tau: float = 0.2  # RANSAC inlier threshold on e = |a·u + b − p| / (a·u)
    relaxed_tau: float = 0.5  # supervision selection threshold on the same e
    seed: int = 0

    def __post_init__(self) -> None:
        if int(self.ransac_iterations) < 1:
            raise InputError(f"ransac_iterations must be >= 1, got {self.ransac_iterations}")
        if not (self.tau > 0 and self.relaxed_tau > 0):
            raise InputError(f"tau and relaxed_tau must be > 0 ({self.tau}, {self.relaxed_tau})")


@dataclass
class AffineAlignmentResult(AlignmentResult):
    """An :class:`AlignmentResult` for ``p ≈ scale·(1/D_sfm) + shift``.

    ``scale`` (a) and ``shift`` (b) map SfM inverse depth to the network's output; ``ok``,
    ``ransac_inliers``, ``selected`` and ``stats`` mean what they mean for the scale-only path.
    ``reason`` says why the fit failed ("" when it did not)."""

    shift: float = float("nan")
    ransac_shift: float = float("nan")
    reason: str = ""

    @property
    def ok(self) -> bool:
        return bool(super().ok and np.isfinite(self.shift))


def relative_residual(c: float, d: float, p: np.ndarray, d_sfm: np.ndarray) -> np.ndarray:
    """e = |c·p + d − 1/D_sfm| · D_sfm: the inverse-depth error relative to the SfM value."""
    return np.abs((c * p + d) * d_sfm - 1.0)


def weighted_ls_affine(d_sfm: np.ndarray, p: np.ndarray) -> tuple[float, float]:
    """Closed-form argmin over (c, d) of Σ (c·p·D_sfm + d·D_sfm − 1)², as (a, b) = (1/c, −d/c).

    Normal equations [Σq² Σqr; Σqr Σr²]·[c; d] = [Σq; Σr] with q = p·D_sfm, r = D_sfm. Returns
    (nan, nan) when they are singular (all p equal, or all D_sfm equal) or c ≤ 0."""
    q, r = p * d_sfm, d_sfm
    sqq, sqr, srr = float(q @ q), float(q @ r), float(r @ r)
    det = sqq * srr - sqr * sqr
    if not det > 1e-12 * sqq * srr:
        return float("nan"), float("nan")
    sq, sr = float(q.sum()), float(r.sum())
    c = (srr * sq - sqr * sr) / det
    d = (sqq * sr - sqr * sq) / det
    if not (np.isfinite(c) and np.isfinite(d) and c > 0):
        return float("nan"), float("nan")
    return 1.0 / c, -d / c


def _failure(n: int, reason: str, **stats: float) -> AffineAlignmentResult:
    none = np.zeros(n, bool)
    return AffineAlignmentResult(float("nan"), none, none.copy(), reason=reason,
                                 stats={"points": n, **stats})


def align_affine(d_sfm: np.ndarray, pred: np.ndarray,
                 config: AffineAlignmentConfig | None = None) -> AffineAlignmentResult:
    """Fit ``pred ≈ a/D_sfm + b`` by two-point RANSAC + weighted LS + relaxed selection.

    ``pred`` is the network's raw affine-invariant inverse depth at the SfM keypoints. Pairs with
    a non-finite or non-positive value on either side are never inliers nor selected (a ReLU
    head's zeros carry no information). Degenerate input (fewer than two valid points, no
    spread in SfM depth or in the prediction, no model with a > 0) gives a result with
    ``ok == False`` and a ``reason``; arrays of different lengths raise :class:`InputError`.
    """
    cfg = config or AffineAlignmentConfig()
    d_sfm, pred = _check(d_sfm, pred)
    n = d_sfm.size
    valid = _valid(d_sfm, pred)
    nv = int(valid.sum())
    if nv < 2:
        return _failure(n, f"{nv} valid point(s): an affine fit needs at least 2", valid=nv)
    idx = np.flatnonzero(valid)
    ds, p = d_sfm[valid], pred[valid]
    u = 1.0 / ds
    if np.ptp(u) <= MIN_INVERSE_DEPTH_SPREAD * float(np.max(u)):
        return _failure(n, "all SfM depths are equal: scale and shift cannot be told apart",
                        valid=nv)
    if np.ptp(p) <= MIN_INVERSE_DEPTH_SPREAD * float(np.max(p)):
        return _failure(n, "the prediction is constant over the points: no affine fit",
                        valid=nv)

    rng = np.random.default_rng(cfg.seed)
    best_count, best_ab, best_mask = 0, (float("nan"), float("nan")), None
    for _ in range(int(cfg.ransac_iterations)):
        i, j = rng.choice(nv, size=2, replace=False)
        du = u[i] - u[j]
        if abs(du) <= MIN_INVERSE_DEPTH_SPREAD * max(u[i], u[j]):
            continue
        a = (p[i] - p[j]) / du
        if not a > 0:  # inverse depth must grow with SfM inverse depth
            continue
        b = p[i] - a * u[i]
        mask = relative_residual(1.0 / a, -b / a, p, ds) <= cfg.tau
        count = int(mask.sum())
        if count > best_count:
            best_count, best_ab, best_mask = count, (float(a), float(b)), mask
    if best_mask is None or best_count < 2:
        return _failure(n, f"no two-point model with a > 0 and >= 2 inliers in "
                        f"{cfg.ransac_iterations} RANSAC trials", valid=nv)
    inliers = np.zeros(n, bool)
    inliers[idx[best_mask]] = True

    a, b = weighted_ls_affine(ds[best_mask], p[best_mask])
    selected = np.zeros(n, bool)
    reason = ""
    if np.isfinite(a):
        selected[idx[relative_residual(1.0 / a, -b / a, p, ds) < cfg.relaxed_tau]] = True
    else:
        reason = "weighted least squares over the RANSAC inliers is singular or gives a <= 0"
    stats = {
        "points": n,
        "valid": nv,
        "ransac_inliers": int(inliers.sum()),
        "inlier_ratio": float(inliers.sum() / nv),
        "selected": int(selected.sum()),
        "selected_ratio": float(selected.sum() / nv),
    }
    return AffineAlignmentResult(a, inliers, selected, ransac_scale=best_ab[0], stats=stats,
                                 shift=b, ransac_shift=best_ab[1], reason=reason)


def affine_targets(result: AffineAlignmentResult, d_sfm: np.ndarray) -> np.ndarray:
    """Supervision in the network's own output space: a·(1/D_sfm) + b for each SfM depth."""
    if not np.isfinite(result.scale) or not np.isfinite(result.shift):
        raise InputError(f"no affine fit to make targets from ({result.reason or 'not ok'})")
    d = np.asarray(d_sfm, np.float64)
    return result.scale / d + result.shift


def affine_to_depth(result: AffineAlignmentResult, pred: np.ndarray) -> np.ndarray:
    """The network's prediction as depth in SfM units, a / (p − b); NaN where p ≤ b (at or
    beyond infinity under the fitted shift). For evaluation and point clouds."""
    if not np.isfinite(result.scale) or not np.isfinite(result.shift):
        raise InputError(f"no affine fit to convert with ({result.reason or 'not ok'})")
    p = np.asarray(pred)
    inv = (p.astype(np.float64) - result.shift) / result.scale
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.where(inv > 0, 1.0 / inv, np.nan)
    return depth.astype(np.result_type(p.dtype, np.float32))


#: The output kinds aligned by :func:`align_affine` (the others by the paper's scale-only fit).
AFFINE_OUTPUT_KINDS = ("relative_inverse_depth",)


def is_affine_output(model) -> bool:
    """Whether ``model``'s output is affine-invariant inverse depth (its ``output_kind``;
    models without one, the Monodepth2 family, predict depth)."""
    return getattr(model, "output_kind", "") in AFFINE_OUTPUT_KINDS


@dataclass
class FrameAffineAlignment(AffineAlignmentResult):
    """Affine fits of a window, one per frame (``frame_scale[k]``, ``frame_shift[k]``: NaN
    where frame k's fit failed; ``frame_sizes[k]``: its number of points, in the order of the
    concatenated arrays). ``ransac_inliers`` / ``selected`` cover the whole window; ``scale`` and
    ``shift`` are the medians over the frames that were fitted (for reports)."""

    frame_scale: np.ndarray = field(default_factory=lambda: np.zeros(0))
    frame_shift: np.ndarray = field(default_factory=lambda: np.zeros(0))
    frame_sizes: np.ndarray = field(default_factory=lambda: np.zeros(0, int))

    def frame(self, k: int) -> AffineAlignmentResult:
        """Frame k's fit as an :class:`AffineAlignmentResult` (for :func:`affine_targets`,
        :func:`affine_to_depth`)."""
        lo = int(np.sum(self.frame_sizes[:k]))
        hi = lo + int(self.frame_sizes[k])
        return AffineAlignmentResult(float(self.frame_scale[k]), self.ransac_inliers[lo:hi],
                                     self.selected[lo:hi], shift=float(self.frame_shift[k]))


def align_affine_frames(d_sfm: np.ndarray, pred: np.ndarray, sizes,
                        config: AffineAlignmentConfig | None = None) -> FrameAffineAlignment:
    """:func:`align_affine` per frame of a window (``sizes``: each frame's number of points in
    the concatenated ``d_sfm`` / ``pred``).

    Affine-invariant networks (MiDaS, DPT, Depth Anything relative) are trained with a
    scale-and-shift-invariant loss PER IMAGE: nothing ties one frame's (a, b) to the next's, so
    one fit for the window (the paper's one ŝ for a depth network) would supervise each frame
    with another frame's shift. Each frame gets its own fit; frames whose fit fails get no
    supervision."""
    cfg = config or AffineAlignmentConfig()
    d_sfm, pred = _check(d_sfm, pred)
    sizes = np.asarray([int(n) for n in sizes], int)
    if sizes.sum() != d_sfm.size or np.any(sizes < 0):
        raise InputError(f"frame sizes {sizes.tolist()} do not add up to {d_sfm.size} points")
    fits, start = [], 0
    for n in sizes:
        fits.append(align_affine(d_sfm[start:start + n], pred[start:start + n], cfg))
        start += n
    scales = np.array([f.scale if f.ok else np.nan for f in fits])
    shifts = np.array([f.shift if f.ok else np.nan for f in fits])
    inliers = np.concatenate([f.ransac_inliers for f in fits]) if fits else np.zeros(0, bool)
    selected = np.concatenate([f.selected if f.ok else np.zeros(len(f.selected), bool)
                               for f in fits]) if fits else np.zeros(0, bool)
    ok = np.isfinite(scales)
    nv = sum(int(f.stats.get("valid", 0)) for f in fits)
    stats = {"points": int(d_sfm.size), "valid": nv, "frames": int(sizes.size),
             "frames_fitted": int(ok.sum()), "ransac_inliers": int(inliers.sum()),
             "inlier_ratio": float(inliers.sum() / max(nv, 1)), "selected": int(selected.sum()),
             "selected_ratio": float(selected.sum() / max(nv, 1))}
    reasons = "; ".join(f"frame {k}: {f.reason}" for k, f in enumerate(fits) if f.reason)
    return FrameAffineAlignment(
        float(np.median(scales[ok])) if ok.any() else float("nan"), inliers, selected,
        stats=stats, shift=float(np.median(shifts[ok])) if ok.any() else float("nan"),
        reason="" if ok.any() else (reasons or "no frame"), frame_scale=scales,
        frame_shift=shifts, frame_sizes=sizes)


def align_output(d_sfm: np.ndarray, pred: np.ndarray, output_kind: str,
                 config: AlignmentConfig | None = None,
                 frame_sizes=None) -> AlignmentResult:
    """Stage 3 for a network of ``output_kind``: for affine-invariant inverse depth one
    :func:`align_affine` per frame (:func:`align_affine_frames`, ``frame_sizes``; the whole
    array as one frame when None; ``config.affine_ransac_iterations`` and its seed, thresholds
    on relative errors, see :class:`AffineAlignmentConfig`), else the paper's
    :func:`~sfm_ttr_ros.core.alignment.scale.align_scale` with ``config``, unchanged."""
    cfg = config or AlignmentConfig()
    if output_kind in AFFINE_OUTPUT_KINDS:
        sizes = [np.asarray(d_sfm).size] if frame_sizes is None else frame_sizes
        return align_affine_frames(d_sfm, pred, sizes, AffineAlignmentConfig(
            ransac_iterations=cfg.affine_ransac_iterations, seed=cfg.seed))
    return align_scale(d_sfm, pred, cfg)
