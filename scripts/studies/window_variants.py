"""Repeat single windows and compare what the window checks see with what refinement did.

pycolmap's multi-threaded mapper does not give the same reconstruction every run: on
hololens_000 windows 1 and 3 come out in one of two (docs/decisions.md, "Window checks"), one
of which refinement turns into worse depth. For each ``--starts`` window (``window_size`` frames
of the params file) and each of ``--reps`` runs this processes the window alone (``reset``,
window mode, every check of the file), and prints one JSON line: abs rel of its frames before
and after (the candidate depth when a check refused it), the sanity statistics (mean
reprojection error, scale spread, inlier ratio), the unsupported change U, and two photometric
statistics of the reconstruction with the network's depth BEFORE refinement and the SfM poses
(Monodepth2's error, t-1 / t+1 sources): ``identity_won``, the share of pixels where the
unwarped source matches better than the warped one (auto-masking), and ``warp_ratio``, the mean
warped error over the mean identity error. Not a check of the package: a measurement of
candidates for one.

    H=../shared/data/hololens_000
    .venv/bin/python scripts/studies/window_variants.py --images $H/images --intrinsics $H/K.txt \\
        --gt-depth $H/depth --gt-scale 1000 --starts 15 45 --reps 6 > variants.jsonl
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[2]


def photometric_stats(model, frames, res, intrinsics) -> dict[str, float]:
    """identity_won and warp_ratio of the window's reconstruction (module docstring)."""
    from sfm_ttr_ros.core.refinement.photometric import (
        PhotometricConfig,
        photometric_loss,
        prepare_frames,
    )

    images = {f.name: f.image for f in frames}
    prepared = prepare_frames(model, [f.name for f in frames], images, res.sfm.frames,
                              res.alignment.scale, intrinsics, PhotometricConfig())
    won, ratio = [], []
    for p in prepared:
        d = torch.from_numpy(res.depths_before[p.name])[None, None]
        d = torch.nn.functional.interpolate(d, size=tuple(p.target.shape[-2:]),
                                            mode="bilinear", align_corners=False)
        with torch.no_grad():
            _, maps = photometric_loss(d, p.target, p.sources, p.K, p.poses,
                                       identity=p.identity, return_maps=True)
            warped = photometric_loss(d, p.target, p.sources, p.K, p.poses, automask=False)
        won.append(float(maps.identity_mask.float().mean()))
        ratio.append(float(warped / p.identity.min(1)[0].mean()))
    return {"identity_won": float(np.mean(won)) if won else float("nan"),
            "warp_ratio": float(np.mean(ratio)) if ratio else float("nan")}


def main() -> int:
    from sfm_ttr_ros.core.evaluation import EvalConfig, Evaluator
    from sfm_ttr_ros.core.models.registry import build_model
    from sfm_ttr_ros.core.params import build, parse_overrides, read_params_file
    from sfm_ttr_ros.core.pipeline import SfmTTR
    from sfm_ttr_ros.tools.cli_args import open_sequence

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kitti-raw")
    ap.add_argument("--drive", default="2011_09_26_drive_0001_sync")
    ap.add_argument("--kitti-gt")
    ap.add_argument("--images")
    ap.add_argument("--intrinsics")
    ap.add_argument("--gt-depth")
    ap.add_argument("--gt-scale", type=float, default=256.0)
    ap.add_argument("--params-file", default=str(REPO / "params" / "kitti.yaml"))
    ap.add_argument("--starts", type=int, nargs="+", required=True,
                    help="first frame of each window")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="a parameter over the file, e.g. check.max_reprojection_error=1.0")
    ap.add_argument("--reps", type=int, default=1)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    seq = open_sequence(args)
    settings = build({**read_params_file(args.params_file, "refiner"),
                      **parse_overrides(args.set)})
    size = settings.stream.window_size
    for start in args.starts:
        frames = seq.frames(start, min(len(seq), start + size))
        for rep in range(args.reps):
            model = build_model(settings.model)
            ttr = SfmTTR(model, settings.ttr)
            res = ttr.process_window(frames, seq.intrinsics)
            ev = {k: Evaluator(EvalConfig()) for k in ("before", "after")}
            for f in frames:
                gt = seq.gt(f.name)
                if gt is not None:
                    ev["before"].add(f.name, res.depths_before[f.name], gt)
                    ev["after"].add(f.name, res.depths_candidate.get(f.name, res.depths[f.name]),
                                    gt)
            c = res.check
            row = {"start": start, "rep": rep, "refined": res.refined,
                   "reason": res.reason_key or res.reason,
                   "abs_rel_before": ev["before"].summary().get("abs_rel"),
                   "abs_rel_after": ev["after"].summary().get("abs_rel"),
                   "scale": res.alignment.scale if res.alignment else None,
                   "reprojection_error": c.reprojection_error if c else None,
                   "scale_spread": c.scale_spread if c else None,
                   "inlier_ratio": c.inlier_ratio if c else None,
                   "unsupported_change": c.unsupported_change if c else None,
                   "sfm_attempts": [{k: a[k] for k in ("seed", "registered", "points",
                                                          "reprojection_error", "kept")}
                                    for a in (res.sfm.attempts if res.sfm else [])]}
            if res.sfm is not None and res.alignment is not None:
                row.update(photometric_stats(model, frames, res, seq.intrinsics))
            print(json.dumps(row), flush=True)
            ttr.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
