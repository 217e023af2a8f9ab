"""``run_benchmark``: the modes over a sequence, then the reports and the figure."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.evaluation import EvalConfig, relative_gain
from sfm_ttr_ros.core.pipeline import TTRConfig
from sfm_ttr_ros.core.stream.windows import StreamSettings
from sfm_ttr_ros.data.sequence import ImageSequence
from sfm_ttr_ros.tools.benchmark.bands import ERROR_FIGURE, error_by_depth_figure
from sfm_ttr_ros.tools.benchmark.figure import pick_figure_frames, qualitative_figure
from sfm_ttr_ros.tools.benchmark.live import run_live
from sfm_ttr_ros.tools.benchmark.report import (
    config_dict,
    describe_model,
    results_markdown,
    write_per_frame,
)
from sfm_ttr_ros.tools.benchmark.runners import (
    DEFAULT_MODES,
    MODES,
    ModeRun,
    log,
    mode_config,
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
from sfm_ttr_ros.tools.report import write_json


def _stderr(line: str) -> None:
    print(f"sfm-ttr benchmark: {line}", file=sys.stderr, flush=True)


def run_benchmark(
    seq: ImageSequence,
    model_factory: Callable[[], Any],
    ttr_config: TTRConfig | None = None,
    stream_settings: StreamSettings | None = None,
    out_dir: str | Path = "benchmark",
    modes: Sequence[str] = DEFAULT_MODES,
    eval_config: EvalConfig | None = None,
    *,
    start: int = 0,
    max_frames: int = 0,
    offline_max_frames: int = 0,
    figure_frames: int = 2,
    save_depth: bool = False,
    model_description: Mapping[str, Any] | None = None,
    settings_info: Mapping[str, Any] | None = None,
    command: str | None = None,
    progress: Callable[[str], None] | None = _stderr,
    rate: float = 10.0,
) -> dict[str, Any]:
    """Run ``modes`` over frames ``start .. start+max_frames`` (0 = to the end) of ``seq`` and
    write ``results.json``, ``results.md``, ``per_frame.csv`` and ``figure.png`` to
    ``out_dir``; returns the ``results.json`` content.

    ``model_factory()`` must return a new network with the original weights at every call (one
    per mode). ``ttr_config`` / ``stream_settings`` default to the node's ``params/kitti.yaml``.
    ``offline_max_frames`` > 0 splits the offline mode into chunks of that many frames.
    ``save_depth`` also writes every depth as ``out_dir/depth/<mode>/<frame>.npy`` (network
    units, for ``sfm-ttr evaluate --pred``). ``progress`` gets one line per step (None: quiet).
    ``rate``: the input rate (Hz) of the real-time ``sfm_ttr_live`` mode.
    """
    modes = list(dict.fromkeys(modes))
    bad = [m for m in modes if m not in MODES]
    if not modes or bad:
        raise InputError(f"unknown mode(s) {bad}; choose from {', '.join(MODES)}")
    if start < 0 or max_frames < 0 or offline_max_frames < 0:
        raise InputError("start, max_frames and offline_max_frames must be >= 0")
    if ttr_config is None or stream_settings is None:
        cfg_p, settings_p, _ = settings_from_params(read_params_file(default_params_file()))
        ttr_config = ttr_config or cfg_p
        stream_settings = stream_settings or settings_p
    eval_config = eval_config or EvalConfig()
    n_all = len(seq)
    if start >= n_all:
        raise InputError(f"--start {start} is past the end of the sequence ({n_all} frames)")
    stop = n_all if max_frames <= 0 else min(n_all, start + max_frames)
    indices = list(range(start, stop))
    names = seq.names
    gt_indices = [i for i in indices if names[i] in seq.gt_paths]
    if not gt_indices:
        raise InputError(f"none of the {len(indices)} frames {start}-{stop - 1} of {seq.name} has "
                         "ground truth: nothing to evaluate (check --kitti-gt / --gt-depth)")
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the output folder {out}: {exc}") from exc
    fig_idx = pick_figure_frames(gt_indices, figure_frames)
    if progress:
        progress(f"{seq.name}: {len(indices)} frames ({start}-{stop - 1}), {len(gt_indices)} "
                 f"with ground truth; modes {', '.join(modes)}; output {out}")

    runs: dict[str, ModeRun] = {}
    description = dict(model_description or {})
    for mode in modes:
        model = model_factory()
        if "class" not in description:
            description.update(describe_model(model))
        run = ModeRun(mode, seq, indices, fig_idx, eval_config,
                       out / "depth" / mode if save_depth else None)
        if progress:
            progress(f"{mode}: start")
        t0 = time.perf_counter()
        if mode == "no_ttr":
            run_no_ttr(run, seq, indices, model, ttr_config, progress)
        elif mode.endswith("_online"):  # sfm_ttr / ph_ttr / hybrid: the mode's loss
            run_online(run, seq, indices, model, mode_config(mode, ttr_config), stream_settings,
                       progress)
        elif mode == "sfm_ttr_live":
            run_live(run, seq, indices, model, ttr_config, stream_settings, progress, rate)
        else:
            run_offline(run, seq, indices, model, mode_config(mode, ttr_config),
                        offline_max_frames, progress)
        runs[mode] = run
        del model
        s = run.summary(len(indices))
        if s["lost_frames"]:
            log.error("%s: %d frame(s) never came out", mode, s["lost_frames"])
        if s["not_published"]:
            log.warning("%s: %d frame(s) skipped and counted: %s", mode,
                        sum(s["not_published"].values()), s["not_published"])
        if progress:
            progress(f"{mode}: done in {time.perf_counter() - t0:.1f} s "
                     f"({s['seconds_per_frame']:.2f} s/frame), abs rel {s['abs_rel']:.4f}, "
                     f"RMSE {s['rmse']:.3f}, {s['refined_frames']}/{len(indices)} refined, "
                     f"{s['frames']} evaluated")

    results: dict[str, Any] = {
        "sequence": seq.name,
        "frames_total": len(indices),
        "frames_with_gt": len(gt_indices),
        "first_frame": start,
        "modes": modes,
    }
    for mode, run in runs.items():
        results[mode] = run.summary(len(indices))
    if "no_ttr" in runs:
        results["relative_gain"] = {m: relative_gain(results["no_ttr"], results[m])
                                    for m in modes if m != "no_ttr"}
    results["settings"] = {
        "eval": config_dict(eval_config),
        "ttr": config_dict(ttr_config),
        "stream": config_dict(stream_settings),
        "offline_max_frames": offline_max_frames,
        **dict(settings_info or {}),
    }
    results["model"] = description
    results["command"] = command if command is not None else " ".join(sys.argv)
    results["figure_frames"] = [names[i] for i in fig_idx]
    results = write_json(out / "results.json", results)
    (out / "results.md").write_text(results_markdown(results))
    write_per_frame(out / "per_frame.csv", seq, gt_indices, runs)
    curves = {m: results[m]["error_by_depth"] for m in modes if m in results}
    if not cv2.imwrite(str(out / ERROR_FIGURE), error_by_depth_figure(
            curves, title=f"{seq.name}: abs rel by GT depth (pixels of all GT frames)")):
        raise InputError(f"cannot write {out / ERROR_FIGURE}")
    logs = {m: results[m]["window_log"] for m in modes if results[m].get("window_log")}
    if logs:
        abs_rel = {m: {i: row.get("abs_rel") for i, row in r.per_frame.items()}
                   for m, r in runs.items()}
        labels = segment_labels(seq, indices)
        if not cv2.imwrite(str(out / TIMELINE_FIGURE), window_timeline_figure(
                abs_rel, logs, indices[0], indices[-1], labels=labels,
                title=f"{seq.name}: abs rel per frame; windows refined (green), refused by a "
                      "check (red), else unrefined (grey)")):
            raise InputError(f"cannot write {out / TIMELINE_FIGURE}")
    if fig_idx:
        blocks = []
        for i in fig_idx:
            gt = seq.gt(names[i])
            preds = {m: r.figure_depths[i] for m, r in runs.items() if i in r.figure_depths}
            if gt is None or not preds:
                continue
            blocks.append(qualitative_figure(seq.frame(i).image, gt, preds, eval_config,
                                             title=f"{seq.name}\nframe {names[i]}"))
        if blocks:
            width = max(b.shape[1] for b in blocks)
            blocks = [np.pad(b, ((0, 8), (0, width - b.shape[1]), (0, 0)),
                             constant_values=255) for b in blocks]
            if not cv2.imwrite(str(out / "figure.png"), np.vstack(blocks)):
                raise InputError(f"cannot write {out / 'figure.png'}")
    if progress:
        progress(f"results in {out}/results.json, results.md, per_frame.csv, figure.png, "
                 f"{ERROR_FIGURE}")
    return results


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
