"""``sfm-ttr benchmark`` and ``sfm-ttr evaluate`` (folder mode; the bag mode lives in
:mod:`sfm_ttr_ros.tools.cli_bag`). :func:`add_commands` registers both on the ``sfm-ttr`` parser.

Benchmark settings: the node's parameter file (``--params-file``, default the installed or the
repository's ``params/kitti.yaml``) gives the windows, keyframes and SfM-TTR options, so the
online mode runs as the node would with that file; the flags and ``--set name=value`` given on
the command line override the file's values (:mod:`sfm_ttr_ros.tools.cli_args`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.ros.bag_evaluation import DEFAULT_PRED_TOPIC
from sfm_ttr_ros.ros.kitti_bag import DEPTH_GT_TOPIC
from sfm_ttr_ros.tools.cli_args import (
    add_parameter_args,
    add_sequence_args,
    command_line,
    open_sequence,
)
from sfm_ttr_ros.tools.one_sequence import (
    benchmark_sequence,
    benchmark_values,
    check_benchmark_options,
)
from sfm_ttr_ros.tools.one_sequence import eval_config as _eval_config


def _add_eval_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("evaluation (KITTI protocol)")
    g.add_argument("--eigen-crop", action="store_true",
                   help="evaluate inside the Eigen (Garg) crop only")
    g.add_argument("--no-median-scaling", dest="median_scaling", action="store_false",
                   help="no per-image median scaling (metric predictions)")
    g.add_argument("--max-depth", type=float, default=80.0, help="depth cap in metres")
    g.add_argument("--min-depth", type=float, default=1e-3, help="smallest valid GT depth")
    g.add_argument("--prediction", choices=("auto", "depth", "relative_inverse_depth"),
                   default="auto",
                   help="what the predictions hold: depth (median-scaled), or affine-invariant "
                        "inverse depth (a per-frame least-squares scale and shift to 1/GT, the "
                        "MiDaS protocol); auto: the network's output kind (benchmark), depth "
                        "(evaluate)")


# ---------------------------------------------------------------------------------------------
# benchmark
# ---------------------------------------------------------------------------------------------


def add_benchmark_parser(sub) -> argparse.ArgumentParser:
    from sfm_ttr_ros.tools.benchmark import DEFAULT_MODES, MODES

    b = sub.add_parser(
        "benchmark",
        help="no TTR vs SfM-TTR online (the node's windows) vs offline (whole sequence)",
        description="Run, on the same frames with the same network, (a) no test-time "
                    "refinement, (b) what the node gives (node_online: its windows, objective "
                    "and weight policy, same code path, no ROS transport), (c) the paper's "
                    "SfM-TTR online in the same windows and (d) offline over the whole sequence; "
                    "evaluate every frame with ground truth and write OUT/results.json, "
                    "results.md, per_frame.csv and figure.png.")
    add_sequence_args(b)
    add_parameter_args(b, ("model", "method", "windows"),
                       "params/kitti.yaml, installed or from the repository")
    g = b.add_argument_group("benchmark")
    g.add_argument("--out", required=True, help="output folder")
    g.add_argument("--modes", nargs="+", choices=MODES, default=list(DEFAULT_MODES),
                   help=f"which modes to run (default: {' '.join(DEFAULT_MODES)}); "
                        "node_online = the node's windows with the parameter file's objective "
                        "and weight policy as they are; sfm_ttr_live feeds the frames in real "
                        "time at --rate; sfm_ttr_*, ph_ttr_* and hybrid_* refine with "
                        "refinement.loss sfm (the paper's Eq. (5)) / photometric / hybrid")
    g.add_argument("--rate", type=float, default=10.0,
                   help="input rate of sfm_ttr_live in Hz (default 10, a KITTI camera)")
    g.add_argument("--node-rate", type=float, default=0.0, metavar="HZ",
                   help="feed node_online at this rate in virtual time: frames queue while "
                        "the worker spends its measured time, and the keyframe rule skips the "
                        "stale ones, as the node on this machine would (default 0: each frame "
                        "waits for the one before, the windows' accuracy at any speed)")
    g.add_argument("--offline-max-frames", type=int, default=0,
                   help="offline mode in chunks of at most N frames, each from the original "
                        "weights (0 = the whole sequence in one window, as the paper)")
    g.add_argument("--figure-frames", type=int, default=2,
                   help="frames shown in figure.png (evenly spaced among the GT frames)")
    g.add_argument("--save-depth", action="store_true",
                   help="also write every depth as OUT/depth/<mode>/<frame>.npy")
    _add_eval_args(b)
    from sfm_ttr_ros.tools.split.command import add_split_args

    add_split_args(b)
    b.set_defaults(func=cmd_benchmark)
    return b


def cmd_benchmark(args: argparse.Namespace) -> int:
    from sfm_ttr_ros.core.params import build
    from sfm_ttr_ros.requirements import check_sfm_dependencies
    from sfm_ttr_ros.tools.benchmark import results_markdown

    check_sfm_dependencies()  # a pycolmap too old for SfM: one error now, not per window
    if getattr(args, "split", None):
        from sfm_ttr_ros.tools.split.command import run_split_command

        return run_split_command(args, "benchmark")
    params_path, values = benchmark_values(args)
    settings = build(values)
    check_benchmark_options(args)
    seq = open_sequence(args)
    results = benchmark_sequence(seq, settings, args, args.out, start=args.start,
                                 max_frames=args.max_frames, params_path=params_path,
                                 command=command_line())
    print(results_markdown(results).split("Command:")[0].rstrip())
    print(f"\nresults in {args.out}")
    return 0


# ---------------------------------------------------------------------------------------------
# evaluate
# ---------------------------------------------------------------------------------------------


def add_evaluate_parser(sub) -> argparse.ArgumentParser:
    e = sub.add_parser(
        "evaluate",
        help="KITTI depth metrics of a folder of predictions, or of a recorded bag",
        description="KITTI metrics (Abs Rel, Sq Rel, RMSE, RMSE log, d<1.25^k) of predicted "
                    "depths against ground truth: folders (--pred DIR... --gt DIR, matched by "
                    "file name) or a recorded bag of the node's depth against the GT topic "
                    "(--bag BAG, matched by stamp).")
    f = e.add_argument_group("folder mode")
    f.add_argument("--pred", nargs="+", metavar="DIR",
                   help="prediction folder(s): NAME.npy (float depth) or NAME.png (uint16 "
                        "depth x pred-scale); several folders are compared row by row, gains "
                        "against the first")
    f.add_argument("--gt", metavar="DIR",
                   help="ground-truth folder: NAME.png, uint16 depth x gt-scale, 0 = none "
                        "(improved or raw-LiDAR GT exported the same way)")
    f.add_argument("--gt-scale", type=float, default=256.0,
                   help="GT PNG value per metre (KITTI: 256; hololens_000: 1000)")
    f.add_argument("--pred-format", choices=["auto", "npy", "png"], default="auto",
                   help="auto: npy when the folder holds .npy files, else png")
    f.add_argument("--pred-scale", type=float, default=None,
                   help="PNG prediction value per metre (default: --gt-scale)")
    try:  # the bag mode's own options, from the module that implements it
        from sfm_ttr_ros.tools.cli_bag import add_evaluate_bag_arguments
    except ImportError:
        bag = e.add_argument_group("bag mode")
        bag.add_argument("--bag", help="rosbag2 holding the node's depth (and the GT topic)")
        bag.add_argument("--gt-bag", help="another bag holding the GT topic (default: --bag)")
        bag.add_argument("--pred-topic", default=DEFAULT_PRED_TOPIC)
        bag.add_argument("--gt-topic", default=DEPTH_GT_TOPIC)
    else:
        add_evaluate_bag_arguments(e)
    _add_eval_args(e)
    e.add_argument("--out", help="write the full results (per frame too) to this JSON file")
    e.set_defaults(func=cmd_evaluate)
    return e


def _pred_format(folder: Path, wanted: str) -> str:
    if wanted != "auto":
        return wanted
    return "npy" if folder.is_dir() and any(folder.glob("*.npy")) else "png"


def evaluate_folder_command(args: argparse.Namespace) -> int:
    from sfm_ttr_ros.core.evaluation import evaluate_folders, format_table, relative_gain

    if not args.pred or not args.gt:
        raise InputError("folder mode needs both --pred DIR and --gt DIR")
    cfg = _eval_config(args)
    folders = [Path(p) for p in args.pred]
    labels = [p.name or str(p) for p in folders]
    if len(set(labels)) != len(labels):
        labels = [str(p) for p in folders]
    results: dict[str, dict] = {}
    for label, folder in zip(labels, folders, strict=True):
        res = evaluate_folders(folder, args.gt, args.gt_scale, _pred_format(folder,
                               args.pred_format), cfg, args.pred_scale)
        if res["frames"] == 0 and res["skipped"] == 0:
            raise InputError(f"no prediction in {folder} matches a ground-truth file of "
                             f"{args.gt} by name ({res['missing_pred']} GT frames without one)")
        results[label] = res
    print(format_table(results, decimals=4).rstrip())
    for label, res in results.items():
        notes = [f"{res['frames']} frames evaluated"]
        for key, what in (("skipped", "skipped (no valid GT / prediction)"),
                          ("missing_pred", "GT frames without a prediction"),
                          ("missing_gt", "predictions without GT"),
                          ("invalid_pred", "non-finite predicted pixels at GT")):
            if res.get(key):
                notes.append(f"{res[key]} {what}")
        print(f"{label}: " + ", ".join(notes))
    gains = {}
    if len(results) > 1:
        first = labels[0]
        for label in labels[1:]:
            gains[label] = relative_gain(results[first], results[label])
            g = gains[label]
            print(f"{label} vs {first}: abs rel {100 * g['abs_rel']:+.1f} %, "
                  f"RMSE {100 * g['rmse']:+.1f} % (positive = better)")
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        from sfm_ttr_ros.tools.report_files import write_json

        doc = {"gt": str(args.gt), "gt_scale": args.gt_scale,
               "eval": {"min_depth": cfg.min_depth, "max_depth": cfg.max_depth,
                        "eigen_crop": cfg.eigen_crop, "median_scaling": cfg.median_scaling},
               "results": results, "relative_gain": gains, "command": command_line()}
        write_json(out, doc)
        print(f"results in {out}")
    empty = [label for label, res in results.items() if res["frames"] == 0]
    if empty:
        print(f"evaluate: no frame could be evaluated for {', '.join(empty)} (no valid GT "
              "pixel or no usable prediction in any frame)", file=sys.stderr)
        return 1
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    if args.bag:
        if args.pred or args.gt:
            raise InputError("give either --bag (bag mode) or --pred/--gt (folder mode), "
                             "not both")
        try:
            from sfm_ttr_ros.tools.cli_bag import evaluate_bag_command
        except ImportError as exc:
            raise InputError(f"bag evaluation is not available in this installation "
                             f"(sfm_ttr_ros.tools.cli_bag: {exc})") from exc
        return int(evaluate_bag_command(args) or 0)
    if args.gt_bag:
        raise InputError("--gt-bag needs --bag")
    if not args.pred and not args.gt:
        raise InputError("give --pred DIR --gt DIR (folder mode) or --bag BAG (bag mode)")
    return evaluate_folder_command(args)


def add_commands(subparsers) -> None:
    """Register ``benchmark``, its ``speed`` measurement and ``evaluate`` on the ``sfm-ttr``
    sub-command parser."""
    from sfm_ttr_ros.tools.cli_speed import add_speed_parser

    add_benchmark_parser(subparsers)
    add_speed_parser(subparsers)
    add_evaluate_parser(subparsers)
