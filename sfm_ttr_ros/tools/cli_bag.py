"""The rosbag subcommands of ``sfm-ttr``: ``kitti-to-bag``, ``play``, and the bag mode of
``evaluate`` (:func:`evaluate_bag_command`, wired into ``sfm-ttr evaluate`` by ``cli.py``).

``cli.py`` calls :func:`add_commands` with its subparsers; every command returns an exit code
and raises :class:`~sfm_ttr_ros.core.frames.InputError` for bad input (``cli.main`` maps it to 2).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.ros.bag import STORAGES
from sfm_ttr_ros.ros.bag_evaluation import DEFAULT_PRED_TOPIC
from sfm_ttr_ros.ros.kitti_bag import DEPTH_GT_TOPIC, ODOM_TOPIC
from sfm_ttr_ros.tools.report_files import write_json


def cmd_kitti_to_bag(args: argparse.Namespace) -> int:
    """Convert a KITTI raw drive (+ improved GT) into a rosbag2."""
    from sfm_ttr_ros.ros.kitti_bag import kitti_to_bag

    res = kitti_to_bag(args.kitti_raw, args.drive, args.out, gt_root=args.kitti_gt,
                       storage=args.storage, start=args.start, max_frames=args.max_frames,
                       progress=not args.quiet, compressed=args.compressed)
    print(f"wrote {res.path} ({res.storage}): {res.frames} frames {res.width}x{res.height}, "
          f"{res.gt_frames} with ground truth, {res.seconds:.1f} s")
    for topic, n in res.counts.items():
        print(f"  {topic}: {n}")
    if res.odometry == "poses.txt":
        print(f"odometry on {ODOM_TOPIC}: the camera's poses from the drive's poses.txt")
    elif res.odometry == "oxts":
        print(f"odometry on {ODOM_TOPIC}: the GPS/IMU's poses from oxts/ (the KITTI devkit's "
              "conversion; the IMU's position and orientation, not the camera's)")
    else:
        print(f"no odometry ({ODOM_TOPIC} not written): the drive has neither poses.txt nor "
              "oxts/data")
    print(f"play it with: sfm-ttr play {res.path}   (or: ros2 bag play {res.path})")
    return 0


def cmd_play(args: argparse.Namespace) -> int:
    """Play a rosbag2 into the ROS 2 graph (for machines without ros2cli)."""
    from sfm_ttr_ros.ros.player import PlaybackInterrupted, play_bag

    try:
        res = play_bag(args.bag, rate=args.rate, clock=args.clock,
                       wait_for_subscribers=not args.no_wait, topics=args.topics,
                       progress=not args.quiet, wait_topics=args.wait_for,
                       wait_timeout=args.wait_timeout, qos_depth=args.qos_depth)
    except PlaybackInterrupted as exc:
        print(f"play: interrupted after {exc.result.total} messages", file=sys.stderr)
        return 130
    print(f"published {res.total} messages ({res.bag_seconds:.1f} s of bag time) in "
          f"{res.seconds:.1f} s" + (f", {res.clock} /clock" if args.clock else ""))
    for topic, n in sorted(res.published.items()):
        note = "  (no subscriber)" if topic in res.no_subscriber else ""
        print(f"  {topic}: {n}{note}")
    if res.unacked:
        print(f"play: warning: not every message on {', '.join(res.unacked)} was acknowledged "
              "by its subscribers before exit", file=sys.stderr)
    return 0


def add_evaluate_bag_arguments(p: argparse.ArgumentParser) -> None:
    """The bag options of ``sfm-ttr evaluate`` (``--bag``, ``--gt-bag``, ``--pred-topic``,
    ``--gt-topic``); the metric options (eigen_crop, median_scaling, max_depth, out) are the
    evaluate command's own."""
    g = p.add_argument_group("bag mode (a recorded bag of predicted depth, matched by stamp)")
    g.add_argument("--bag", help="rosbag2 holding the predicted depth (e.g. a recording of the "
                                 "refiner's ~/depth/image)")
    g.add_argument("--gt-bag", default=None,
                   help="rosbag2 holding the ground truth (default: the same bag)")
    g.add_argument("--pred-topic", default=DEFAULT_PRED_TOPIC,
                   help=f"predicted depth topic (default {DEFAULT_PRED_TOPIC}); a refiner "
                        "output is read with its relative twin (depth not yet in metres)")
    g.add_argument("--gt-topic", default=DEPTH_GT_TOPIC,
                   help=f"ground-truth depth topic (default {DEPTH_GT_TOPIC})")


def evaluate_bag_command(args: argparse.Namespace) -> int:
    """KITTI metrics of a bag's predicted depth against GT matched by header stamp.

    Reads ``args.bag``, ``args.gt_bag`` (None = same), ``args.pred_topic``, ``args.gt_topic``,
    ``args.eigen_crop``, ``args.median_scaling``, ``args.max_depth`` and ``args.out`` (optional
    JSON path); missing attributes take the defaults. Prints the table and the frame counts;
    returns 0, or 1 when no frame could be evaluated.
    """
    from sfm_ttr_ros.core.evaluation import MAX_DEPTH, EvalConfig, format_table
    from sfm_ttr_ros.ros.bag_evaluation import evaluate_bag

    bag = getattr(args, "bag", None)
    if not bag:
        raise InputError("evaluate: give the bag of predicted depth (--bag BAG)")
    pred_topic = getattr(args, "pred_topic", None) or DEFAULT_PRED_TOPIC
    gt_topic = getattr(args, "gt_topic", None) or DEPTH_GT_TOPIC
    max_depth = getattr(args, "max_depth", None)
    config = EvalConfig(max_depth=MAX_DEPTH if max_depth is None else float(max_depth),
                        eigen_crop=bool(getattr(args, "eigen_crop", False)),
                        median_scaling=bool(getattr(args, "median_scaling", True)))
    res = evaluate_bag(bag, getattr(args, "gt_bag", None), pred_topic, gt_topic, config,
                       progress=not getattr(args, "quiet", False))
    print(f"{res['pred_bag']} {pred_topic} vs {res['gt_bag']} {gt_topic} "
          f"(eigen crop {'on' if config.eigen_crop else 'off'}, median scaling "
          f"{'on' if config.median_scaling else 'off'}, cap {config.max_depth:g} m)")
    print(format_table({pred_topic: res}))
    print(f"frames: {res['pred_frames']} predicted, {res['gt_frames']} with GT, "
          f"{res['matched']} matched by stamp, {res['frames']} evaluated, "
          f"{res['skipped']} skipped; {res['missing_gt']} predictions without GT, "
          f"{res['missing_pred']} GT frames without a prediction")
    if res["duplicate_pred"] or res["duplicate_gt"]:
        print(f"repeated stamps (first message used): {res['duplicate_pred']} predicted, "
              f"{res['duplicate_gt']} GT")
    for name, reason in res["skipped_frames"].items():
        print(f"  skipped {name}: {reason}")
    out = getattr(args, "out", None)
    if out:
        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        write_json(out, res)
        print(f"results in {out}")
    if res["frames"] == 0:
        print("evaluate: no frame could be evaluated (no prediction stamp matches a GT stamp, "
              "or none has valid GT)", file=sys.stderr)
        return 1
    return 0


def add_commands(subparsers) -> None:
    """Register ``kitti-to-bag`` and ``play`` on ``sfm-ttr``'s subparsers."""
    k = subparsers.add_parser(
        "kitti-to-bag", help="convert a KITTI raw drive (+ improved GT) into a rosbag2",
        description="Write /kitti/camera_color_left/{image_raw,camera_info,depth_gt} "
                    "(kitti2bag names) and, when the drive has poses.txt or oxts/, /kitti/odom "
                    "(nav_msgs/Odometry) from a KITTI raw drive into a rosbag2 that ros2 bag play "
                    "and sfm-ttr play read.")
    k.add_argument("--kitti-raw", required=True, help="KITTI raw root (holds <date>/<drive>)")
    k.add_argument("--drive", required=True, help="<date>_drive_XXXX_sync")
    k.add_argument("--kitti-gt", default=None,
                   help="KITTI depth GT root (holds {train,val}/<drive>/proj_depth/groundtruth)")
    k.add_argument("--out", required=True, help="output bag folder (must not exist)")
    k.add_argument("--storage", choices=STORAGES, default="mcap",
                   help="rosbag2 storage plugin (default mcap, Jazzy's default)")
    k.add_argument("--start", type=int, default=0, help="first frame index")
    k.add_argument("--max-frames", type=int, default=0, help="0 = all")
    k.add_argument("--compressed", action="store_true",
                   help="images as sensor_msgs/CompressedImage (JPEG, quality 95) on "
                        ".../image_raw/compressed (image_transport's compressed transport)")
    k.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    k.set_defaults(func=cmd_kitti_to_bag)

    p = subparsers.add_parser(
        "play", help="play a rosbag2 into ROS 2 (no ros2cli needed)",
        description="Publish every message of a rosbag2 with its recorded timing (scaled by "
                    "--rate), RELIABLE QoS, after waiting for subscribers.")
    p.add_argument("bag", help="rosbag2 folder")
    p.add_argument("--rate", type=float, default=1.0, help="playback speed factor")
    p.add_argument("--clock", action="store_true", help="publish the bag time on /clock")
    p.add_argument("--no-wait", action="store_true",
                   help="start at once instead of waiting for subscribers")
    p.add_argument("--wait-for", action="append", metavar="TOPIC", default=None,
                   help="wait until TOPIC has a subscriber (repeatable; default: wait until "
                        "any topic of the bag has one)")
    p.add_argument("--wait-timeout", type=float, default=30.0,
                   help="seconds to wait for subscribers (default 30)")
    p.add_argument("--topics", nargs="+", default=None, help="play only these topics")
    p.add_argument("--qos-depth", type=int, default=100,
                   help="publisher KEEP_LAST depth (RELIABLE; default 100)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_play)
