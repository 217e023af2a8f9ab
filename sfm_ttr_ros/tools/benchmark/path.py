"""The stream's camera path (core/stream/path.py: the poses its windows report,
``WindowStats.path_poses``) against a drive's poses: the benchmark's ``path``.

Both paths are expressed relative to the path's first frame (est_0⁻¹·est_i against
gt_0⁻¹·gt_i, so the ``odom`` axes drop out). ``drift_pct``: the translation error at the path's
last frame over the distance the poses travelled, in %, the usual end-point drift of visual
odometry; ``max_drift_pct`` the largest error over the distance travelled up to that frame (the
first tenth of the distance left out: there the ratio is over a few metres); ``ate_rmse`` the
RMS position error after the rigid motion (Kabsch) that best lays the path on the poses. In
metres when the path is (``units`` "m"); otherwise the least-squares scale of the positions is
fitted first (``scale_fitted``) and the drift is of the shape only. A path that turned metric
midway is measured over its poses in metres (those before went out in SfM units).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from sfm_ttr_ros.core.geometry import nearest_rotation
from sfm_ttr_ros.core.stream.records import FramePose


def _relative(poses: list[np.ndarray]) -> np.ndarray:
    """The positions of ``poses`` (4x4) in the first one's frame (N x 3)."""
    first = np.linalg.inv(poses[0])
    return np.array([(first @ P)[:3, 3] for P in poses])


def _kabsch_rmse(a: np.ndarray, b: np.ndarray) -> float:
    """RMS of ||R·a_i + t − b_i|| for the best rigid (R, t)."""
    ca, cb = a - a.mean(0), b - b.mean(0)
    R = nearest_rotation(cb.T @ ca)  # Kabsch: the rotation nearest Σ b_i a_iᵀ
    return float(np.sqrt(np.mean(np.sum((ca @ R.T - cb) ** 2, 1))))


def path_drift(poses: Sequence[FramePose], summary: Mapping[str, object],
               gt_from_name: Mapping[str, np.ndarray]) -> dict[str, object]:
    """The drift of the path's ``poses`` (as the windows reported them, in order) against
    ``gt_from_name`` (name → 4x4 camera-to-world, metres) over those in the path's units
    (``summary``: the stream's path summary) that have a pose (module docstring); with the
    summary."""
    out: dict[str, object] = dict(summary)
    units = out.get("units", "")
    kept = [p.pose for p in poses if p.units == units and p.name in gt_from_name]
    out["compared"] = len(kept)
    if len(kept) < 2:
        out["reason"] = "fewer than two path frames with a pose"
        return out
    est = _relative([p.odom_from_camera for p in kept])
    gt = _relative([np.asarray(gt_from_name[p.name], np.float64) for p in kept])
    steps = np.linalg.norm(np.diff(gt, axis=0), axis=1)
    travelled = np.concatenate([[0.0], np.cumsum(steps)])
    length = float(travelled[-1])
    out["length_m"] = length
    out["scale_fitted"] = units != "m"
    if units != "m":
        denom = float(np.sum(est * est))
        scale = float(np.sum(est * gt)) / denom if denom > 0 else float("nan")
        est = est * scale
    err = np.linalg.norm(est - gt, axis=1)
    if not (length > 0 and np.isfinite(err).all()):
        out["reason"] = "the poses do not move, or the path is not finite"
        return out
    late = travelled >= 0.1 * length
    out["end_error_m"] = float(err[-1])
    out["drift_pct"] = 100.0 * float(err[-1]) / length
    out["max_drift_pct"] = 100.0 * float(np.max(err[late] / travelled[late]))
    out["ate_rmse"] = _kabsch_rmse(est, gt)
    out["mean_position_sd"] = float(np.mean([math.sqrt(p.position_var) for p in kept]))
    return out


def path_report(path_poses: Sequence[FramePose], summary: Mapping[str, object],
                poses: np.ndarray | None, index_of) -> dict[str, object]:
    """``{"path": drift}`` of the stream's ``path_poses`` (``summary`` its path's summary)
    against a sequence's ``poses`` (N x 4 x 4 camera-to-world; frame ``name`` at
    ``index_of(name)``); {} when the sequence has none."""
    if poses is None:
        return {}
    return {"path": path_drift(path_poses, summary,
                               {p.name: poses[index_of(p.name)] for p in path_poses})}


def path_lines(results: Mapping[str, object], modes) -> list[str]:
    """Markdown: per windowed mode with a ``path``, its drift against the drive's poses."""
    rows = [(m, results[m]["path"]) for m in modes if "path" in results[m]]
    if not rows:
        return []
    lines = ["The camera's path against the drive's poses (drift: end-point error over the "
             "distance travelled; ATE after a rigid alignment):", "",
             "| method | units | frames | distance m | drift % | max drift % | ATE | breaks |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for m, p in rows:
        cells = [f"{p[k]:.2f}" if isinstance(p.get(k), float) else "-"
                 for k in ("length_m", "drift_pct", "max_drift_pct", "ate_rmse")]
        units = p.get("units", "") + (" (scale fitted)" if p.get("scale_fitted") else "")
        lines.append(f"| {m} | {units} | {p.get('compared', 0)} | " + " | ".join(cells)
                     + f" | {p.get('breaks', 0)} |")
    return lines + [""]
