#!/usr/bin/env python3
"""Cost of one refinement step per ``refinement.loss`` (is a hybrid step ≤ 2x an SfM step?).

The network, its input size and the refinement settings come from the node's parameter file
(default ``params/kitti.yaml``: the default model, encoder fixed up to its 1/4 map, channels-last)
with ``--set`` overrides. One window of a generated domain-B drive at KITTI size is supervised
from its exact depths and poses (``--points`` points per frame, in place of SfM; the step cost
does not depend on where the points come from), then ``refine_encoder`` runs ``--steps`` steps
with each loss, the losses taking turns ``--repeats`` times so that a busy machine slows them
alike. Reported per loss: the median over repeats of seconds per step, and the one-off
per-window preparation of the photometric terms (``prepare_frames``: images at the network size,
poses, identity errors)::

    .venv/bin/python scripts/studies/loss_step_cost.py --steps 20 --repeats 3
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from sfm_ttr_ros.core import params as schema
from sfm_ttr_ros.core.models import build_model
from sfm_ttr_ros.core.refinement.config import LOSSES
from sfm_ttr_ros.core.refinement.encoder import refine_encoder
from sfm_ttr_ros.core.refinement.photometric import prepare_frames
from sfm_ttr_ros.core.refinement.supervision import FrameSupervision
from sfm_ttr_ros.data.synthetic import make_sequence


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--params-file", default="params/kitti.yaml")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    p.add_argument("--frames", type=int, default=15, help="frames in the window")
    p.add_argument("--points", type=int, default=800, help="supervision points per frame")
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", default="", help="also write the numbers to this JSON file")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    values = {**schema.read_params_file(args.params_file, "refiner"),
              **schema.parse_overrides(args.set)}
    settings = schema.build(values)
    model = build_model(settings.model)
    base = settings.ttr.refinement

    seq = make_sequence(seed=1, domain="B", num_frames=args.frames)
    names = [f"{i:010d}" for i in range(args.frames)]
    rng = np.random.default_rng(0)
    sup = []
    for name, image, depth in zip(names, seq.images, seq.depths, strict=True):
        ys, xs = np.nonzero(depth > 0)
        k = rng.choice(len(xs), args.points, replace=False)
        sup.append(FrameSupervision(name, image, np.c_[xs[k], ys[k]].astype(np.float32),
                                    depth[ys[k], xs[k]].astype(np.float64),
                                    np.full(args.points, 0.9)))
    poses = dict(zip(names, seq.cam_from_world, strict=True))
    images = dict(zip(names, seq.images, strict=True))
    t0 = time.perf_counter()
    frames = prepare_frames(model, names, images, poses, 1.0, seq.intrinsics,
                            base.photometric_config())
    prep = time.perf_counter() - t0

    state = {k: v.clone() for k, v in model.encoder.state_dict().items()}
    per_step: dict[str, list[float]] = {loss: [] for loss in LOSSES}
    for _ in range(args.repeats):
        for loss in LOSSES:
            model.encoder.load_state_dict(state)
            cfg = type(base)(**{**base.__dict__, "steps": args.steps, "loss": loss})
            t0 = time.perf_counter()
            res = refine_encoder(model, sup, cfg, photometric=frames)
            per_step[loss].append((time.perf_counter() - t0) / max(1, res.steps_done))
    out = {"input_size": list(model.input_size), "frames": args.frames,
           "points_per_frame": args.points, "steps": args.steps, "repeats": args.repeats,
           "threads": args.threads, "prepare_frames_s": prep,
           "frozen_encoder_levels": base.frozen_encoder_levels,
           "seconds_per_step": {k: float(np.median(v)) for k, v in per_step.items()},
           "all_runs": per_step}
    sfm = out["seconds_per_step"]["sfm"]
    out["ratio_to_sfm"] = {k: v / sfm for k, v in out["seconds_per_step"].items()}
    for loss in LOSSES:
        print(f"{loss:12s} {out['seconds_per_step'][loss]:.4f} s/step "
              f"({out['ratio_to_sfm'][loss]:.2f}x sfm)")
    print(f"prepare_frames (once per window of {args.frames}): {prep:.2f} s")
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(out, fh, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
