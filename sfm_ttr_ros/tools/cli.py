"""``sfm-ttr`` / ``python -m sfm_ttr_ros``: the ROS-free command line."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.params import build
from sfm_ttr_ros.tools.cli_args import (
    add_parameter_args,
    add_sequence_args,
    open_sequence,
    parameter_values,
)

log = logging.getLogger("sfm_ttr_ros")


def cmd_run(args: argparse.Namespace) -> int:
    """Offline SfM-TTR over a whole sequence (the paper's setting) and write the results."""
    from sfm_ttr_ros.requirements import check_sfm_dependencies
    from sfm_ttr_ros.tools.one_sequence import run_whole_sequence

    check_sfm_dependencies()  # a pycolmap too old for SfM: one error now, not per window
    if getattr(args, "split", None):
        from sfm_ttr_ros.tools.split.command import run_split_command

        return run_split_command(args, "run")
    _, values = parameter_values(args)  # bad options fail before any image is read
    settings = build(values)
    seq = open_sequence(args)
    summary = run_whole_sequence(seq, settings, args.out, start=args.start,
                                 max_frames=args.max_frames, eigen_crop=args.eigen_crop)
    print(f"{summary['frames_total']} frames, refined={summary['refined']} "
          f"{summary['reason']}".strip())
    if "metrics" in summary:
        from sfm_ttr_ros.core.evaluation import format_table

        print(format_table({"no_ttr": summary["metrics"]["before"],
                            "sfm_ttr": summary["metrics"]["after"]}))
    print(f"results in {args.out}")
    return 0


STREET_FRAMES = 30  # `generate --frames` default (street scenario)


def cmd_generate(args: argparse.Namespace) -> int:
    """Write a synthetic KITTI-format drive (raw layout + improved-GT PNGs)."""
    from sfm_ttr_ros.data.kitti import SEGMENTS_FILE, write_kitti_drive
    from sfm_ttr_ros.data.poses import CAMERA_HEIGHT_FILE, POSES_FILE
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
    drive_dir = Path(args.kitti_raw) / drive[:10] / drive
    print(f"camera height above the road: {seq.params.camera_height:.3f} m "
          f"({drive_dir / CAMERA_HEIGHT_FILE}); camera poses (camera-to-world, metres): "
          f"{drive_dir / POSES_FILE}")
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
    from sfm_ttr_ros.tools.split.command import add_split_args

    add_split_args(r)
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
    g.add_argument("--domain", default="B", help="A (training domain), B (held out) or C (a "
                   "road with real edges: camber, curbs, a wall, a track bed, the bonnet)")
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
