#!/usr/bin/env python3
"""Does each window check refuse exactly the windows whose refinement hurt?

Runs SfM-TTR window by window over a sequence, in the node's windows (``window_size``,
``window_stride`` of the parameter file, every frame a keyframe), measuring every window check
(core/checks/measures.py) but refusing nothing before refinement (the sanity thresholds are set to
0 for the run; the held-out split stays as configured, and the refined weights' depths are kept
even when the held-out check refuses them). For every window it then knows what refinement did
to its own frames against GT (median-scaled abs rel, before -> after), and judges it with the
parameter file's thresholds (plus ``--set``) exactly as the pipeline does. It prints a table and
the confusion numbers of the issue's target:

* harmful windows (refinement made the window's frames worse against GT): all must be refused;
* helpful windows: >= 90 % must be accepted.

With ``--policy reset`` (the default) windows are independent, so one run judges any threshold
set. Example (BENCHMARKS.md §9)::

    .venv/bin/python scripts/studies/check_outcomes.py --kitti-raw bench/hard/raw \\
        --kitti-gt bench/hard/gt --drive 2011_09_26_drive_0001_sync --out bench/hard/checks.json
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import sys
import time
from collections import Counter, deque
from pathlib import Path

import numpy as np

from sfm_ttr_ros.core.checks.measures import (
    UNSUPPORTED_HISTORY,
    CheckReport,
    accept,
    sanity_check,
    unsupported_change,
    unsupported_refusal,
)
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.evaluation import EvalConfig, Evaluator
from sfm_ttr_ros.core.params import build
from sfm_ttr_ros.core.pipeline import SfmTTR
from sfm_ttr_ros.tools.benchmark.run import segment_labels
from sfm_ttr_ros.tools.benchmark.settings import default_params_file
from sfm_ttr_ros.tools.cli_args import (
    add_parameter_args,
    add_sequence_args,
    build_model_for,
    open_sequence,
    parameter_values,
)

SANITY = ("max_reprojection_error", "min_track_length", "min_parallax", "min_inlier_ratio",
          "max_scale_spread", "max_scale_jump")


def window_abs_rel(depths: dict, names: list[str], seq, frame_names: dict) -> float:
    """Median-scaled abs rel pooled over the window's frames with GT (NaN: none)."""
    ev = Evaluator(EvalConfig(median_scaling=True))
    n = 0
    for name in names:
        gt = seq.gt(frame_names[name])
        if gt is not None and name in depths and ev.add(name, depths[name], gt) is not None:
            n += 1
    return ev.summary()["abs_rel"] if n else float("nan")


#: (ρ, τ) pairs of the unsupported-change statistic recorded for every window besides the
#: configured one, to see which separates harmful from helpful windows
GRID = ((0.03, 1.25), (0.05, 1.15), (0.05, 1.25), (0.05, 1.5), (0.08, 1.25))  # (ρ, τ)


def unsupported_grid(res, after: dict) -> dict:
    """U of the window (verification.unsupported_change) for every (ρ, τ) of GRID."""
    if res.sfm is None or not res.sfm.ok or not after:
        return {}
    pixels = {n: res.sfm.frames[n].pixels for n in res.names if n in res.sfm.frames}
    return {f"{r:g}/{f:g}": unsupported_change(res.depths_before, after, pixels, radius=r,
                                                factor=f) for r, f in GRID}


def windows_of(n: int, size: int, stride: int) -> list[range]:
    """The node's windows over n keyframes: [k, k + size) every stride, the rest in a last
    (shorter) window as the idle flush does."""
    out, k = [], 0
    while k + size <= n:
        out.append(range(k, k + size))
        k += stride
    last = out[-1].stop if out else 0
    if n - max(last - (size - stride), 0) >= 2 and last < n:
        out.append(range(max(0, last - (size - stride)), n))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_sequence_args(p)
    add_parameter_args(p, ("model", "method", "windows"), "params/kitti.yaml")
    p.add_argument("--out", default="", help="write the per-window records here (JSON)")
    args = p.parse_args(argv)
    _, values = parameter_values(args, None if args.params_file else default_params_file())
    settings = build(values)
    judge = settings.ttr.check
    measure_cfg = copy.deepcopy(settings.ttr)
    measure_cfg.check = dataclasses.replace(  # measures every check, refuses nothing
        judge, **{k: 0.0 for k in (*SANITY, "max_unsupported_change")})
    seq = open_sequence(args)
    stop = len(seq) if args.max_frames <= 0 else min(len(seq), args.start + args.max_frames)
    indices = list(range(args.start, stop))
    labels = segment_labels(seq, indices) or ["-"] * len(indices)
    ttr = SfmTTR(build_model_for(settings), measure_cfg)
    st = settings.stream
    records = []
    previous_accepted = True
    accepted_u: deque[float] = deque(maxlen=UNSUPPORTED_HISTORY)  # unsupported_change_ratio
    try:
        for w in windows_of(len(indices), st.window_size, st.window_stride):
            frames = []
            for k in w:
                f = seq.frame(indices[k])
                f.name = f"{k:010d}"
                frames.append(f)
            frame_names = {f.name: seq.names[f.index] for f in frames}
            t0 = time.perf_counter()
            res = ttr.process_window(frames, seq.intrinsics)
            seconds = time.perf_counter() - t0
            c = res.check or CheckReport()
            after = res.depths if res.refined else res.depths_candidate
            before_e = window_abs_rel(res.depths_before, res.names, seq, frame_names)
            after_e = window_abs_rel(after, res.names, seq, frame_names) if after else np.nan
            # the verdict with the file's thresholds; the scale jump only against an accepted
            # previous window, as the pipeline does
            judged = sanity_check(judge, dataclasses.replace(
                c, reason_key="", reason="",
                scale_jump=c.scale_jump if previous_accepted else float("nan")))
            if judged.reason_key:
                verdict = judged.reason_key
            elif res.refinement is None or not (res.refined or res.depths_candidate):
                verdict = res.reason_key or ("not refined: " + res.reason)[:40]
            elif not accept(judge, c.error_before, c.error_after):
                verdict = "rejected_by_check"
            elif unsupported_refusal(judge, c.unsupported_change, accepted_u):
                verdict = "check_unsupported_change"
            else:
                verdict = "accepted"
            previous_accepted = verdict == "accepted"
            if previous_accepted and np.isfinite(c.unsupported_change):
                accepted_u.append(c.unsupported_change)
            seg = Counter(labels[k] for k in w).most_common(1)[0][0]
            rec = {"window": len(records), "frames": [indices[w.start], indices[w.stop - 1]],
                   "segment": seg, "abs_rel_before": before_e, "abs_rel_after": after_e,
                   "verdict": verdict, "window_seconds": seconds,
                   **{k: v for k, v in c.summary().items() if k not in ("reason", "reason_key",
                                                                         "seconds")},
                   "check_seconds": c.seconds,
                   "unsupported_grid": unsupported_grid(res, after)}
            records.append(rec)
            print(f"window {rec['window']:2d} {rec['frames'][0]:4d}-{rec['frames'][1]:4d} "
                  f"{seg:9s} abs rel {before_e:.4f} -> {after_e:.4f}  reproj "
                  f"{c.reprojection_error:.2f} track {c.track_length:.2f} par {c.parallax:.3f} inl "
                  f"{c.inlier_ratio:.2f} spread {c.scale_spread:.2f} jump {c.scale_jump:.2f} "
                  f"check {c.error_before:.4f} -> {c.error_after:.4f} unsupported "
                  f"{c.unsupported_change:.3f}  {verdict}",
                  file=sys.stderr, flush=True)
    finally:
        ttr.close()
    judged = [r for r in records if np.isfinite(r["abs_rel_after"])]
    harmful = [r for r in judged if r["abs_rel_after"] > r["abs_rel_before"]]
    helpful = [r for r in judged if r["abs_rel_after"] < r["abs_rel_before"]]
    unknown = [r for r in records if not np.isfinite(r["abs_rel_after"])]
    summary = {
        "windows": len(records),
        "harmful": len(harmful),
        "harmful_refused": sum(r["verdict"] != "accepted" for r in harmful),
        "helpful": len(helpful),
        "helpful_accepted": sum(r["verdict"] == "accepted" for r in helpful),
        "not_refined": len(unknown),
        "check_share_of_window_time": float(np.nanmedian(
            [r["check_seconds"] / r["window_seconds"] for r in records
             if r["window_seconds"] > 0]
            or [np.nan])),
        "thresholds": dataclasses.asdict(judge),
    }
    print(json.dumps(summary, indent=1))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps({"summary": summary, "windows": records},
                                             indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
