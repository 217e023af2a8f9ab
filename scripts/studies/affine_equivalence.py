"""The affine path's equivalence on a generated drive: the default network, and the same network
made affine-invariant (sfm_ttr_ros/tools/affine_wrap.py: p = a_j / D + b_j, random per frame),
refined window by window on the SAME SfM result; both evaluated as depth (the affine path's
output through each frame's own fit, a / (p − b)), median-scaled, the KITTI protocol.

    .venv/bin/python scripts/studies/affine_equivalence.py --kitti-raw /tmp/lv/raw \\
        --drive 2011_09_26_drive_0001_sync --kitti-gt /tmp/lv/gt --frames 300 --out affine_eq.json

params/kitti.yaml's windows and steps, with ``refinement.loss`` sfm (photometric terms need
depth) and ``frozen_encoder_levels`` 0 (the wrapper runs the whole network) for BOTH paths;
``reset`` policy (each window from the start-up weights). Prints per window and overall abs
rel / RMSE before and after for both paths and the affine path's relative gap.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from sfm_ttr_ros.core.alignment.affine import affine_to_depth  # noqa: E402
from sfm_ttr_ros.core.evaluation import Evaluator  # noqa: E402
from sfm_ttr_ros.core.models import build_model  # noqa: E402
from sfm_ttr_ros.core.pipeline import SfmTTR  # noqa: E402
from sfm_ttr_ros.data.sequence import open_kitti  # noqa: E402
from sfm_ttr_ros.tools.affine_wrap import AffineInverse  # noqa: E402
from sfm_ttr_ros.tools.benchmark.settings import (  # noqa: E402
    read_params_file,
    settings_from_params,
)


def summary(ev: Evaluator) -> dict:
    s = ev.summary()
    return {"abs_rel": s["abs_rel"], "rmse": s["rmse"], "frames": s["frames"]}


def summaries(evs: dict[str, Evaluator]) -> dict[str, dict]:
    """:func:`summary` of each evaluator that holds a frame."""
    return {k: s for k, s in ((k, summary(e)) for k, e in evs.items()) if s["frames"]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kitti-raw", required=True)
    ap.add_argument("--drive", required=True)
    ap.add_argument("--kitti-gt", required=True)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--params-file", default=str(REPO / "params" / "kitti.yaml"))
    ap.add_argument("--seed", type=int, default=7, help="the per-frame (a, b) draw")
    ap.add_argument("--affine-ransac-iterations", type=int, default=0,
                    help="alignment.affine_ransac_iterations (0: the params file's)")
    ap.add_argument("--out", default="")
    args = ap.parse_args()

    cfg, stream, model_cfg = settings_from_params(read_params_file(args.params_file))
    cfg.refinement.loss = "sfm"
    cfg.refinement.frozen_encoder_levels = 0
    cfg.weight_policy = "reset"
    if args.affine_ransac_iterations:
        cfg.alignment.affine_ransac_iterations = args.affine_ransac_iterations
    seq = open_kitti(args.kitti_raw, args.drive, args.kitti_gt)
    n = min(args.frames, len(seq))
    frames = seq.frames(0, n)
    plain = SfmTTR(build_model(model_cfg), copy.deepcopy(cfg))
    wrapped = AffineInverse(build_model(model_cfg), [f.image for f in frames], seed=args.seed)
    affine = SfmTTR(wrapped, copy.deepcopy(cfg))
    evs = {k: Evaluator() for k in ("before", "scale_only", "affine")}
    windows = []
    size = stream.window_size
    t0 = time.perf_counter()
    try:
        for start in range(0, n - size + 1, stream.window_stride):
            win = frames[start:start + size]
            so = plain.process_window(win, seq.intrinsics)
            if not so.refined:
                windows.append({"start": start, "refined": False, "reason": so.reason})
                continue
            affine.reconstructor.reconstruct = lambda *a, _sfm=so.sfm, **k: _sfm
            af = affine.process_window(win, seq.intrinsics)
            reg = [f.name for f in win if f.name in so.sfm.frames]
            fit = {n_: k for k, n_ in enumerate(reg)}
            w_ev = {k: Evaluator() for k in evs}
            for f in win:
                gt = seq.gt(f.name)
                if gt is None or f.name not in fit or not af.refined:
                    continue
                depth_af = affine_to_depth(af.alignment.frame(fit[f.name]), af.depths[f.name])
                for key, d in (("before", so.depths_before[f.name]),
                               ("scale_only", so.depths[f.name]), ("affine", depth_af)):
                    evs[key].add(f.name, d, gt)
                    w_ev[key].add(f.name, d, gt)
            row = {"start": start, "refined": bool(af.refined), "reason": af.reason,
                   **summaries(w_ev)}
            windows.append(row)
            if "affine" in row:
                print(f"frames {start}-{start + size - 1}: before {row['before']['abs_rel']:.4f}"
                      f" scale-only {row['scale_only']['abs_rel']:.4f} affine "
                      f"{row['affine']['abs_rel']:.4f}", flush=True)
    finally:
        plain.close()
        affine.close()
    total = {k: summary(e) for k, e in evs.items()}
    gap = {m: total["affine"][m] / total["scale_only"][m] - 1 for m in ("abs_rel", "rmse")}
    report = {"command": " ".join(sys.argv), "seconds": time.perf_counter() - t0,
              "affine_ransac_iterations": cfg.alignment.affine_ransac_iterations,
              "overall": total, "affine_gap": gap, "windows": windows}
    print(json.dumps({"overall": total, "affine_gap": gap}, indent=1))
    if args.out:
        Path(args.out).write_text(json.dumps(report, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
