"""``sfm-ttr run`` for one sequence: offline SfM-TTR over the whole sequence (the paper's
setting), every depth before and after written, the frames with ground truth evaluated
(:func:`run_whole_sequence`; also each task of ``sfm-ttr run --split``)."""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path

import numpy as np

from sfm_ttr_ros.core.frames import InputError

#: Names of the two predictions in ``summary.json``'s ``metrics`` and their labels as methods.
METHODS = {"before": "no_ttr", "after": "sfm_ttr"}


def _plain(summary: dict) -> dict:
    return {k: v for k, v in summary.items() if k not in ("per_frame",)}


def run_whole_sequence(seq, settings, out: str | Path, *, start: int = 0, max_frames: int = 0,
                       eigen_crop: bool = False) -> dict:
    """One window over frames ``start .. start + max_frames`` (0 = to the end) of ``seq``:
    ``out/before`` and ``out/after`` (every depth as .npy and a colour PNG), ``points.ply``,
    ``summary.json`` (returned) and, when frames have ground truth, ``per_frame.csv``."""
    from sfm_ttr_ros.core.evaluation import EvalConfig, Evaluator
    from sfm_ttr_ros.core.pipeline import SfmTTR
    from sfm_ttr_ros.core.visualize import colorize_depth, write_ply
    from sfm_ttr_ros.tools.cli_args import build_model_for

    if not 0 <= start < len(seq):
        raise InputError(f"--start {start} is outside the sequence's {len(seq)} frames "
                         f"(0 .. {len(seq) - 1})")
    stop = len(seq) if max_frames <= 0 else min(len(seq), start + max_frames)
    frames = seq.frames(start, stop)
    out = Path(out)
    try:
        for sub in METHODS:
            (out / sub).mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the output folder {out}: {exc}") from exc
    model = build_model_for(settings)
    ttr = SfmTTR(model, settings.ttr)
    t0 = time.perf_counter()
    try:
        res = ttr.process_window(frames, seq.intrinsics)
    finally:
        ttr.close()
    seconds = time.perf_counter() - t0
    import cv2

    evals = {k: Evaluator(EvalConfig(eigen_crop=eigen_crop)) for k in METHODS}
    for f in frames:
        for key, depths in (("before", res.depths_before), ("after", res.depths)):
            np.save(out / key / f"{f.name}.npy", depths[f.name].astype(np.float32))
            cv2.imwrite(str(out / key / f"{f.name}.png"), colorize_depth(depths[f.name]))
            gt = seq.gt(f.name)
            if gt is not None:
                evals[key].add(f.name, depths[f.name], gt)
    if res.cloud_xyz.size:
        write_ply(out / "points.ply", res.cloud_xyz,
                  res.sfm.points_rgb if res.sfm is not None else None,
                  {"reprojection_error": res.cloud_error})
    summary = {
        "sequence": seq.name,
        "frames_total": len(frames),
        "first_frame": start,
        **res.summary(),
        "alignment": res.alignment.stats if res.alignment else {},
        "loss_history": res.refinement.loss_history if res.refinement else [],
        "cloud_frame": res.cloud_frame,
        "timings": res.timings,
        "seconds": seconds,
        "seconds_per_frame": seconds / max(1, len(frames)),
    }
    if evals["before"].summary()["frames"]:
        full = {k: e.summary() for k, e in evals.items()}
        summary["metrics"] = {k: _plain(v) for k, v in full.items()}
        write_per_frame(out / "per_frame.csv", full, res.refined)
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=float))
    return summary


def write_per_frame(path: Path, full: dict, refined: bool) -> None:
    """abs rel and RMSE of every evaluated frame before and after (the columns of the
    benchmark's per_frame.csv, methods ``no_ttr`` and ``sfm_ttr``)."""
    rows = {k: {r["name"]: r for r in v["per_frame"]} for k, v in full.items()}
    cols = ["name"]
    for method in METHODS.values():
        cols += [f"{method}_abs_rel", f"{method}_rmse", f"{method}_refined"]
    with open(path, "w", newline="") as fh:
        wr = csv.writer(fh)
        wr.writerow(cols)
        for name in rows["before"]:
            row = [name]
            for key in METHODS:
                r = rows[key].get(name, {})
                row += [f"{r['abs_rel']:.6f}" if "abs_rel" in r else "",
                        f"{r['rmse']:.6f}" if "rmse" in r else "",
                        int(bool(refined) and key == "after")]
            wr.writerow(row)
