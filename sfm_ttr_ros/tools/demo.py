"""``sfm-ttr demo``: KITTI drive → rosbag2 → the ``refiner`` node → evaluation, with nothing to
download.

Steps (each printed as it runs):

1. the drive: with no arguments a synthetic KITTI-format drive of the held-out domain "B"
   (:mod:`sfm_ttr_ros.data.synthetic`, written in the real KITTI raw + improved-GT layouts),
   a real one with ``--kitti-raw/--kitti-gt/--drive``, or any image folder with its K and GT
   depth (``--images/--intrinsics/--gt-depth``, e.g. hololens_000), written in those layouts
   (with the camera poses of a ``poses.txt`` beside the folder, or of the synthetic drive);
2. ``kitti-to-bag`` (:func:`sfm_ttr_ros.ros.kitti_bag.kitti_to_bag`; the poses on
   ``/kitti/odom``);
3. the unrefined network's depth for every image of the bag (same model, same weights) → a
   ``no_ttr`` bag with the same stamps;
4. ``refiner`` started as a separate process with ``params/kitti.yaml`` (+ ``--set`` overrides),
   remapped to the bag's topics; the bag played into it (:func:`sfm_ttr_ros.ros.player.play_bag`)
   while ``/refiner/depth/image`` is recorded (:class:`sfm_ttr_ros.ros.player.TopicRecorder`)
   until every image came back; then SIGINT;
5. both bags evaluated against the GT topic matched by stamp
   (:func:`sfm_ttr_ros.ros.bag_evaluation.evaluate_bag`),
   the before/after table printed and written (``results.md`` / ``results.json`` /
   ``per_frame.csv``, by the benchmark's writer, :mod:`sfm_ttr_ros.tools.report_files`) with a
   qualitative figure of the frame of median gain, saying so (``figure.png``,
   :mod:`sfm_ttr_ros.tools.demo_figure`).

ROS traffic stays on this machine (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``) on a random
``ROS_DOMAIN_ID`` unless one is set.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import random
import shutil
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from sfm_ttr_ros.core import params as schema
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.data.poses import POSES_FILE
from sfm_ttr_ros.ros import names
from sfm_ttr_ros.tools.demo_figure import FigureFrame, choose_frame, draw_figure
from sfm_ttr_ros.tools.process import interrupt

DEPTH_TOPIC = names.DEPTH_TOPIC_RESOLVED  # the refiner's live depth: /refiner/depth/image
REFINED_TOPIC = names.DEPTH_REFINED_TOPIC_RESOLVED  # each frame out of its window
# depth not (yet) in metres comes on the relative twins (REP 118): each output is read from both
TWINS = {t: names.relative_twin_of(t) for t in (DEPTH_TOPIC, REFINED_TOPIC)}
LIVE_GRACE_S = 5.0  # after the last refined depth, how long to wait for missing live ones
NODE_START_TIMEOUT_S = 120.0  # from starting the refiner to its publishers being discovered
ACCOUNTING_FILE = "refiner_accounting.json"  # the node's final accounting, written as it stops


def _say(msg: str) -> None:
    print(f"[demo] {msg}", file=sys.stderr, flush=True)


@dataclass
class DemoOptions:
    out: Path = Path("sfm_ttr_demo")
    kitti_raw: str | None = None
    kitti_gt: str | None = None
    drive: str | None = None
    images: str | None = None  # an image folder (with intrinsics and gt_depth) instead
    intrinsics: str | None = None
    gt_depth: str | None = None
    gt_scale: float = 256.0
    start: int = 0  # real drive or image folder: first frame
    # The synthetic drive and how fast it is played: slow enough that the first window's
    # weights reach ~/depth while the drive still plays, so that the live output shows what a
    # robot gets, not only the windowed one.
    frames: int = 45
    width: int = 1242
    height: int = 375
    domain: str = "B"
    seed: int = 0
    gt_skip_ends: int = 5  # synthetic drive: frames without GT at each end (KITTI: 5)
    max_frames: int = 0  # real drive or image folder: 0 = all
    params_file: str | None = None  # default: params/kitti.yaml
    overrides: list[str] = field(default_factory=list)  # NAME=VALUE, as --set everywhere
    rate: float = 0.15
    timeout_s: float = 1800.0
    threads: int = 2
    storage: str = "mcap"
    eigen_crop: bool = False
    overwrite: bool = False
    compressed: bool = False  # the bag's images as JPEG CompressedImages (image_transport)


def bag_image_topic(compressed: bool) -> str:
    """The bag's image topic: kitti2bag's image_raw, or its image_transport ``/compressed``."""
    from sfm_ttr_ros.ros.kitti_bag import COMPRESSED_SUFFIX, IMAGE_TOPIC

    return IMAGE_TOPIC + COMPRESSED_SUFFIX if compressed else IMAGE_TOPIC


def _prepare_out(opts: DemoOptions) -> Path:
    out = Path(opts.out)
    if out.exists():
        if not opts.overwrite:
            raise InputError(f"{out} exists: choose another --out or pass --overwrite")
        shutil.rmtree(out)
    out.mkdir(parents=True)
    return out


def _make_drive(opts: DemoOptions, out: Path) -> tuple[str, str, str]:
    if opts.kitti_raw or opts.kitti_gt or opts.drive:
        if not (opts.kitti_raw and opts.kitti_gt and opts.drive):
            raise InputError("a real drive needs all of --kitti-raw, --kitti-gt and --drive")
        return opts.kitti_raw, opts.kitti_gt, opts.drive
    if opts.images or opts.intrinsics or opts.gt_depth:
        return _image_folder_drive(opts, out)
    from sfm_ttr_ros.data.kitti import write_kitti_drive
    from sfm_ttr_ros.data.synthetic import make_sequence

    _say(f"1/5 generating a synthetic KITTI drive: {opts.frames} frames {opts.width}x"
         f"{opts.height}, domain {opts.domain} (seed {opts.seed})")
    seq = make_sequence(seed=opts.seed, domain=opts.domain, num_frames=opts.frames,
                        width=opts.width, height=opts.height)
    raw, gt = out / "kitti_raw", out / "kitti_gt"
    drive = write_kitti_drive(seq, raw, gt, gt_skip_ends=opts.gt_skip_ends)
    return str(raw), str(gt), drive


def _image_folder_drive(opts: DemoOptions, out: Path) -> tuple[str, str, str]:
    """An image folder, its K file and GT depth written as a KITTI drive (stamps at 10 Hz,
    intrinsics as P_rect_02, GT as improved-GT PNGs where the folder has them, the camera poses
    of a ``poses.txt`` beside the folder as the drive's, for /kitti/odom), read one frame at a
    time (a long folder is never all in memory)."""
    from types import SimpleNamespace

    from sfm_ttr_ros.core.frames import load_rgb
    from sfm_ttr_ros.data.kitti import write_kitti_drive
    from sfm_ttr_ros.data.sequence import open_image_folder

    if not (opts.images and opts.intrinsics and opts.gt_depth):
        raise InputError("an image folder needs all of --images, --intrinsics and --gt-depth "
                         "(the demo scores the node against the ground truth)")
    seq = open_image_folder(opts.images, opts.intrinsics, opts.gt_depth, opts.gt_scale)
    _say(f"1/5 writing {len(seq)} images of {opts.images} as a KITTI drive")
    drive_seq = SimpleNamespace(images=_Lazy(load_rgb, seq.image_paths),
                                depths=_Lazy(seq.gt, seq.names), stamps=seq.stamps,
                                intrinsics=seq.intrinsics,
                                cam_to_world=seq.poses)
    _say(f"   camera poses from {POSES_FILE} beside {opts.images} (on /kitti/odom)"
         if seq.poses is not None
         else f"   no {POSES_FILE} beside {opts.images}: the bag gets no odometry")
    raw, gt = out / "kitti_raw", out / "kitti_gt"
    return str(raw), str(gt), write_kitti_drive(drive_seq, raw, gt, gt_skip_ends=0)


class _Lazy(Sequence):
    """``[read(k) for k in keys]``, each item read when it is asked for."""

    def __init__(self, read, keys) -> None:
        self._read, self._keys = read, list(keys)

    def __len__(self) -> int:
        return len(self._keys)

    def __getitem__(self, i):
        return self._read(self._keys[i])


def _predict_no_ttr(bag: Path, out_bag: Path, model, storage: str,
                    compressed: bool = False) -> int:
    """The unrefined network's depth for every image of ``bag``, same stamps, into ``out_bag``."""
    from sfm_ttr_ros.ros.bag import IMAGE_MSGTYPE, BagRecorder, bag_rgb, depth_msg, read_bag

    n = 0
    with BagRecorder(out_bag, storage) as rec:
        rec.add_topic(TWINS[DEPTH_TOPIC], IMAGE_MSGTYPE)  # the network's units, not metres
        for _, _, stamp_ns, msg in read_bag(bag, [bag_image_topic(compressed)]):
            rgb = bag_rgb(msg)
            depth = model.predict(rgb)[0]
            rec.write(TWINS[DEPTH_TOPIC], depth_msg(depth, stamp_ns, msg.header.frame_id))
            n += 1
    return n


def _ros_env() -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 100)))
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env


def refiner_command(params_file: Path, overrides: list[str], compressed: bool = False,
                    accounting: Path | None = None) -> list[str]:
    """The refiner as ``ros2 run sfm_ttr_ros refiner`` would start it, remapped to the bag
    (``compressed``: ``image_transport:=compressed``, it then reads ``<image>/compressed``;
    ``accounting``: the file it writes its final accounting to as it stops)."""
    from sfm_ttr_ros.ros.accounting import ACCOUNTING_ARG
    from sfm_ttr_ros.ros.kitti_bag import CAMERA_INFO_TOPIC, IMAGE_TOPIC

    cmd = [sys.executable, "-m", "sfm_ttr_ros.ros.node"]
    if accounting is not None:
        cmd += [ACCOUNTING_ARG, str(accounting)]
    cmd += ["--ros-args", "--params-file", str(params_file), "-r",
            f"{names.IMAGE_TOPIC}:={IMAGE_TOPIC}", "-r",
            f"{names.CAMERA_INFO_TOPIC}:={CAMERA_INFO_TOPIC}"]
    if compressed:
        cmd += ["-p", "image_transport:=compressed"]
    # the demo scores ~/depth_refined on every frame: unrefined ones must come back there too
    cmd += ["-p", "republish_unrefined:=true"]
    return cmd + node_arguments(overrides)  # the default QoS: every frame counts as it is


def node_arguments(items: list[str]) -> list[str]:
    """``--set NAME=VALUE`` items as the node's ``-p NAME:=VALUE`` arguments: checked and typed
    by the one schema, as ``sfm-ttr run`` and ``benchmark`` take them (:class:`InputError`
    before the node starts for an unknown name, a wrong type or a value out of range; only the
    node's own parameters); the scripts that start the node take ``--set`` through this too."""
    values = schema.parse_overrides(items)
    unknown = [n for n in values if n not in schema.SCHEMA]
    if unknown:
        raise InputError(f"--set {unknown[0]}: not a parameter of the refiner node")
    out: list[str] = []
    for name, value in values.items():
        out += ["-p", f"{name}:={schema.ros_literal(value)}"]
    return out


def _got(rec, topic: str) -> int:
    """Messages ``rec`` has of an output: on ``topic`` and on its relative twin."""
    counts = rec.counts
    return counts.get(topic, 0) + counts.get(TWINS[topic], 0)


def _wait_got(rec, topic: str, n: int, timeout: float) -> bool:
    """Wait until ``rec`` has ``n`` messages of an output (:func:`_got`); False on timeout."""
    deadline = time.monotonic() + timeout
    while _got(rec, topic) < n:
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.1)
    return True


def _run_refiner(opts: DemoOptions, bag: Path, out: Path, expected: int) -> dict:
    """Start the node, play the bag into it, record ``/refiner/depth/image`` (live) and
    ``/refiner/depth_refined/image`` (windows), each with its relative twin (depth not yet in
    metres), until every frame is back on both outputs."""
    from sfm_ttr_ros.ros.bag import IMAGE_MSGTYPE
    from sfm_ttr_ros.ros.kitti_bag import CAMERA_INFO_TOPIC
    from sfm_ttr_ros.ros.player import TopicRecorder, play_bag
    from sfm_ttr_ros.tools.benchmark import default_params_file

    params = Path(opts.params_file) if opts.params_file else default_params_file()
    if not params.is_file():
        raise InputError(f"params file not found: {params}")
    env = _ros_env()
    os.environ.update({k: env[k] for k in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID")})
    accounting_path = out / ACCOUNTING_FILE
    cmd = refiner_command(params, opts.overrides, opts.compressed, accounting_path)
    log_path = out / "refiner.log"
    _say(f"4/5 starting refiner ({params.name}; log {log_path}) and playing the bag into it")
    t0 = time.perf_counter()
    with open(log_path, "w") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
        try:
            wanted = {t: IMAGE_MSGTYPE for pair in TWINS.items() for t in pair}
            with TopicRecorder(out / "refined_bag", wanted, storage=opts.storage) as rec:
                # the recorder's subscriptions are VOLATILE: what the node publishes before they
                # match is never delivered: wait for the match before playing
                missing = rec.wait_for_publishers(list(wanted), timeout=NODE_START_TIMEOUT_S,
                                                  alive=lambda: proc.poll() is None)
                if proc.poll() is not None:
                    raise InputError(f"refiner exited with code {proc.returncode} at start-up; "
                                     f"see {log_path}")
                if REFINED_TOPIC in missing:
                    raise InputError(f"no publisher of {REFINED_TOPIC} within "
                                     f"{NODE_START_TIMEOUT_S:.0f} s of starting the refiner; "
                                     f"see {log_path}")
                if missing:
                    _say(f"   no publisher of {', '.join(missing)} (publish_live off?): the live "
                         "output is not recorded")
                played = play_bag(bag, rate=opts.rate,
                                  wait_topics=[bag_image_topic(opts.compressed),
                                               CAMERA_INFO_TOPIC],
                                  wait_timeout=120.0, progress=True)
                _say(f"   played {played.total} messages; waiting for the refined depth of "
                     f"{expected} frames")
                last, t_wait = -1, time.monotonic()
                while time.monotonic() - t_wait < opts.timeout_s:
                    if _wait_got(rec, REFINED_TOPIC, expected, timeout=10.0):
                        # live frames come first; one skipped under load (live_max_queue) is
                        # counted by the node, not waited for
                        _wait_got(rec, DEPTH_TOPIC, expected, timeout=LIVE_GRACE_S)
                        break
                    if proc.poll() is not None:
                        raise InputError(f"refiner exited with code {proc.returncode} "
                                         f"before publishing every frame; see {log_path}")
                    got = _got(rec, REFINED_TOPIC)
                    if got != last:
                        _say(f"   {got}/{expected} refined depth images received "
                             f"({_got(rec, DEPTH_TOPIC)} live)")
                        last = got
                received = _got(rec, REFINED_TOPIC)
                live_received = _got(rec, DEPTH_TOPIC)
        finally:
            interrupt(proc, timeout=20)
    seconds = time.perf_counter() - t0
    if received < expected:
        raise InputError(f"only {received} of {expected} depth images came back from refiner "
                         f"within {opts.timeout_s:.0f} s; see {log_path}")
    return {"received": received, "live_received": live_received, "seconds": seconds,
            "exit_code": proc.returncode, "command": " ".join(cmd),
            **_live_accounting(accounting_path)}


def _live_accounting(path: Path) -> dict:
    """The node's own count of its live output, from the accounting it wrote at ``path`` as it
    stopped (``live_published`` / ``live_skipped``; None where it has none: live off, or the
    node did not stop cleanly)."""
    from sfm_ttr_ros.ros.accounting import read_accounting

    values = read_accounting(path) or {}
    return {"live_published": values.get("live.published"),
            "live_skipped": values.get("live.skipped")}


def _live_line(node: dict, expected: int) -> str:
    """Where each of the ``expected`` live frames went: recorded, skipped by the node (its
    count), or published and not recorded (lost in transport)."""
    got, published, skipped = node["live_received"], node["live_published"], node["live_skipped"]
    text = f"{got}/{expected} live frames recorded"
    if published is None:
        return text + ("" if got == expected else "; the node's count is in refiner.log")
    if skipped:
        text += f"; the node skipped {skipped} under load ({ACCOUNTING_FILE})"
    if published > got:
        text += f"; {published - got} published by the node but not recorded (lost in transport)"
    return text


def run_demo(opts: DemoOptions) -> dict:
    """Run the whole demo; returns the results written to ``out/results.json``."""
    from sfm_ttr_ros.core.evaluation import EvalConfig

    t_start = time.perf_counter()
    out = _prepare_out(opts)
    drive, bag, gt_frames = _drive_to_bag(opts, out)
    expected = _predict_unrefined(opts, bag, out)
    opts = _with_camera_height(opts, out)
    node = _run_refiner(opts, bag, out, expected)
    _say("5/5 evaluating against the ground truth topic (matched by stamp)")
    cfg = EvalConfig(eigen_crop=opts.eigen_crop)
    evals = _evaluate_outputs(out, bag, cfg)
    shown = choose_frame(evals["no_ttr"]["per_frame"], evals["sfm_ttr"]["per_frame"])
    fig_path = shown and draw_figure(out, bag, drive, cfg, bag_image_topic(opts.compressed),
                                     _output_sources(out), shown)
    results = {
        "drive": drive, "frames": expected, "gt_frames": gt_frames,
        **_compare_outputs(evals),
        "metric": _metric_outputs(out, bag, EvalConfig(eigen_crop=opts.eigen_crop,
                                                       median_scaling=False)),
        "refiner": node,
        "seconds_total": time.perf_counter() - t_start,
        "figure": str(fig_path) if fig_path else None,
        "figure_frame": dataclasses.asdict(shown) if fig_path else None,
    }
    _write_reports(out, results, evals, _frame_indices(bag, opts.start))
    _print_summary(results, out)
    return results


def _with_camera_height(opts: DemoOptions, out: Path) -> DemoOptions:
    """``opts`` with the drive's camera height (its ``camera_height.txt``: a generated drive
    knows it) as ``metric.camera_height``, unless ``--set`` gives one: the depth in metres."""
    from sfm_ttr_ros.data.poses import CAMERA_HEIGHT_FILE, read_camera_height

    if "metric.camera_height" in schema.parse_overrides(opts.overrides):
        return opts
    found = sorted(out.glob(f"kitti_raw/*/*/{CAMERA_HEIGHT_FILE}"))
    if not found:
        return opts
    height = read_camera_height(found[0])
    _say(f"   the drive's camera height {height:.3f} m: metric.camera_height")
    return dataclasses.replace(opts, overrides=[*opts.overrides,
                                                f"metric.camera_height={height!r}"])


def _metric_outputs(out: Path, bag: Path, cfg) -> dict[str, dict]:
    """The refined outputs evaluated WITHOUT median scaling (metres): abs rel, RMSE and the
    frames' scale ratio (median GT / median prediction) and its spread."""
    from sfm_ttr_ros.ros.bag_evaluation import evaluate_bag
    from sfm_ttr_ros.ros.kitti_bag import DEPTH_GT_TOPIC

    sources = _output_sources(out)
    keep = ("abs_rel", "rmse", "ratio_median", "ratio_std", "frames",
            "pred_relative_frames")
    out_metrics = {}
    for key in ("sfm_ttr", "sfm_ttr_live"):
        e = evaluate_bag(sources[key][0], bag, sources[key][1], DEPTH_GT_TOPIC, cfg)
        out_metrics[key] = {k: e.get(k) for k in keep}
    return out_metrics


def _drive_to_bag(opts: DemoOptions, out: Path) -> tuple[str, Path, int]:
    """Steps 1-2: the drive, converted to ``out/drive_bag``; (drive, bag, GT frames)."""
    from sfm_ttr_ros.ros.kitti_bag import kitti_to_bag

    raw, gt_root, drive = _make_drive(opts, out)
    _say(f"2/5 converting {drive} to a rosbag2 ({opts.storage})")
    bag = out / "drive_bag"
    conv = kitti_to_bag(raw, drive, bag, gt_root, storage=opts.storage,
                        start=opts.start, max_frames=opts.max_frames,
                        compressed=opts.compressed)
    _say(f"   {conv.frames} images, {conv.gt_frames} with ground truth")
    if conv.gt_frames == 0:
        raise InputError(f"{drive} has no frame with ground truth: nothing to evaluate (a "
                         f"synthetic drive needs more than 2 x {opts.gt_skip_ends} frames)")
    return drive, bag, conv.gt_frames


def _predict_unrefined(opts: DemoOptions, bag: Path, out: Path) -> int:
    """Step 3: the parameter file's network, unrefined, over every image of ``bag`` into
    ``out/no_ttr_bag``; returns the number of images (the frames expected back)."""
    import torch

    from sfm_ttr_ros.core.models import build_model
    from sfm_ttr_ros.ros.bag import bag_topics
    from sfm_ttr_ros.tools.benchmark import (
        default_params_file,
        read_params_file,
        settings_from_params,
    )

    expected = bag_topics(bag)[bag_image_topic(opts.compressed)].count
    torch.set_num_threads(max(1, opts.threads))
    params = Path(opts.params_file) if opts.params_file else default_params_file()
    _, _, model_config = settings_from_params(read_params_file(params))
    _say(f"3/5 unrefined depth (model {model_config.type!r} of {params.name}, no refinement)")
    model = build_model(model_config)
    _predict_no_ttr(bag, out / "no_ttr_bag", model, opts.storage, opts.compressed)
    return expected


def _output_sources(out: Path) -> dict[str, tuple[Path, str]]:
    """Each scored output: its name -> (bag, topic)."""
    return {"no_ttr": (out / "no_ttr_bag", DEPTH_TOPIC),
            "sfm_ttr_live": (out / "refined_bag", DEPTH_TOPIC),
            "sfm_ttr": (out / "refined_bag", REFINED_TOPIC)}


def _evaluate_outputs(out: Path, bag: Path, cfg) -> dict[str, dict]:
    """Step 5: each output's :func:`evaluate_bag` against the drive bag's GT topic."""
    from sfm_ttr_ros.ros.bag_evaluation import evaluate_bag
    from sfm_ttr_ros.ros.kitti_bag import DEPTH_GT_TOPIC

    return {key: evaluate_bag(pred_bag, bag, topic, DEPTH_GT_TOPIC, cfg)
            for key, (pred_bag, topic) in _output_sources(out).items()}


def _compare_outputs(evals: dict[str, dict]) -> dict:
    """The outputs' metrics and their relative gains over no TTR: the windowed one on every
    frame, the live one on its own frames (a live frame the node skipped, or that was not
    recorded, is left out of both; ``metrics["no_ttr (live's frames)"]`` then) and by third
    of the drive (the live output starts on the start-up weights and improves as the windows'
    weights reach it)."""
    from sfm_ttr_ros.core.evaluation import mean_over_frames, relative_gain

    metrics = {k: {m: v for m, v in e.items() if not isinstance(v, list | dict)}
               for k, e in evals.items()}
    gain = relative_gain(metrics["no_ttr"], metrics["sfm_ttr"])
    base_on_live, _ = _paired_by_stamp(evals["no_ttr"]["per_frame"],
                                       evals["sfm_ttr_live"]["per_frame"])
    live_base = metrics["no_ttr"]
    if len(base_on_live) != len(evals["no_ttr"]["per_frame"]):
        live_base = metrics["no_ttr (live's frames)"] = mean_over_frames(base_on_live)
    live_gain = relative_gain(live_base, metrics["sfm_ttr_live"])
    live_by_third = _gain_by_part(evals["no_ttr"]["per_frame"],
                                  evals["sfm_ttr_live"]["per_frame"])
    return {"metrics": metrics, "relative_gain": gain, "relative_gain_live": live_gain,
            "relative_gain_live_by_third": live_by_third}


def _frame_indices(bag: Path, start: int) -> dict[str, int]:
    """Frame name (``sec.nanosec``) -> its index in the drive, from the bag's CameraInfo
    stamps (one per image, in stamp order from frame ``start``)."""
    from sfm_ttr_ros.ros.bag import read_bag, stamp_str
    from sfm_ttr_ros.ros.kitti_bag import CAMERA_INFO_TOPIC

    stamps = sorted({s for _, _, s, _ in read_bag(bag, [CAMERA_INFO_TOPIC])})
    return {stamp_str(s): start + k for k, s in enumerate(stamps)}


def _gain_lines(results: dict) -> tuple[str, str, str]:
    """The summary's gains: windowed, live, live by third of the drive."""
    def line(gain: dict) -> str:
        return ", ".join(f"{k} {v:+.1%}" for k, v in gain.items() if k in ("abs_rel", "rmse"))

    thirds = " -> ".join(f"{g['abs_rel']:+.1%} / {g['rmse']:+.1%}"
                         for g in results["relative_gain_live_by_third"])
    return line(results["relative_gain"]), line(results["relative_gain_live"]), thirds


def _results_markdown(results: dict) -> str:
    """``results.md``: the metric and gain tables as the benchmark writes them, the live
    output's gains by third of the drive and the figure."""
    from sfm_ttr_ros.tools.report_files import gain_table, metric_table

    thirds_line = _gain_lines(results)[2]
    lines = [f"# sfm-ttr demo: {results['drive']}", "",
             f"{results['frames']} frames, {results['gt_frames']} with ground truth.", "",
             metric_table(results["metrics"]),
             "sfm_ttr = /refiner/depth_refined (each frame once its window is done), "
             "sfm_ttr_live = /refiner/depth (every frame at once, served with the newest "
             "refined weights).", ""]
    lines += gain_table({"sfm_ttr": results["relative_gain"],
                         "sfm_ttr_live": results["relative_gain_live"]},
                        title="Relative gain against no_ttr (positive = better; sfm_ttr_live "
                              "on its own frames):")
    lines += [f"Relative change (positive = lower error than no TTR) of sfm_ttr_live by third "
              f"of the drive (abs rel / RMSE): {thirds_line}", ""]
    if results.get("figure"):
        lines += ["![qualitative results](figure.png)", "",
                  f"The figure's frame: {_figure_caption(results)}.", ""]
    return "\n".join(lines)


def _write_reports(out: Path, results: dict, evals: dict[str, dict],
                   indices: dict[str, int]) -> None:
    """``results.json``, ``results.md`` and ``per_frame.csv`` (abs rel and RMSE of every
    evaluated frame of each output, named by stamp), with the benchmark's writer."""
    from sfm_ttr_ros.tools.report_files import write_json, write_per_frame_csv

    write_json(out / "results.json", results)
    (out / "results.md").write_text(_results_markdown(results))
    per_frame = {k: {indices.get(r["name"], -1): r for r in e["per_frame"]}
                 for k, e in evals.items()}
    names = sorted({r["name"] for e in evals.values() for r in e["per_frame"]},
                   key=lambda n: tuple(int(x) for x in n.split(".")))
    frames = [(indices.get(n, -1), n) for n in names]
    write_per_frame_csv(out / "per_frame.csv", frames, per_frame, columns=("abs_rel", "rmse"))


def _figure_caption(results: dict) -> str:
    """Which frame the figure shows and why, in one line."""
    return "; ".join(line.strip().rstrip(":")
                     for line in FigureFrame(**results["figure_frame"]).caption())


def _print_summary(results: dict, out: Path) -> None:
    """The before/after table and the gains on stdout (README quotes these lines)."""
    from sfm_ttr_ros.core.evaluation import format_table

    node, expected = results["refiner"], results["frames"]
    gain_line, live_line, thirds_line = _gain_lines(results)
    print(format_table(results["metrics"]))
    print(f"SfM-TTR (windowed, ~/depth_refined) vs no TTR: {gain_line} (gain; positive = lower "
          "error)")
    print(f"SfM-TTR live (~/depth) vs no TTR on the same frames: {live_line} "
          f"({_live_line(node, expected)})")
    print(f"SfM-TTR live by third of the drive (abs rel / RMSE; the first on the start-up "
          f"weights until the first window's reach it): {thirds_line}")
    m = results["metric"]["sfm_ttr"]
    if m.get("ratio_median") is not None:
        print(f"in metres (no median scaling): windowed abs rel {m['abs_rel']:.4f}, RMSE "
              f"{m['rmse']:.3f} m, GT / depth {m['ratio_median']:.3f} (spread "
              f"{m['ratio_std']:.1%})")
    print(f"refiner: {node['received']} frames in {node['seconds']:.0f} s; "
          f"total {results['seconds_total']:.0f} s")
    if results["figure"]:
        print(f"figure: {results['figure']} ({_figure_caption(results)})")
    print(f"results: {out / 'results.md'}")


def _gain_by_part(base_rows: list[dict], live_rows: list[dict], parts: int = 3) -> list[dict]:
    """The live output's :func:`relative_gain` over no TTR in each of ``parts`` consecutive
    parts of the drive (frames in stamp order, named ``sec.nanosec``; both on the live
    output's frames)."""
    from sfm_ttr_ros.core.evaluation import means_by_part, relative_gain

    base, live = _paired_by_stamp(base_rows, live_rows)
    return [relative_gain(b, a) for b, a in zip(means_by_part(base, parts),
                                                means_by_part(live, parts), strict=True)]


def _paired_by_stamp(base_rows: list[dict], live_rows: list[dict]) -> tuple[list, list]:
    """(no TTR's rows, the live output's rows) on the live output's frames that no TTR has too
    (a live frame the node skipped, or that was not recorded, is left out of both), in stamp
    order (frames named ``sec.nanosec``)."""
    base = {r["name"]: r for r in base_rows}
    live = sorted((r for r in live_rows if r["name"] in base),
                  key=lambda r: tuple(int(x) for x in r["name"].split(".")))
    return [base[r["name"]] for r in live], live


def cmd_demo(args: argparse.Namespace) -> int:
    from sfm_ttr_ros.requirements import check_sfm_dependencies

    check_sfm_dependencies()  # before minutes of preparation for a node that could not refine
    opts = DemoOptions(out=Path(args.out), kitti_raw=args.kitti_raw, kitti_gt=args.kitti_gt,
                       drive=args.drive, images=args.images, intrinsics=args.intrinsics,
                       gt_depth=args.gt_depth, gt_scale=args.gt_scale, start=args.start,
                       frames=args.frames, width=args.width,
                       height=args.height, domain=args.domain, seed=args.seed,
                       max_frames=args.max_frames, params_file=args.params_file,
                       overrides=list(args.set or []), rate=args.rate,
                       timeout_s=args.timeout, threads=args.threads, storage=args.storage,
                       eigen_crop=args.eigen_crop, overwrite=args.overwrite,
                       compressed=args.compressed)
    run_demo(opts)
    return 0


def add_commands(sub) -> None:
    from sfm_ttr_ros.tools.cli_args import add_sequence_args

    d = sub.add_parser("demo", help="generate (or read) a KITTI drive or an image folder, replay "
                       "it through refiner and print the before/after table")
    d.add_argument("--out", default="sfm_ttr_demo", help="output folder (default sfm_ttr_demo)")
    d.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    add_sequence_args(d)  # none given: a synthetic drive
    d.add_argument("--frames", type=int, default=DemoOptions.frames,
                   help="synthetic drive length")
    d.add_argument("--width", type=int, default=1242)
    d.add_argument("--height", type=int, default=375)
    d.add_argument("--domain", default="B", help="synthetic domain (B = held out from training)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--params-file", help="refiner parameters (default params/kitti.yaml)")
    d.add_argument("--set", dest="set", action="append", default=[], metavar="NAME=VALUE",
                   help="a refiner parameter over the parameter file (repeatable), as in "
                        "sfm-ttr run / benchmark, e.g. --set refinement.steps=50")
    d.add_argument("--rate", type=float, default=DemoOptions.rate,
                   help="bag playback rate (1 = as recorded, 10 Hz for KITTI)")
    d.add_argument("--timeout", type=float, default=1800.0,
                   help="seconds to wait for the refined depth after playback")
    d.add_argument("--threads", type=int, default=2, help="torch threads for no-TTR prediction")
    d.add_argument("--storage", choices=["mcap", "sqlite3"], default="mcap")
    d.add_argument("--eigen-crop", action="store_true")
    d.add_argument("--compressed", action="store_true",
                   help="write the bag's images as JPEG CompressedImages and run the refiner "
                        "with image_transport:=compressed")
    d.set_defaults(func=cmd_demo)
