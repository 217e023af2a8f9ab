"""The benchmark's reports: ``results.md`` and ``per_frame.csv`` (their tables, the JSON and
the CSV written by the shared :mod:`sfm_ttr_ros.tools.report_files`, as the demo's are), the
settings and model as ``results.json`` records them."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from sfm_ttr_ros.core.evaluation import ERROR_METRICS
from sfm_ttr_ros.data.sequence import ImageSequence
from sfm_ttr_ros.tools.benchmark.bands import ERROR_FIGURE
from sfm_ttr_ros.tools.benchmark.path import path_lines
from sfm_ttr_ros.tools.benchmark.runners import MODES, ModeRun
from sfm_ttr_ros.tools.report_files import gain_table, metric_table, write_per_frame_csv


def config_dict(obj) -> dict:
    from dataclasses import asdict, is_dataclass

    return asdict(obj) if is_dataclass(obj) else dict(obj)


def describe_model(model) -> dict[str, Any]:
    """Class, input size and parameter counts of a depth network."""
    enc = sum(p.numel() for p in model.encoder.parameters())
    total = sum(p.numel() for p in model.parameters())
    return {"class": type(model).__name__, "input_size": list(getattr(model, "input_size", ())),
            "parameters": int(total), "encoder_parameters": int(enc)}


def write_per_frame(path: Path, seq: ImageSequence, gt_indices: Sequence[int],
                    runs: Mapping[str, ModeRun]) -> None:
    """``per_frame.csv``: abs rel, RMSE, the scale ratio (median GT / median prediction),
    refined and reason of every GT frame in every mode."""
    write_per_frame_csv(path, [(i, seq.names[i]) for i in gt_indices],
                        {m: r.per_frame for m, r in runs.items()},
                        ("abs_rel", "rmse", "ratio", "refined", "reason"))


def band_table(results: Mapping[str, Any], modes: Sequence[str]) -> list[str]:
    """results.md's lines for the ``bands`` of every mode: abs rel / RMSE per GT depth band
    (pooled over pixels) and each band's pixel count."""
    names = next((list(results[m]["bands"]) for m in modes if results[m].get("bands")), [])
    if not names:
        return []

    def cell(b: Mapping[str, Any] | None) -> str:
        if not b or not b.get("pixels"):
            return "n/a"
        return f"{b['abs_rel']:.4f} / {b['rmse']:.3f}"

    lines = ["By GT depth band (abs rel / RMSE over the band's pixels of all GT frames):", "",
             "| method | " + " | ".join(f"{n} m" for n in names) + " |",
             "|---|" + "---:|" * len(names)]
    for m in modes:
        bands = results[m].get("bands") or {}
        lines.append(f"| {m} | " + " | ".join(cell(bands.get(n)) for n in names) + " |")
    first = results[modes[0]].get("bands") or {}
    lines += ["| pixels | " + " | ".join(str((first.get(n) or {}).get("pixels", 0))
                                         for n in names) + " |", ""]
    return lines


def results_markdown(results: Mapping[str, Any]) -> str:
    """``results.md``: the metric table, the gains against no_ttr, time and the figure."""
    modes = [m for m in results.get("modes", MODES) if m in results]
    ev = results.get("settings", {}).get("eval", {})
    lines = [f"# SfM-TTR benchmark: {results.get('sequence', '')}", ""]
    model = results.get("model", {})
    lines.append(
        f"{results.get('frames_total')} frames, {results.get('frames_with_gt')} with ground "
        f"truth; model {model.get('type', '')} {model.get('class', '')} "
        f"{'x'.join(str(v) for v in model.get('input_size', []))}; Eigen crop "
        f"{'on' if ev.get('eigen_crop') else 'off'}, median scaling "
        f"{'on' if ev.get('median_scaling', True) else 'off'}, depth cap "
        f"{ev.get('max_depth', 80)} m.")
    lines += ["", metric_table({m: results[m] for m in modes})]
    lines += band_table(results, modes)
    lines += gain_table(results.get("relative_gain") or {})
    stages = ("sfm", "align", "refine", "predict_before", "predict_after", "predict", "check")
    lines += ["| method | s/frame | refined frames | windows (refined) | "
              + " | ".join(f"{s} s" for s in stages) + " |",
              "|---|" + "---:|" * (3 + len(stages))]
    for m in modes:
        r = results[m]
        t = r.get("timings", {})
        win = f"{r['windows']} ({r.get('windows_refined', 0)})" if "windows" in r else "-"
        spf = r.get("seconds_per_frame")
        lines.append(f"| {m} | {spf:.2f} | {r.get('refined_frames', 0)}/"
                     f"{r.get('processed_frames', 0)} | {win} | "
                     + " | ".join(f"{t[s]:.1f}" if s in t else "-" for s in stages) + " |")
    lines += ["", "Lower is better for " + ", ".join(ERROR_METRICS)
              + "; higher for a1-a3. Frames SfM could not use count with the prediction the "
              "mode published for them.", ""]
    lines += window_check_lines(results, modes)
    lines += path_lines(results, modes)
    lines += [f"![error by GT depth]({ERROR_FIGURE})", ""]
    if results.get("figure_frames"):
        lines += [f"![qualitative results, frames {', '.join(results['figure_frames'])}]"
                  "(figure.png)", ""]
    lines += ["Command:", "", "```", str(results.get("command", "")), "```", ""]
    return "\n".join(lines)


def window_check_lines(results: Mapping[str, Any], modes: Sequence[str]) -> list[str]:
    """Markdown: per windowed mode, each window's outcome (its reason key when not refined),
    mean reprojection error and unsupported change; the window timeline figure."""
    logged = [m for m in modes if results[m].get("window_log")]
    if not logged:
        return []
    lines = ["Windows (refused = a window check refused it; reprojection = the mean SfM "
             "reprojection error, px; unsupported = share of the pixels far from every SfM "
             "point whose depth the refinement moved):", "",
             "| method | window | frames | outcome | reprojection | unsupported |",
             "|---|---:|---|---|---:|---:|"]
    for m in logged:
        for w in results[m]["window_log"]:
            c = w.get("check") or {}
            frames = w.get("frames") or [0]
            what = "refined" if w.get("refined") else w.get("reason_key") or "unrefined"
            r, u = (_fixed(c.get(k), 3) for k in ("reprojection_error", "unsupported_change"))
            lines.append(f"| {m} | {w['index']} | {min(frames)}-{max(frames)} | {what} | "
                         f"{r} | {u} |")
    return lines + ["", "![windows](windows.png)", ""]


def _fixed(v: Any, decimals: int) -> str:
    return f"{v:.{decimals}f}" if isinstance(v, float) and math.isfinite(v) else "-"
