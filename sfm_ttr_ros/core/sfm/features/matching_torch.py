"""Mutual nearest-neighbour matching with Lowe's ratio test, in torch (on the GPU when the
descriptors are there): the matcher of the torch SIFT features (core/sfm/features/sift_torch.py),
with COLMAP's SIFT matching thresholds as defaults."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class MatchConfig:
    """Options of :func:`match_mutual_ratio` (COLMAP's SIFT matching defaults)."""

    max_ratio: float = 0.8  # Lowe 2004, Sec. 7.1: nearest / second-nearest distance
    max_distance: float = 0.7  # COLMAP: arccos of the descriptors' dot product (radians)
    cross_check: bool = True  # mutual nearest neighbours
    chunk: int = 4096  # rows of the distance matrix per block (memory)


def mutual_ratio_candidates(desc1, desc2, cfg: MatchConfig | None = None):
    """For each row of ``desc1`` (N1 x D unit descriptors; ``desc2`` N2 x D, N2 >= 2, same
    device): its nearest neighbour in ``desc2`` and whether the match passes Lowe's ratio test
    (Lowe 2004, Sec. 7.1: the closest neighbour's distance below ``max_ratio`` times the second
    closest), the absolute distance limit and (``cross_check``) mutual consistency. Two device
    tensors (best (N1,) int64, keep (N1,) bool) and no read back to the host: a window's pairs
    are matched back to back and read once (:func:`matches_from_candidates`)."""
    import torch

    cfg = cfg or MatchConfig()
    n1, n2 = desc1.shape[0], desc2.shape[0]
    d1 = desc1.float()
    d2 = desc2.float()
    best12 = torch.empty(n1, dtype=torch.long, device=d1.device)
    ok12 = torch.empty(n1, dtype=torch.bool, device=d1.device)
    best21_val = torch.full((n2,), -2.0, device=d1.device)
    best21 = torch.zeros(n2, dtype=torch.long, device=d1.device)
    for a in range(0, n1, cfg.chunk):
        sim = d1[a:a + cfg.chunk] @ d2.T  # cosine similarity
        top, idx = sim.topk(2, dim=1)
        # Euclidean distance of unit vectors: sqrt(2 - 2 cos)
        dist = torch.sqrt((2 - 2 * top).clamp_min(0))
        ang = torch.arccos(top[:, 0].clamp(-1, 1))
        ok12[a:a + cfg.chunk] = (dist[:, 0] < cfg.max_ratio * dist[:, 1]) & \
                                (ang <= cfg.max_distance)
        best12[a:a + cfg.chunk] = idx[:, 0]
        cmax, carg = sim.max(0)
        better = cmax > best21_val
        best21_val = torch.where(better, cmax, best21_val)
        best21 = torch.where(better, carg + a, best21)
    keep = ok12
    if cfg.cross_check:
        keep = keep & (best21[best12] == torch.arange(n1, device=d1.device))
    return best12, keep


def matches_from_candidates(best: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """(M, 2) int64 indices (into desc1, into desc2) of the kept candidates, in desc1's order."""
    i1 = np.flatnonzero(keep)
    return np.stack([i1, np.asarray(best)[i1]], 1).astype(np.int64)


def match_mutual_ratio(desc1, desc2, cfg: MatchConfig | None = None):
    """Nearest-neighbour matching of unit descriptors (N1 x D, N2 x D torch tensors, same
    device) with Lowe's ratio test (Lowe 2004, Sec. 7.1), an absolute distance limit, and
    mutual consistency (:func:`mutual_ratio_candidates`). Returns an (M, 2) int64 numpy array
    of indices (into desc1, into desc2)."""
    if desc1.shape[0] == 0 or desc2.shape[0] < 2:
        return np.zeros((0, 2), np.int64)
    best, keep = mutual_ratio_candidates(desc1, desc2, cfg)
    return matches_from_candidates(best.cpu().numpy(), keep.cpu().numpy())
