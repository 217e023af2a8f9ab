"""Stage 3 of SfM-TTR: scale alignment of sparse SfM depth to the network's depth.

Izquierdo & Civera, CVPR 2023, Sec. 3.2 (and the authors' release):

1. RANSAC over one-point models ``s = D_nn / D_sfm`` (20 trials); a point is an inlier when
   ``(s·D_sfm − D_nn)² / (s·D_sfm) ≤ τ`` (τ = 0.5; a chi-square-like test, note it is not scale
   invariant: it depends on the network's depth units).
2. Weighted least squares over the inliers, ``min_s Σ w (s·D_sfm − D_nn)²`` with ``w = 1/D_nn²``,
   whose closed form is  ŝ = Σ(D_sfm/D_nn) / Σ(D_sfm/D_nn)².
3. A relaxed second selection over ALL points with ``|ŝ·D_sfm − D_nn| / (ŝ·D_sfm) < τ₂``
   chooses the supervision points: it keeps points whose network depth is noisy on purpose,
   since those are the ones the refinement should correct.

The ablation's baselines (median, unweighted least squares) live with the tests that compare them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sfm_ttr_ros.core.errors import InputError


@dataclass
class AlignmentConfig:
    ransac_iterations: int = 20
    # two-point (scale, shift) RANSAC of relative inverse-depth outputs (alignment_affine.py)
    affine_ransac_iterations: int = 200
    tau: float = 0.5  # RANSAC inlier threshold on (s·D_sfm − D_nn)² / (s·D_sfm)
    relaxed_tau: float = 0.5  # final selection threshold on |s·D_sfm − D_nn| / (s·D_sfm)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.ransac_iterations < 1 or self.affine_ransac_iterations < 1:
            raise InputError(f"ransac_iterations and affine_ransac_iterations must be >= 1, got "
                             f"{self.ransac_iterations}, {self.affine_ransac_iterations}")
        if not (self.tau > 0 and self.relaxed_tau > 0):
            raise InputError(f"tau and relaxed_tau must be > 0 ({self.tau}, {self.relaxed_tau})")


@dataclass
class AlignmentResult:
    """``scale`` maps SfM depth to network depth units: D_nn ≈ scale · D_sfm."""

    scale: float
    ransac_inliers: np.ndarray  # bool mask, inliers of the best RANSAC model
    selected: np.ndarray  # bool mask, relaxed selection = supervision points
    ransac_scale: float = float("nan")  # the best one-point model before least squares
    stats: dict[str, float] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return bool(np.isfinite(self.scale) and self.scale > 0 and self.selected.any())


def _check(d_sfm: np.ndarray, d_nn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d_sfm = np.asarray(d_sfm, np.float64).ravel()
    d_nn = np.asarray(d_nn, np.float64).ravel()
    if d_sfm.shape != d_nn.shape:
        raise InputError(f"depth arrays differ in length: {d_sfm.size} vs {d_nn.size}")
    return d_sfm, d_nn


def _valid(d_sfm: np.ndarray, d_nn: np.ndarray) -> np.ndarray:
    return np.isfinite(d_sfm) & np.isfinite(d_nn) & (d_sfm > 0) & (d_nn > 0)


def weighted_ls_scale(d_sfm: np.ndarray, d_nn: np.ndarray) -> float:
    """Closed-form argmin_s Σ (s·D_sfm − D_nn)² / D_nn²  =  Σ q / Σ q²,  q = D_sfm / D_nn."""
    q = d_sfm / d_nn
    den = float(np.sum(q * q))
    return float(np.sum(q) / den) if den > 0 else float("nan")


def align_scale(d_sfm: np.ndarray, d_nn: np.ndarray,
                config: AlignmentConfig | None = None) -> AlignmentResult:
    """Scale of SfM depth to network depth by the paper's RANSAC + weighted LS + relaxed pass.

    Invalid pairs (non-finite, ≤ 0) are never inliers nor selected.
    """
    cfg = config or AlignmentConfig()
    d_sfm, d_nn = _check(d_sfm, d_nn)
    n = d_sfm.size
    valid = _valid(d_sfm, d_nn)
    none = np.zeros(n, bool)
    if not valid.any():
        return AlignmentResult(float("nan"), none, none.copy(), stats={"points": n, "valid": 0})

    rng = np.random.default_rng(cfg.seed)
    idx = np.flatnonzero(valid)
    picks = rng.choice(idx, size=cfg.ransac_iterations, replace=idx.size < cfg.ransac_iterations)
    ds, dn = d_sfm[valid], d_nn[valid]
    best_count, best_s, best_mask = -1, float("nan"), None
    for i in picks:  # one-point models s = D_nn / D_sfm
        s = d_nn[i] / d_sfm[i]
        pred = s * ds
        mask = (pred - dn) ** 2 / pred <= cfg.tau
        count = int(mask.sum())
        if count > best_count:
            best_count, best_s, best_mask = count, s, mask
    inliers = none.copy()
    inliers[idx[best_mask]] = True

    scale = weighted_ls_scale(d_sfm[inliers], d_nn[inliers])
    selected = none.copy()
    if np.isfinite(scale):
        pred = scale * ds
        selected[idx[np.abs(pred - dn) / pred < cfg.relaxed_tau]] = True
    stats = {
        "points": n,
        "valid": int(valid.sum()),
        "ransac_inliers": int(inliers.sum()),
        "inlier_ratio": float(inliers.sum() / valid.sum()),
        "selected": int(selected.sum()),
        "selected_ratio": float(selected.sum() / valid.sum()),
    }
    return AlignmentResult(scale, inliers, selected, ransac_scale=float(best_s), stats=stats)
