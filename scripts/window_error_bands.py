#!/usr/bin/env python3
"""Where SfM-TTR helps and where it hurts: one window, per-frame error by ground-truth depth band.

Runs :meth:`SfmTTR.process_window` once per variant on frames [start, start + window) of a KITTI
-layout drive and prints, for each frame with GT, the median-scaled abs rel before / after and
the abs rel within GT bands 0-5, 5-10, 10-20, 20-80 m (with the band's share of the GT pixels),
plus the percentiles of the SfM depths. BENCHMARKS.md section 3 quotes it::

    .venv/bin/python scripts/window_error_bands.py --kitti-raw bench/data/raw \\
        --kitti-gt bench/data/gt --drive 2011_09_26_drive_0001_sync --start 10 \\
        --variant '{}' --variant '{"lr": 3e-5}' --variant '{"bn_mode": "train"}'

A variant is a JSON object of RefinementConfig fields (the paper's defaults otherwise).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from sfm_ttr_ros.core.evaluation import EvalConfig, Evaluator
from sfm_ttr_ros.core.models import ModelConfig, build_model
from sfm_ttr_ros.core.pipeline import SfmTTR, TTRConfig
from sfm_ttr_ros.core.refinement import RefinementConfig
from sfm_ttr_ros.core.sfm import SfmConfig
from sfm_ttr_ros.data.sequence import open_kitti

BANDS = ((0, 5), (5, 10), (10, 20), (20, 80))


def abs_rel(depth: np.ndarray, gt: np.ndarray) -> float:
    ev = Evaluator(EvalConfig(median_scaling=True))
    ev.add("frame", depth, gt)
    return ev.summary()["abs_rel"]


def band_errors(depth: np.ndarray, gt: np.ndarray) -> str:
    """abs rel (share of GT pixels) per GT band, after per-image median scaling."""
    m = gt > 0
    g = gt[m]
    d = depth[m] * np.median(g) / np.median(depth[m])
    e = np.abs(d - g) / g
    parts = []
    for lo, hi in BANDS:
        k = (g >= lo) & (g < hi)
        parts.append(f"{lo}-{hi} m {e[k].mean() if k.any() else float('nan'):.2f} "
                     f"({k.mean():.0%})")
    return ", ".join(parts)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--kitti-raw", required=True)
    p.add_argument("--kitti-gt", required=True)
    p.add_argument("--drive", required=True)
    p.add_argument("--start", type=int, default=10)
    p.add_argument("--window", type=int, default=10)
    p.add_argument("--variant", action="append", default=[],
                   help="JSON object of RefinementConfig fields (repeatable)")
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    seq = open_kitti(args.kitti_raw, args.drive, args.kitti_gt)
    frames = seq.frames(args.start, min(len(seq), args.start + args.window))
    model = build_model(ModelConfig(type="default"))
    for text in args.variant or ["{}"]:
        cfg = TTRConfig(sfm=SfmConfig(max_image_size=640, num_threads=2, init_min_tri_angle=1.0),
                        refinement=RefinementConfig(**json.loads(text)), weight_policy="reset")
        ttr = SfmTTR(model, cfg)
        try:
            t0 = time.perf_counter()
            res = ttr.process_window(frames, seq.intrinsics)
            seconds = time.perf_counter() - t0
        finally:
            ttr.reset_model()
            ttr.close()
        print(f"variant {text}: refined {res.refined} {res.reason} in {seconds:.1f} s, "
              f"scale {res.scale:.3f}, loss {res.loss_before:.3f} -> {res.loss_after:.3f}")
        if res.sfm is not None and res.sfm.ok:
            d_sfm = np.concatenate([o.depths for o in res.sfm.frames.values()]) * res.scale
            print("  SfM depth percentiles 1/10/50/90/99:",
                  np.percentile(d_sfm, [1, 10, 50, 90, 99]).round(1).tolist())
        for f in frames:
            gt = seq.gt(f.name)
            if gt is None:
                continue
            print(f"  {f.name}: abs rel {abs_rel(res.depths_before[f.name], gt):.3f} -> "
                  f"{abs_rel(res.depths[f.name], gt):.3f}")
            print(f"    before: {band_errors(res.depths_before[f.name], gt)}")
            print(f"    after:  {band_errors(res.depths[f.name], gt)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
