"""``run_benchmark``: the modes over a sequence, then the reports and the figure."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.evaluation import EvalConfig, relative_gain
from sfm_ttr_ros.core.pipeline import TTRConfig
from sfm_ttr_ros.core.stream.window_runner import StreamSettings
from sfm_ttr_ros.data.sequence import ImageSequence
from sfm_ttr_ros.tools.benchmark.bands import ERROR_FIGURE, error_by_depth_figure
from sfm_ttr_ros.tools.benchmark.benchmark_report import (
    config_dict,
    describe_model,
    results_markdown,
    write_per_frame,
)
from sfm_ttr_ros.tools.benchmark.figure import pick_figure_frames, qualitative_figure
from sfm_ttr_ros.tools.benchmark.live import run_live
from sfm_ttr_ros.tools.benchmark.runners import (
    DEFAULT_MODES,
    MODES,
    NODE_MODE,
    ModeRun,
    log,
    mode_config,
    mode_stream,
    run_no_ttr,
    run_offline,
    run_online,
)
from sfm_ttr_ros.tools.benchmark.settings import (
    default_params_file,
    read_params_file,
    settings_from_params,
)
from sfm_ttr_ros.tools.benchmark.timeline import TIMELINE_FIGURE, window_timeline_figure
from sfm_ttr_ros.tools.report_files import write_json


def _stderr(line: str) -> None:
    print(f"sfm-ttr benchmark: {line}", file=sys.stderr, flush=True)


@dataclass
class BenchmarkOptions:
    """What :func:`run_benchmark` does besides running the modes over the sequence.

    ``start`` / ``max_frames``: frames ``start .. start+max_frames`` (0 = to the end).
    ``offline_max_frames`` > 0 splits the offline modes into chunks of that many frames.
    ``figure_frames``: GT frames drawn in ``figure.png``. ``save_depth`` also writes every depth
    as ``out_dir/depth/<mode>/<frame>.npy`` (network units, for ``sfm-ttr evaluate --pred``).
    ``rate``: the input rate (Hz) of the real-time ``sfm_ttr_live`` mode. ``node_rate`` > 0:
    ``node_online`` fed at that rate in virtual time (the keyframe rule's stale frames
    skipped as in the node on this machine); 0: each frame waits for the one before (the
    windows' accuracy at any speed; under ``newest`` nothing is stale). ``model_description``
    / ``settings_info`` / ``command``: recorded in ``results.json`` (``command`` defaults to
    this process's command line). ``progress`` gets one line per step (None: quiet).
    """

    start: int = 0
    max_frames: int = 0
    offline_max_frames: int = 0
    figure_frames: int = 2
    save_depth: bool = False
    rate: float = 10.0
    node_rate: float = 0.0
    model_description: Mapping[str, Any] | None = None
    settings_info: Mapping[str, Any] | None = None
    command: str | None = None
    progress: Callable[[str], None] | None = _stderr


@dataclass
class _Benchmark:
    """One benchmark's checked inputs: what each of its steps reads."""

    seq: ImageSequence
    modes: list[str]
    ttr: TTRConfig
    stream: StreamSettings
    eval: EvalConfig
    indices: list[int]  # the frames run
    gt_indices: list[int]  # those with ground truth
    figure_indices: list[int]
    out: Path
    options: BenchmarkOptions

    def say(self, line: str) -> None:
        if self.options.progress:
            self.options.progress(line)


def run_benchmark(
    seq: ImageSequence,
    model_factory: Callable[[], Any],
    ttr_config: TTRConfig | None = None,
    stream_settings: StreamSettings | None = None,
    out_dir: str | Path = "benchmark",
    modes: Sequence[str] = DEFAULT_MODES,
    eval_config: EvalConfig | None = None,
    options: BenchmarkOptions | None = None,
) -> dict[str, Any]:
    """Run ``modes`` over the frames of ``seq`` that ``options`` selects and write
    ``results.json``, ``results.md``, ``per_frame.csv`` and the figures to ``out_dir``; returns
    the ``results.json`` content.

    ``model_factory()`` must return a new network with the original weights at every call (one
    per mode). ``ttr_config`` / ``stream_settings`` default to the node's ``params/kitti.yaml``.
    """
    bench = _prepare(seq, ttr_config, stream_settings, out_dir, modes, eval_config,
                     options or BenchmarkOptions())
    runs, description = _run_modes(bench, model_factory)
    results = write_json(bench.out / "results.json", _results(bench, runs, description))
    _write_reports(bench, results, runs)
    return results


def _prepare(seq: ImageSequence, ttr_config: TTRConfig | None,
             stream_settings: StreamSettings | None, out_dir: str | Path,
             modes: Sequence[str], eval_config: EvalConfig | None,
             options: BenchmarkOptions) -> _Benchmark:
    """The checked modes, the settings (the node's parameter file where not given), the
    frames and the output folder."""
    modes = list(dict.fromkeys(modes))
    bad = [m for m in modes if m not in MODES]
    if not modes or bad:
        raise InputError(f"unknown mode(s) {bad}; choose from {', '.join(MODES)}")
    start, max_frames = options.start, options.max_frames
    if start < 0 or max_frames < 0 or options.offline_max_frames < 0:
        raise InputError("start, max_frames and offline_max_frames must be >= 0")
    if ttr_config is None or stream_settings is None:
        cfg_p, settings_p, _ = settings_from_params(read_params_file(default_params_file()))
        ttr_config = ttr_config or cfg_p
        stream_settings = stream_settings or settings_p
    n_all = len(seq)
    if start >= n_all:
        raise InputError(f"--start {start} is past the end of the sequence ({n_all} frames)")
    stop = n_all if max_frames <= 0 else min(n_all, start + max_frames)
    indices = list(range(start, stop))
    gt_indices = [i for i in indices if seq.names[i] in seq.gt_paths]
    if not gt_indices:
        raise InputError(f"none of the {len(indices)} frames {start}-{stop - 1} of {seq.name} has "
                         "ground truth: nothing to evaluate (check --kitti-gt / --gt-depth)")
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the output folder {out}: {exc}") from exc
    bench = _Benchmark(seq, modes, ttr_config, stream_settings, eval_config or EvalConfig(),
                       indices, gt_indices, pick_figure_frames(gt_indices, options.figure_frames),
                       out, options)
    bench.say(f"{seq.name}: {len(indices)} frames ({start}-{stop - 1}), {len(gt_indices)} "
              f"with ground truth; modes {', '.join(modes)}; output {out}")
    return bench


def _run_modes(bench: _Benchmark, model_factory: Callable[[], Any]
               ) -> tuple[dict[str, ModeRun], dict[str, Any]]:
    """Each mode on a fresh network; (the runs, the network's description)."""
    runs: dict[str, ModeRun] = {}
    description = dict(bench.options.model_description or {})
    for mode in bench.modes:
        model = model_factory()
        if "class" not in description:
            description.update(describe_model(model))
        bench.say(f"{mode}: start")
        t0 = time.perf_counter()
        runs[mode] = _run_mode(bench, mode, model)
        del model
        _log_mode(bench, runs[mode], time.perf_counter() - t0)
    return runs, description


def _run_mode(bench: _Benchmark, mode: str, model) -> ModeRun:
    """One mode over the frames: its runner, on the mode's settings."""
    opts, seq, indices, progress = bench.options, bench.seq, bench.indices, bench.options.progress
    run = ModeRun(mode, seq, indices, bench.figure_indices, bench.eval,
                  bench.out / "depth" / mode if opts.save_depth else None)
    if mode == "no_ttr":
        run_no_ttr(run, seq, indices, model, bench.ttr, progress)
    elif mode.endswith("_online"):  # sfm_ttr / ph_ttr / hybrid: the mode's loss
        virtual = mode == NODE_MODE and opts.node_rate > 0
        run_online(run, seq, indices, model, mode_config(mode, bench.ttr),
                   mode_stream(mode, bench.stream), progress,
                   opts.node_rate if virtual else None)
    elif mode == "sfm_ttr_live":
        run_live(run, seq, indices, model, bench.ttr, bench.stream, progress, opts.rate)
    else:
        run_offline(run, seq, indices, model, mode_config(mode, bench.ttr),
                    opts.offline_max_frames, progress)
    return run


def _log_mode(bench: _Benchmark, run: ModeRun, seconds: float) -> None:
    """Frames lost or skipped (logged), and the mode's headline numbers (progress)."""
    n = len(bench.indices)
    s = run.summary(n)
    if s["lost_frames"]:
        log.error("%s: %d frame(s) never came out", run.mode, s["lost_frames"])
    if s["not_published"]:
        log.warning("%s: %d frame(s) skipped and counted: %s", run.mode,
                    sum(s["not_published"].values()), s["not_published"])
    bench.say(f"{run.mode}: done in {seconds:.1f} s ({s['seconds_per_frame']:.2f} s/frame), "
              f"abs rel {s['abs_rel']:.4f}, RMSE {s['rmse']:.3f}, {s['refined_frames']}/{n} "
              f"refined, {s['frames']} evaluated")


def _results(bench: _Benchmark, runs: dict[str, ModeRun],
             description: dict[str, Any]) -> dict[str, Any]:
    """The content of ``results.json``."""
    n = len(bench.indices)
    results: dict[str, Any] = {
        "sequence": bench.seq.name,
        "frames_total": n,
        "frames_with_gt": len(bench.gt_indices),
        "first_frame": bench.options.start,
        "modes": bench.modes,
    }
    for mode, run in runs.items():
        results[mode] = run.summary(n)
    if "no_ttr" in runs:
        results["relative_gain"] = {m: relative_gain(results["no_ttr"], results[m])
                                    for m in bench.modes if m != "no_ttr"}
    opts = bench.options
    results["settings"] = {
        "eval": config_dict(bench.eval),
        "ttr": config_dict(bench.ttr),
        "stream": config_dict(bench.stream),
        "offline_max_frames": opts.offline_max_frames,
        **dict(opts.settings_info or {}),
    }
    results["model"] = description
    results["command"] = opts.command if opts.command is not None else " ".join(sys.argv)
    results["figure_frames"] = [bench.seq.names[i] for i in bench.figure_indices]
    return results


def _write_reports(bench: _Benchmark, results: dict[str, Any],
                   runs: dict[str, ModeRun]) -> None:
    """``results.md``, ``per_frame.csv`` and the figures (``results.json`` is written)."""
    out = bench.out
    (out / "results.md").write_text(results_markdown(results))
    write_per_frame(out / "per_frame.csv", bench.seq, bench.gt_indices, runs)
    curves = {m: results[m]["error_by_depth"] for m in bench.modes if m in results}
    _write_image(out / ERROR_FIGURE, error_by_depth_figure(
        curves, title=f"{bench.seq.name}: abs rel by GT depth (pixels of all GT frames)"))
    logs = {m: results[m]["window_log"] for m in bench.modes if results[m].get("window_log")}
    if logs:
        _write_image(out / TIMELINE_FIGURE, _timeline_figure(bench, runs, logs))
    figure = _qualitative_figure(bench, runs)
    if figure is not None:
        _write_image(out / "figure.png", figure)
    bench.say(f"results in {out}/results.json, results.md, per_frame.csv, figure.png, "
              f"{ERROR_FIGURE}")


def _write_image(path: Path, image: np.ndarray) -> None:
    if not cv2.imwrite(str(path), image):
        raise InputError(f"cannot write {path}")


def _timeline_figure(bench: _Benchmark, runs: dict[str, ModeRun],
                     logs: dict[str, list]) -> np.ndarray:
    """The windowed modes' abs rel per frame and their windows' outcomes."""
    abs_rel = {m: {i: row.get("abs_rel") for i, row in r.per_frame.items()}
               for m, r in runs.items()}
    indices = bench.indices
    return window_timeline_figure(
        abs_rel, logs, indices[0], indices[-1], labels=segment_labels(bench.seq, indices),
        title=f"{bench.seq.name}: abs rel per frame; windows refined (green), refused by a "
              "check (red), else unrefined (grey)")


def _qualitative_figure(bench: _Benchmark, runs: dict[str, ModeRun]) -> np.ndarray | None:
    """One block per figure frame that has GT and a depth of some mode, stacked; None when
    there is none."""
    seq, blocks = bench.seq, []
    for i in bench.figure_indices:
        gt = seq.gt(seq.names[i])
        preds = {m: r.figure_depths[i] for m, r in runs.items() if i in r.figure_depths}
        if gt is None or not preds:
            continue
        blocks.append(qualitative_figure(seq.frame(i).image, gt, preds, bench.eval,
                                         title=f"{seq.name}\nframe {seq.names[i]}"))
    if not blocks:
        return None
    width = max(b.shape[1] for b in blocks)
    return np.vstack([np.pad(b, ((0, 8), (0, width - b.shape[1]), (0, 0)), constant_values=255)
                      for b in blocks])


def segment_labels(seq: ImageSequence, indices: Sequence[int]) -> list[str] | None:
    """The per-frame segment labels of a generated drive (``segments.txt`` beside the image
    folder, written by ``sfm-ttr generate --scenario hard``) for ``indices``; None when there
    is none or it does not cover them."""
    from sfm_ttr_ros.data.kitti import SEGMENTS_FILE, read_segments

    if not seq.image_paths:
        return None
    path = Path(seq.image_paths[0]).parent.parent / SEGMENTS_FILE
    if not path.is_file():
        return None
    try:
        labels = read_segments(path)
        return [labels[i] for i in indices]
    except (InputError, IndexError) as exc:
        log.warning("ignoring %s: %s", path, exc)
        return None
