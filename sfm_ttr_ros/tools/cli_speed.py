"""``sfm-ttr speed``: the speed and memory measurement of the benchmark
(:mod:`sfm_ttr_ros.tools.benchmark.speed`) on a generated drive, a naive run against the tuned
settings. Its parameters are those of ``sfm-ttr benchmark`` (the node's parameter file, the
flags, ``--set``: :mod:`sfm_ttr_ros.tools.cli_args`) for the tuned run; ``--naive-set`` for the
naive one."""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import tempfile
from pathlib import Path

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.tools.cli_args import add_parameter_args, command_line, parameter_values

DEFAULT_CACHE = Path(tempfile.gettempdir()) / "sfm_ttr_speed_cache"


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected WxH, got {text!r}") from exc
    return w, h


def add_speed_parser(sub) -> argparse.ArgumentParser:
    s = sub.add_parser(
        "speed", help="the node's code path timed on a generated drive: naive vs tuned",
        description="Time the node's code path frame by frame (decode, WindowRunner, message "
                    "conversion) on a generated KITTI-size drive, a naive run against the tuned "
                    "settings, with stage shares, latency and accuracy; --memory-frames: peak "
                    "RSS over a long stream. Writes OUT/speed.json and speed.md.")
    add_parameter_args(s, ("model", "method", "windows"),
                       "params/kitti.yaml, installed or from the repository")
    g = s.add_argument_group("speed")
    g.add_argument("--out", required=True, help="output folder (speed.json, speed.md)")
    g.add_argument("--domain", default="B", choices=("A", "B"), help="the drive's domain")
    g.add_argument("--drive-seed", type=int, default=3, help="the drive's scene")
    g.add_argument("--frames", type=int, default=60)
    g.add_argument("--size", type=_size, default=(1242, 375), metavar="WxH")
    g.add_argument("--cache-dir", default=str(DEFAULT_CACHE),
                   help="rendered drives are cached here ('' = no cache)")
    g.add_argument("--configs", default="naive,tuned", help="comma-separated, run in this order")
    g.add_argument("--naive-set", action="append", default=[], metavar="NAME=VALUE",
                   help="a parameter of the naive configuration (smoke runs; repeatable)")
    g.add_argument("--no-baseline", action="store_true", help="skip the no_ttr accuracy row")
    g.add_argument("--memory-frames", type=int, default=0,
                   help="also measure memory over a stream of N frames (fresh process)")
    g.add_argument("--memory-size", type=_size, default=(320, 96), metavar="WxH")
    g.add_argument("--memory-after", type=int, default=100)
    g.add_argument("--memory-only", action="store_true", help="skip the speed comparison")
    g.add_argument("--quiet", action="store_true")
    s.set_defaults(func=cmd_speed)
    return s


def speed_configs(args: argparse.Namespace, image_size: tuple[int, int], names=None):
    """The configurations of ``--configs`` (or ``names``) from the parameters of ``args``."""
    from sfm_ttr_ros.tools.benchmark import default_params_file
    from sfm_ttr_ros.tools.benchmark.speed import build_configs

    default = None if args.params_file else default_params_file()
    _, base = parameter_values(args, default, overrides=[])
    if names is None:
        names = [c.strip() for c in args.configs.split(",") if c.strip()]
    return build_configs(base, args.set, args.naive_set, image_size, names)


def _say(line: str) -> None:
    print(f"sfm-ttr speed: {line}", file=sys.stderr, flush=True)


def cmd_speed(args: argparse.Namespace) -> int:
    from sfm_ttr_ros.core.models.registry import resolve_device
    from sfm_ttr_ros.tools.benchmark import speed
    from sfm_ttr_ros.tools.benchmark.drive import load_drive
    from sfm_ttr_ros.tools.benchmark.speed_report import machine_info, speed_table, write_speed

    progress = None if args.quiet else _say
    load = os.getloadavg()[0]
    if progress and load > 0.5 * (os.cpu_count() or 1):
        progress(f"WARNING: load average {load:.1f} on {os.cpu_count()} CPUs: timings are not "
                 "meaningful")
    configs = speed_configs(args, args.size)
    results = {"command": command_line(),
               "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
               "latency_definition": speed.LATENCY_DEFINITION,
               "machine": machine_info(str(resolve_device(configs[0].model.device))
                                       if configs else "cpu")}
    if args.memory_frames > 0:  # first, while this process is still small
        (tuned,) = speed_configs(args, args.memory_size, ("tuned",))
        w, h = args.memory_size
        results["memory"] = speed.memory_in_child(tuned, {
            "frames": args.memory_frames, "width": w, "height": h, "domain": args.domain,
            "seed": args.drive_seed, "after": args.memory_after}, progress)
    if not args.memory_only and configs:
        if args.frames < 2:
            raise InputError(f"--frames must be >= 2, got {args.frames}")
        drive = load_drive(args.domain, args.drive_seed, args.frames, *args.size,
                           args.cache_dir or None, progress)
        results["drive"] = drive.info
        results.update(speed.run_speed(drive, configs, not args.no_baseline, progress))
    path = write_speed(results, args.out)
    print(speed_table(results))
    print(f"\nresults: {path} and {path.with_suffix('.md')}")
    return 0
