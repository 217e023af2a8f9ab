"""``--split FILE`` of ``sfm-ttr benchmark`` and ``sfm-ttr run``: the options
(:func:`add_split_args`) and the command (:func:`run_split_command`).

Threads: each task runs ``torch_num_threads`` threads (``--threads``) for torch and for SfM
(``sfm.num_threads``, unless ``--set sfm.num_threads=`` says otherwise), and declares as many
CPUs to Ray. Without ``--threads`` a local run sizes them to the machine (``cores // workers``,
at least 1) and a cluster run uses 1 per task (the cluster's CPUs then decide how many tasks run
at once).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any

from sfm_ttr_ros.core.errors import InputError

DEFAULT_RETRIES = 2
DEFAULT_EIGEN_CONTEXT = 10
#: What a task of each command takes from the command line besides the parameters.
BENCHMARK_OPTIONS = ("modes", "rate", "offline_max_frames", "figure_frames", "save_depth",
                     "eigen_crop", "median_scaling", "max_depth", "min_depth", "prediction")
RUN_OPTIONS = ("eigen_crop",)
#: Single-sequence options that --split replaces.
SINGLE_SEQUENCE = ("drive", "images", "intrinsics", "gt_depth")


def add_split_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group(
        "many sequences (a split file; docs/cluster.md)",
        "--split FILE runs every sequence of FILE (KITTI drives, image folders with K, rosbag2 "
        "bags, or the KITTI Eigen split's lines), one task per sequence, and writes one row "
        "per sequence and the metrics pooled over all their frames to OUT/results.json and "
        "results.md, every sequence's own results to OUT/sequences/<id>/. A sequence already "
        "done with the same settings and code is not computed again.")
    g.add_argument("--split", metavar="FILE",
                   help="the split file (one sequence per line; --kitti-raw / --kitti-gt are "
                        "the roots of its KITTI lines)")
    g.add_argument("--workers", type=int, default=1,
                   help="tasks at once on a local Ray instance started for this command "
                        "(default 1: one after the other in this process, no Ray needed)")
    g.add_argument("--ray-address", metavar="ADDRESS", default=None,
                   help="run the tasks on this running Ray cluster (e.g. HEAD_IP:6379) "
                        "instead; the data paths must be readable on every node")
    g.add_argument("--retries", type=int, default=DEFAULT_RETRIES,
                   help="times a task is submitted again when its worker dies (default "
                        f"{DEFAULT_RETRIES}); a sequence failing on its data is not retried")
    g.add_argument("--gpus-per-worker", type=float, default=None,
                   help="GPUs a task declares (default: 1 with a cuda device, else 0)")
    g.add_argument("--eigen-context", type=int, default=DEFAULT_EIGEN_CONTEXT,
                   help="Eigen-split drives run from this many frames before their first "
                        "listed frame to as many after their last (default "
                        f"{DEFAULT_EIGEN_CONTEXT})")
    g.add_argument("--overwrite", action="store_true",
                   help="compute every sequence again, even those already done")


def _explicit_sets(args: argparse.Namespace) -> set[str]:
    from sfm_ttr_ros.core import params as schema

    return set(schema.parse_overrides(args.set or []))


def size_threads(values: dict[str, Any], args: argparse.Namespace, cluster: bool) -> int:
    """Threads per task (module docstring), written into ``values``."""
    threads = int(values.get("torch_num_threads") or 0)
    if threads <= 0:
        threads = 1 if cluster else max(1, (os.cpu_count() or 1) // max(1, args.workers))
    values["torch_num_threads"] = threads
    if "sfm.num_threads" not in _explicit_sets(args):
        values["sfm.num_threads"] = threads
    if int(values.get("worker_threads", 1) or 0) > threads:
        values["worker_threads"] = threads
    return threads


def _absolute_model_files(values: dict[str, Any]) -> None:
    from sfm_ttr_ros.tools.split.cache import FILE_PARAMS

    for key in FILE_PARAMS:
        v = values.get(key)
        if v and not Path(v).is_absolute() and Path(v).exists():
            values[key] = str(Path(v).resolve())


def check_split_args(args: argparse.Namespace) -> None:
    given = [f"--{k.replace('_', '-')}" for k in SINGLE_SEQUENCE if getattr(args, k, None)]
    if given:
        raise InputError(f"--split lists the sequences: {', '.join(given)} cannot go with it")
    if args.start or args.max_frames:
        raise InputError("--start / --max-frames do not apply to --split: give start=N "
                         "frames=N on a line of the split file")
    if args.workers < 1 or args.retries < 0 or args.eigen_context < 0:
        raise InputError("--workers must be >= 1, --retries and --eigen-context >= 0")
    if args.gpus_per_worker is not None and args.gpus_per_worker < 0:
        raise InputError("--gpus-per-worker must be >= 0")


def run_split_command(args: argparse.Namespace, kind: str) -> int:
    """``sfm-ttr benchmark|run --split FILE``: 0 when every sequence is done, 1 when one
    failed, 130 when interrupted (the results so far written either way)."""
    from sfm_ttr_ros.core.params import build
    from sfm_ttr_ros.tools.cli_args import command_line, parameter_values
    from sfm_ttr_ros.tools.split import cache, report
    from sfm_ttr_ros.tools.split.engine import EngineConfig, Interrupted, run_tasks
    from sfm_ttr_ros.tools.split.progress import SplitProgress
    from sfm_ttr_ros.tools.split.spec import read_split
    from sfm_ttr_ros.tools.split.task import SplitJob

    check_split_args(args)
    if kind == "benchmark":
        from sfm_ttr_ros.tools.one_sequence import benchmark_values, check_benchmark_options

        params_path, values = benchmark_values(args)
        check_benchmark_options(args)
        names = BENCHMARK_OPTIONS
    else:
        params_path, values = parameter_values(args)
        names = RUN_OPTIONS
    threads = size_threads(values, args, cluster=args.ray_address is not None)
    _absolute_model_files(values)
    settings = build(values)  # bad parameters fail here, before any task
    gpus = args.gpus_per_worker
    if gpus is None:
        gpus = 1.0 if str(settings.model.device).startswith("cuda") else 0.0
    config = EngineConfig(workers=args.workers, threads=threads, gpus=gpus,
                          retries=args.retries, address=args.ray_address)
    specs = read_split(args.split, args.kitti_raw, args.kitti_gt, args.eigen_context)
    options = {k: getattr(args, k) for k in names}
    job = SplitJob(kind, values, str(params_path or ""), options, threads, command_line())
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the output folder {out}: {exc}") from exc

    keys = {s.id: cache.sequence_key(s, job) for s in specs}
    records: dict[str, dict[str, Any]] = {}
    reused: set[str] = set()
    if not args.overwrite:
        for s in specs:
            rec = cache.load_done(out, s, keys[s.id])
            if rec is not None:
                records[s.id] = rec
                reused.add(s.id)
    todo = [s for s in specs if s.id not in reused]
    engine_info: dict[str, Any] = {"workers": args.workers, "threads_per_worker": threads,
                                   "gpus_per_worker": gpus, "retries": args.retries,
                                   "address": args.ray_address, "where": "", "seconds": 0.0}
    settings_info = {"params_file": str(params_path or ""), "options": options,
                     "values": values, "code": cache.code_fingerprint()}
    retried: dict[str, int] = {}

    def write(interrupted: bool = False) -> dict[str, Any]:
        res = report.build_results(
            specs, records, reused, _modes(kind, options), split_file=str(args.split),
            command=job.command_line, kind=kind, engine=engine_info, retried=retried,
            interrupted=interrupted, settings=settings_info)
        report.write_results(out, res)
        return res

    progress = SplitProgress(len(specs), len(reused), label=kind)

    def on_outcome(spec, outcome, attempts: int) -> None:
        records[spec.id] = cache.store(out, spec, outcome, keys[spec.id], attempts)
        retried[spec.id] = attempts - 1
        progress.update(records[spec.id])
        write()

    interrupted = False
    try:
        stats = run_tasks(todo, job, config, on_outcome) if todo else None
    except Interrupted as exc:
        stats, interrupted = exc.stats, True
    finally:
        progress.close()
    if stats is not None:
        retried.update({k: v for k, v in stats.retried.items() if v > retried.get(k, 0)})
        engine_info.update(where=stats.where, seconds=stats.seconds)
    else:
        engine_info.update(where="nothing to compute (every sequence reused)")
    res = write(interrupted)
    _print_summary(res, out)
    if interrupted:
        return 130
    return 1 if res["counts"]["failed"] else 0


def _modes(kind: str, options: dict[str, Any]) -> list[str]:
    if kind == "benchmark":
        return list(dict.fromkeys(options["modes"]))
    from sfm_ttr_ros.tools.one_sequence import METHODS

    return list(METHODS.values())


def _print_summary(res: dict[str, Any], out: Path) -> None:
    from sfm_ttr_ros.tools.split.report import results_markdown

    text = results_markdown(res)
    print(text.split("Per sequence")[0].rstrip())
    for q in res["sequences"]:
        if q["status"] == "failed":
            print(f"FAILED {q['id']}: {q['reason']}")
    print(f"\nresults in {out}/results.json, results.md, per_frame.csv")
