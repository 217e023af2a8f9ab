"""``sfm-ttr`` / ``python -m sfm_ttr_ros``: the ROS-free command line."""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

from sfm_ttr_ros.core.frames import InputError
from sfm_ttr_ros.core.params import build
from sfm_ttr_ros.tools.cli_args import (
    add_parameter_args,
    add_sequence_args,
    build_model_for,
    open_sequence,
    parameter_values,
)

log = logging.getLogger("sfm_ttr_ros")


def cmd_run(args: argparse.Namespace) -> int:
    """Offline SfM-TTR over a whole sequence (the paper's setting) and write the results."""
    from sfm_ttr_ros.core.evaluation import EvalConfig, Evaluator
    from sfm_ttr_ros.core.pipeline import SfmTTR
    from sfm_ttr_ros.core.visualize import colorize_depth, write_ply

    _, values = parameter_values(args)  # bad options fail before any image is read
    settings = build(values)
    seq = open_sequence(args)
    if not 0 <= args.start < len(seq):
        raise InputError(f"--start {args.start} is outside the sequence's {len(seq)} frames "
                         f"(0 .. {len(seq) - 1})")
    stop = len(seq) if args.max_frames <= 0 else min(len(seq), args.start + args.max_frames)
    frames = seq.frames(args.start, stop)
    out = Path(args.out)
    try:
        for sub in ("before", "after"):
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

    evals = {k: Evaluator(EvalConfig(eigen_crop=args.eigen_crop)) for k in ("before", "after")}
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
        **res.summary(),
        "alignment": res.alignment.stats if res.alignment else {},
        "loss_history": res.refinement.loss_history if res.refinement else [],
        "cloud_frame": res.cloud_frame,
        "timings": res.timings,
        "seconds": seconds,
        "seconds_per_frame": seconds / max(1, len(frames)),
    }
    if evals["before"].summary()["frames"]:
        summary["metrics"] = {k: _plain(e.summary()) for k, e in evals.items()}
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=float))
    print(f"{len(frames)} frames, refined={res.refined} {res.reason}".strip())
    if "metrics" in summary:
        from sfm_ttr_ros.core.evaluation import format_table

        print(format_table({"no_ttr": summary["metrics"]["before"],
                            "sfm_ttr": summary["metrics"]["after"]}))
    print(f"results in {out}")
    return 0


def _plain(summary: dict) -> dict:
    return {k: v for k, v in summary.items() if k not in ("per_frame",)}


STREET_FRAMES = 30  # `generate --frames` default (street scenario)


def cmd_generate(args: argparse.Namespace) -> int:
    """Write a synthetic KITTI-format drive (raw layout + improved-GT PNGs)."""
    from sfm_ttr_ros.data.kitti import SEGMENTS_FILE, write_kitti_drive
    from sfm_ttr_ros.data.synthetic import (
        DEFAULT_HARD_SEGMENTS,
        make_hard_sequence,
        make_sequence,
        replace_segments,
    )

    if args.scenario == "hard":
        if args.frames is not None:
            raise InputError("--frames does not apply to --scenario hard: its length is its "
                             "segment list")
        segments = DEFAULT_HARD_SEGMENTS
        for item in args.replace:
            old, sep, new = item.partition("=")
            if not sep:
                raise InputError(f"--replace takes OLD=NEW segment kinds, got {item!r}")
            segments = replace_segments(segments, old.strip(), new.strip())
        seq = make_hard_sequence(seed=args.seed, domain=args.domain, width=args.width,
                                 height=args.height, segments=segments)
    else:
        if args.replace:
            raise InputError("--replace applies to --scenario hard only")
        frames = STREET_FRAMES if args.frames is None else args.frames
        seq = make_sequence(seed=args.seed, domain=args.domain, num_frames=frames,
                            width=args.width, height=args.height)
    drive = write_kitti_drive(seq, args.kitti_raw, args.kitti_gt, drive_number=args.drive_number)
    print(f"wrote {drive}: {len(seq)} frames {args.width}x{args.height} "
          f"to {args.kitti_raw} (GT: {args.kitti_gt})")
    if seq.labels:
        print(f"segment labels in {drive}/image_02/{SEGMENTS_FILE}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="sfm-ttr", description=__doc__)
    p.add_argument("-v", "--verbose", action="store_true")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="SfM-TTR over a whole sequence (offline, as the paper)")
    add_sequence_args(r)
    add_parameter_args(r, ("model", "method"), "none: the schema's defaults, the paper's "
                       "settings")
    r.add_argument("--eigen-crop", action="store_true", help="evaluate inside the Garg crop")
    r.add_argument("--out", required=True, help="output folder")
    r.set_defaults(func=cmd_run)

    g = sub.add_parser("generate", help="write a synthetic KITTI-format drive")
    g.add_argument("--kitti-raw", required=True)
    g.add_argument("--kitti-gt", default=None)
    g.add_argument("--scenario", choices=("street", "hard"), default="street",
                   help="street: ordinary forward driving (default); hard: ordinary driving "
                   "between turning on the spot, a standing camera, cars crossing, a vehicle "
                   "ahead moving with the camera and an exposure change (the frames of "
                   "synthetic.DEFAULT_HARD_SEGMENTS), per-frame labels in "
                   "image_02/segments.txt")
    g.add_argument("--frames", type=int, default=None,
                   help=f"frames of the street scenario (default {STREET_FRAMES}); an error "
                   "with --scenario hard")
    g.add_argument("--replace", action="append", default=[], metavar="OLD=NEW",
                   help="--scenario hard: make every OLD segment a NEW one of the same length "
                   "(repeatable), e.g. truck=drive: the same scene and camera path without the "
                   "truck, frame for frame (a counterfactual drive)")
    g.add_argument("--width", type=int, default=1242)
    g.add_argument("--height", type=int, default=375)
    g.add_argument("--domain", default="B", help="A (training domain) or B (held out)")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--drive-number", type=int, default=1)
    g.set_defaults(func=cmd_generate)

    from sfm_ttr_ros.tools.cli_bag import add_commands as add_bag_commands
    from sfm_ttr_ros.tools.cli_benchmark import add_commands as add_benchmark_commands
    from sfm_ttr_ros.tools.demo import add_commands as add_demo_commands
    from sfm_ttr_ros.tools.params_doc import add_commands as add_params_commands

    add_benchmark_commands(sub)
    add_bag_commands(sub)
    add_demo_commands(sub)
    add_params_commands(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except InputError as exc:
        print(f"sfm-ttr: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("sfm-ttr: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
