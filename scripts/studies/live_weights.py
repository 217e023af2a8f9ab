"""What a window's weights are worth on the frames after it: the ceiling of the live output.

Runs the node's windows one after another in window mode (``window_size`` frames of the params
file, side by side, its weight policy and checks) and, before each window k+1, predicts that
window's frames with the weights the live output would serve them at best (those left by window
k, as if they arrived the moment window k ended), with those weights shrunk toward the start-up
ones (θ₀ + α·(θ_k − θ₀) for each ``--alpha``), and with the start-up weights; then the window is
refined and its own refined depth (the windowed output) is recorded too. Prints one JSON line
per window and two summaries, over the windows after the first and over the whole sequence
(abs rel, RMSE per variant and its share of the windowed gain). Not a check of the package: a
measurement of the live output's ceiling and of a candidate for it.

    H=../shared/data/hololens_000
    .venv/bin/python scripts/studies/live_weights.py --images $H/images --intrinsics $H/K.txt \\
        --gt-depth $H/depth --gt-scale 1000 --alpha 0.5 > live_weights.jsonl
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def blended(theta0: dict, theta: dict, alpha: float) -> dict:
    """θ₀ + α·(θ − θ₀) for every floating tensor; the others (counters) from θ."""
    return {k: (theta0[k] + alpha * (v - theta0[k]) if v.is_floating_point() else v)
            for k, v in theta.items()}


def gain_shares(summary: dict[str, list[float]]) -> dict[str, list[float]]:
    """Each variant's (abs rel, RMSE) gain over ``no_ttr`` as a share of ``windowed``'s."""
    base, best = summary["no_ttr"], summary["windowed"]
    return {v: [(base[i] - m[i]) / (base[i] - best[i]) for i in (0, 1)]
            for v, m in summary.items()}


def main() -> int:
    from sfm_ttr_ros.core.evaluation import EvalConfig, Evaluator, mean_over_frames
    from sfm_ttr_ros.core.params import build
    from sfm_ttr_ros.core.pipeline import SfmTTR
    from sfm_ttr_ros.core.refinement.encoder import restore_encoder, snapshot_encoder
    from sfm_ttr_ros.tools.cli_args import (
        add_parameter_args,
        add_sequence_args,
        build_model_for,
        open_sequence,
        parameter_values,
    )

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_sequence_args(ap)
    add_parameter_args(ap, (), "params/kitti.yaml")
    ap.add_argument("--alpha", type=float, nargs="*", default=[0.5],
                    help="shrink factors of the carried weights toward the start-up ones")
    args = ap.parse_args()
    seq = open_sequence(args)
    settings = build(parameter_values(args, REPO / "params" / "kitti.yaml")[1])
    size = settings.stream.window_size
    model = build_model_for(settings)
    ttr = SfmTTR(model, settings.ttr)
    theta0 = snapshot_encoder(model)
    variants = ["no_ttr", "carried"] + [f"alpha_{a:g}" for a in args.alpha] + ["windowed"]
    evaluator = Evaluator(EvalConfig())
    # per variant, each GT frame's metrics once: (window index, metrics)
    frame_metrics: dict[str, list[tuple[int, dict]]] = {v: [] for v in variants}

    def predict_with(state, frames):
        current = snapshot_encoder(model)
        restore_encoder(model, state)
        ttr.predictor.clear()
        depths = ttr.predictor.predict([f.image for f in frames])
        restore_encoder(model, current)
        ttr.predictor.clear()
        return depths

    stop = len(seq) if args.max_frames <= 0 else min(len(seq), args.start + args.max_frames)
    for k, start in enumerate(range(args.start, stop, size)):
        frames = seq.frames(start, min(stop, start + size))
        theta = snapshot_encoder(model)
        depths = {"no_ttr": predict_with(theta0, frames), "carried": predict_with(theta, frames)}
        for a in args.alpha:
            depths[f"alpha_{a:g}"] = predict_with(blended(theta0, theta, a), frames)
        res = ttr.process_window(frames, seq.intrinsics)
        depths["windowed"] = [res.depths[f.name] for f in frames]
        row = {"window": k, "frames": [start, start + len(frames) - 1], "refined": res.refined,
               "reason": res.reason_key or res.reason}
        for v in variants:
            for f, d in zip(frames, depths[v], strict=True):
                gt = seq.gt(f.name)
                r = evaluator.add(f.name, d, gt) if gt is not None else None
                if r is not None:
                    frame_metrics[v].append((k, r.metrics))
            s = mean_over_frames([m for w, m in frame_metrics[v] if w == k])
            row[v] = [s["abs_rel"], s["rmse"]]
        print(json.dumps(row), flush=True)
    for name, first in (("windows_after_the_first", 1), ("whole", 0)):
        means = {v: mean_over_frames([m for w, m in frame_metrics[v] if w >= first])
                 for v in variants}
        summary = {v: [means[v]["abs_rel"], means[v]["rmse"]] for v in variants}
        print(json.dumps({"frames": name, "abs_rel_rmse": summary,
                          "share_of_windowed_gain": gain_shares(summary)}))
    ttr.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
