"""What ``sfm-ttr benchmark`` and ``sfm-ttr run`` do for one sequence, used by the commands for
one sequence and by every task of ``--split`` (:mod:`sfm_ttr_ros.tools.split`):

* :func:`benchmark_sequence`: the benchmark's modes over the sequence
  (:func:`~sfm_ttr_ros.tools.benchmark.run_benchmark`) with the settings' network, and the
  option helpers of the benchmark command (:func:`benchmark_values`, :func:`eval_config`,
  :func:`check_benchmark_options`);
* :func:`run_whole_sequence`: offline SfM-TTR over the whole sequence in one window (the paper's
  setting), every depth before and after written, the frames with ground truth evaluated.
"""

from __future__ import annotations

import argparse
import copy
import json
import time
from pathlib import Path

import numpy as np

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.tools.cli_args import build_model_for, parameter_values

#: Names of the two predictions in ``summary.json``'s ``metrics`` and their labels as methods.
METHODS = {"before": "no_ttr", "after": "sfm_ttr"}


def eval_config(args: argparse.Namespace, model=None):
    """The evaluation options of the flags; ``--prediction auto`` follows ``model``'s output
    (relative inverse depth for affine-invariant networks, else depth)."""
    from sfm_ttr_ros.core.alignment.affine import is_affine_output
    from sfm_ttr_ros.core.evaluation import EvalConfig

    kind = args.prediction
    if kind == "auto":
        affine = model is not None and is_affine_output(model)
        kind = "relative_inverse_depth" if affine else "depth"
    return EvalConfig(min_depth=args.min_depth, max_depth=args.max_depth,
                      eigen_crop=args.eigen_crop, median_scaling=args.median_scaling,
                      prediction=kind)


def benchmark_values(args: argparse.Namespace) -> tuple[Path, dict]:
    """(parameter file, parameter values): the file's, then the flags, then ``--set``."""
    from sfm_ttr_ros.tools.benchmark import default_params_file

    path, values = parameter_values(args, None if args.params_file else default_params_file())
    return path, values


def check_benchmark_options(args: argparse.Namespace) -> None:
    if args.offline_max_frames < 0 or args.figure_frames < 0:
        raise InputError("--offline-max-frames and --figure-frames must be >= 0")


def benchmark_sequence(seq, settings, args: argparse.Namespace, out, *, start: int,
                       max_frames: int, params_path, command: str,
                       quiet: bool = False) -> dict:
    """:func:`~sfm_ttr_ros.tools.benchmark.run_benchmark` of ``seq`` with the network and
    settings of ``settings`` and the benchmark options of ``args`` (modes, rate, offline chunks,
    figure frames, depth files, evaluation): what ``sfm-ttr benchmark`` does for one sequence,
    also each task of ``--split`` (``quiet``: no progress lines)."""
    import torch

    from sfm_ttr_ros.tools.benchmark import BenchmarkOptions, run_benchmark

    base = build_model_for(settings)

    def factory():
        return copy.deepcopy(base)  # the original weights, untouched by earlier modes

    model_config = settings.model
    description = {"type": model_config.type, "encoder_path": model_config.encoder_path,
                   "decoder_path": model_config.decoder_path, "device": model_config.device,
                   "load_weights_path": settings.node.load_weights_path}
    options = BenchmarkOptions(
        start=start, max_frames=max_frames,
        offline_max_frames=args.offline_max_frames, figure_frames=args.figure_frames,
        save_depth=args.save_depth, model_description=description, rate=args.rate,
        node_rate=args.node_rate,
        settings_info={"params_file": str(params_path),
                       "torch_threads": torch.get_num_threads()},
        command=command, **({"progress": None} if quiet else {}))
    return run_benchmark(seq, factory, settings.ttr, settings.stream, out, args.modes,
                         eval_config(args, base), options)


def _plain(summary: dict) -> dict:
    return {k: v for k, v in summary.items() if k not in ("per_frame",)}


def run_whole_sequence(seq, settings, out: str | Path, *, start: int = 0, max_frames: int = 0,
                       eigen_crop: bool = False) -> dict:
    """One window over frames ``start .. start + max_frames`` (0 = to the end) of ``seq``:
    ``out/before`` and ``out/after`` (every depth as .npy and a colour PNG), ``points.ply``,
    ``summary.json`` (returned) and, when frames have ground truth, ``per_frame.csv``."""
    from sfm_ttr_ros.core.evaluation import EvalConfig, Evaluator
    from sfm_ttr_ros.core.pipeline import SfmTTR
    from sfm_ttr_ros.core.visualize import colorize_depth, write_ply

    if not 0 <= start < len(seq):
        raise InputError(f"--start {start} is outside the sequence's {len(seq)} frames "
                         f"(0 .. {len(seq) - 1})")
    stop = len(seq) if max_frames <= 0 else min(len(seq), start + max_frames)
    frames = seq.frames(start, stop)
    out = Path(out)
    try:
        for sub in METHODS:
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

    evals = {k: Evaluator(EvalConfig(eigen_crop=eigen_crop)) for k in METHODS}
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
        "frames_total": len(frames),
        "first_frame": start,
        **res.summary(),
        "alignment": res.alignment.stats if res.alignment else {},
        "loss_history": res.refinement.loss_history if res.refinement else [],
        "cloud_frame": res.cloud_frame,
        "timings": res.timings,
        "seconds": seconds,
        "seconds_per_frame": seconds / max(1, len(frames)),
    }
    if evals["before"].summary()["frames"]:
        full = {k: e.summary() for k, e in evals.items()}
        summary["metrics"] = {k: _plain(v) for k, v in full.items()}
        write_per_frame(out / "per_frame.csv", frames, full, res.refined)
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=float))
    return summary


def write_per_frame(path: Path, frames, full: dict, refined: bool) -> None:
    """abs rel and RMSE of every evaluated frame before and after, methods ``no_ttr`` and
    ``sfm_ttr`` (:func:`~sfm_ttr_ros.tools.report_files.write_per_frame_csv`, the benchmark's
    per_frame.csv)."""
    from sfm_ttr_ros.tools.report_files import write_per_frame_csv

    index_of = {f.name: f.index for f in frames}
    rows = {METHODS[key]: {index_of[r["name"]]: {**r, "refined": bool(refined) and key == "after"}
                           for r in v["per_frame"]} for key, v in full.items()}
    evaluated = [(index_of[r["name"]], r["name"]) for r in full["before"]["per_frame"]]
    write_per_frame_csv(path, evaluated, rows, columns=("abs_rel", "rmse", "refined"))
