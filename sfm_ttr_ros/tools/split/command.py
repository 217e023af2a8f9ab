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
BENCHMARK_OPTIONS = ("modes", "rate", "node_rate", "offline_max_frames", "figure_frames",
                     "save_depth", "eigen_crop", "median_scaling", "max_depth", "min_depth",
                     "prediction")
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
    from sfm_ttr_ros.tools.cli_args import command_line
    from sfm_ttr_ros.tools.split.spec import read_split
    from sfm_ttr_ros.tools.split.task import SplitJob

    check_split_args(args)
    params_path, values, options = _task_values(args, kind)
    threads = size_threads(values, args, cluster=args.ray_address is not None)
    _absolute_model_files(values)
    config = _engine_config(args, values, threads)  # bad parameters fail here, before any task
    specs = read_split(args.split, args.kitti_raw, args.kitti_gt, args.eigen_context)
    job = SplitJob(kind, values, str(params_path or ""), options, threads, command_line())
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the output folder {out}: {exc}") from exc
    split = _SplitRun(out, specs, job, config, str(args.split), str(params_path or ""))
    if not args.overwrite:
        split.reuse_done()
    res, interrupted = split.run()
    _print_summary(res, out)
    if interrupted:
        return 130
    return 1 if res["counts"]["failed"] else 0


def _task_values(args: argparse.Namespace, kind: str) -> tuple[Any, dict[str, Any],
                                                               dict[str, Any]]:
    """(the parameter file, the parameter values, the command's own options) of a task."""
    from sfm_ttr_ros.tools.cli_args import parameter_values

    if kind == "benchmark":
        from sfm_ttr_ros.tools.one_sequence import benchmark_values, check_benchmark_options

        params_path, values = benchmark_values(args)
        check_benchmark_options(args)
        names = BENCHMARK_OPTIONS
    else:
        params_path, values = parameter_values(args)
        names = RUN_OPTIONS
    return params_path, values, {k: getattr(args, k) for k in names}


def _engine_config(args: argparse.Namespace, values: dict[str, Any], threads: int):
    """Workers, threads, GPUs (1 per task with a cuda device unless --gpus-per-worker),
    retries and the cluster address (something must answer there); the parameters are built
    (checked) on the way."""
    from sfm_ttr_ros.core.params import build
    from sfm_ttr_ros.tools.split.engine import EngineConfig, check_cluster_address

    settings = build(values)
    gpus = args.gpus_per_worker
    if gpus is None:
        gpus = 1.0 if str(settings.model.device).startswith("cuda") else 0.0
    check_cluster_address(args.ray_address)  # seconds, not Ray's minutes of retries
    return EngineConfig(workers=args.workers, threads=threads, gpus=gpus,
                        retries=args.retries, address=args.ray_address)


class _SplitRun:
    """One ``--split`` run: the sequences' records (reused or computed), and the results
    written again as each sequence ends."""

    def __init__(self, out: Path, specs: list, job, config, split_file: str,
                 params_file: str) -> None:
        from sfm_ttr_ros.tools.split import cache

        self.out, self.specs, self.job, self.config = out, specs, job, config
        self.split_file = split_file
        self.keys = {s.id: cache.sequence_key(s, job) for s in specs}
        self.records: dict[str, dict[str, Any]] = {}
        self.reused: set[str] = set()
        self.retried: dict[str, int] = {}
        self.engine_info: dict[str, Any] = {
            "workers": config.workers, "threads_per_worker": job.threads,
            "gpus_per_worker": config.gpus, "retries": config.retries,
            "address": config.address, "where": "", "seconds": 0.0}
        self.settings_info = {"params_file": params_file, "options": job.options,
                              "values": job.values, "code": cache.code_fingerprint()}
        self.progress = None

    def reuse_done(self) -> None:
        """Take the sequences already done with the same settings and code as they are."""
        from sfm_ttr_ros.tools.split import cache

        for s in self.specs:
            rec = cache.load_done(self.out, s, self.keys[s.id])
            if rec is not None:
                self.records[s.id] = rec
                self.reused.add(s.id)

    def run(self) -> tuple[dict[str, Any], bool]:
        """Compute the sequences not reused; (the results written last, interrupted)."""
        from sfm_ttr_ros.tools.split.engine import Interrupted, run_tasks
        from sfm_ttr_ros.tools.split.progress import SplitProgress

        todo = [s for s in self.specs if s.id not in self.reused]
        self.progress = SplitProgress(len(self.specs), len(self.reused), label=self.job.command)
        interrupted = False
        try:
            stats = run_tasks(todo, self.job, self.config, self.on_outcome) if todo else None
        except Interrupted as exc:
            stats, interrupted = exc.stats, True
        finally:
            self.progress.close()
        if stats is not None:
            self.retried.update({k: v for k, v in stats.retried.items()
                                 if v > self.retried.get(k, 0)})
            self.engine_info.update(where=stats.where, seconds=stats.seconds)
        else:
            self.engine_info.update(where="nothing to compute (every sequence reused)")
        return self.write(interrupted), interrupted

    def on_outcome(self, spec, outcome, attempts: int) -> None:
        from sfm_ttr_ros.tools.split import cache

        self.records[spec.id] = cache.store(self.out, spec, outcome, self.keys[spec.id],
                                            attempts)
        self.retried[spec.id] = attempts - 1
        self.progress.update(self.records[spec.id])
        self.write()

    def write(self, interrupted: bool = False) -> dict[str, Any]:
        from sfm_ttr_ros.tools.split import split_report

        res = split_report.build_results(
            self.specs, self.records, self.reused, _modes(self.job.command, self.job.options),
            split_file=self.split_file, command=self.job.command_line, kind=self.job.command,
            engine=self.engine_info, retried=self.retried, interrupted=interrupted,
            settings=self.settings_info)
        split_report.write_results(self.out, res)
        return res


def _modes(kind: str, options: dict[str, Any]) -> list[str]:
    if kind == "benchmark":
        return list(dict.fromkeys(options["modes"]))
    from sfm_ttr_ros.tools.one_sequence import METHODS

    return list(METHODS.values())


def _print_summary(res: dict[str, Any], out: Path) -> None:
    from sfm_ttr_ros.tools.split.split_report import results_markdown

    text = results_markdown(res)
    print(text.split("Per sequence")[0].rstrip())
    for q in res["sequences"]:
        if q["status"] == "failed":
            print(f"FAILED {q['id']}: {q['reason']}")
    print(f"\nresults in {out}/results.json, results.md, per_frame.csv")
