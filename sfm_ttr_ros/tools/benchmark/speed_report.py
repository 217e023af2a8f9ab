"""``sfm-ttr speed``'s reports: ``speed.json`` (:func:`~sfm_ttr_ros.tools.report_files.write_json`)
and ``speed.md`` (tables through :func:`~sfm_ttr_ros.tools.report_files.markdown_table`): per
configuration the time per frame, latency, accuracy and stage shares, the speed-up naive/tuned,
and the memory run."""

from __future__ import annotations

import math
import os
import platform
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from sfm_ttr_ros.tools.benchmark.speed import LATENCY_DEFINITION, STAGES
from sfm_ttr_ros.tools.report_files import markdown_table, write_json


def _f(v, fmt: str = ".3f") -> str:
    return "n/a" if v is None or (isinstance(v, float) and not math.isfinite(v)) \
        else format(v, fmt)


def _pct(v) -> str:
    return _f(None if v is None else 100 * v, "+.2f")


def _config_rows(results: Mapping[str, Any]) -> list[list[str]]:
    rows = []
    for name, r in results["configs"].items():
        a = r["accuracy"]
        rows.append([name, _f(r["seconds_per_frame"]), _f(r["latency_s"]["median"], ".2f"),
                     _f(r["latency_s"]["max"], ".2f"), _f(a["abs_rel"], ".4f"), _f(a["rmse"]),
                     f"{r['refined_frames']}/{r['frames']}",
                     f"{r['windows']} ({r['windows_refined']})", str(r["refinement_steps"])])
    if "no_ttr" in results:
        b = results["no_ttr"]
        rows.append(["no_ttr (reference)", _f(b["seconds_per_frame"]), "-", "-",
                     _f(b["abs_rel"], ".4f"), _f(b["rmse"]), "0", "-", "-"])
    return rows


def _memory_line(m: Mapping[str, Any]) -> str:
    a, e = m["rss_after_first"], m["rss_end"]
    return (f"Memory over {m['frames']} frames at {m['width']}x{m['height']}: peak RSS (VmHWM) "
            f"{m['peak_after_first_mib']:.0f} MiB after frame {m['after_frames']}, "
            f"{m['peak_mib']:.0f} MiB at the end (ratio {m['peak_ratio']:.3f}, within 10 %: "
            f"{'yes' if m['within_10_percent'] else 'NO'}); ru_maxrss "
            f"{a['ru_maxrss_kib'] / 1024:.0f} → {e['ru_maxrss_kib'] / 1024:.0f} MiB (ratio "
            f"{m['peak_ratio_ru_maxrss']:.3f}); VmRSS {a.get('VmRSS_kib', 0) / 1024:.0f} → "
            f"{e.get('VmRSS_kib', 0) / 1024:.0f} MiB; {m['seconds_per_frame']:.3f} s/frame, "
            f"{m['refined_frames']}/{m['published_frames']} refined.")


def speed_table(results: Mapping[str, Any]) -> str:
    """The main tables (markdown): one row per configuration, the stage shares, the
    comparison, the memory run."""
    cfgs = results.get("configs", {})
    lines: list[str] = []
    if cfgs:
        lines += markdown_table(["config", "s/frame", "latency median s", "latency max s",
                                 "abs rel", "RMSE", "refined frames", "windows (refined)",
                                 "steps"], _config_rows(results))
        lines += ["", "Stage shares (of all the work; seconds per input frame in brackets):", ""]
        lines += markdown_table(["config", *STAGES], [
            [name, *(f"{100 * r['stage_shares'][s]:.1f} % ({r['stages_s_per_frame'][s]:.3f})"
                     for s in STAGES)] for name, r in cfgs.items()])
        c = results.get("comparison") or {}
        if c:
            lines += ["", f"Speed-up naive/tuned: {_f(c['speedup_naive_over_tuned'], '.2f')}x; "
                      f"abs rel tuned vs naive: {_pct(c.get('abs_rel_relative_difference'))} % "
                      f"(RMSE {_pct(c.get('rmse_relative_difference'))} %).",
                      "Targets: " + ", ".join(f"{k}: {'yes' if v else 'NO'}"
                                              for k, v in c["targets"].items())]
    if results.get("memory"):
        lines += ["", _memory_line(results["memory"])]
    return "\n".join(lines)


def speed_markdown(results: Mapping[str, Any]) -> str:
    """``speed.md``: the drive, the machine, :func:`speed_table`, latency, settings, command."""
    d, mach = results.get("drive", {}), results.get("machine", {})
    lines = ["# SfM-TTR speed", ""]
    if d:
        lines.append(f"Drive: synthetic domain {d.get('domain')}, seed {d.get('seed')}, "
                     f"{d.get('frames')} frames of {d.get('width')}x{d.get('height')}. ")
    cuda = f" ({mach['cuda']})" if mach.get("cuda") else ""
    lines.append(f"Machine: {mach.get('cpus')} CPUs (load average "
                 f"{_f(mach.get('load_average_1min_at_start'), '.1f')} at the start), torch "
                 f"{mach.get('torch')} with {mach.get('torch_threads')} threads, device "
                 f"{mach.get('device')}{cuda}, pycolmap {mach.get('pycolmap')}.")
    lines += ["", speed_table(results), "", f"Latency: {LATENCY_DEFINITION}.", ""]
    cfgs = results.get("configs", {})
    if cfgs:
        lines += ["Queued latency at the input rate (median / max s): " + ", ".join(
            f"{k} {_f(r['queued_latency_at_input_rate_s']['median'], '.1f')} / "
            f"{_f(r['queued_latency_at_input_rate_s']['max'], '.1f')}" for k, r in cfgs.items()),
            "", "Settings:", ""]
        for k, r in cfgs.items():
            s = r["settings"]
            lines.append(f"- {k}: feature cache {'on' if s['feature_cache'] else 'off'}; "
                         f"overrides {s['overrides'] or 'none'}; model input "
                         f"{r['model'].get('input_size')}")
        lines.append("")
    lines += ["Command:", "", "```", str(results.get("command", "")), "```", ""]
    return "\n".join(lines)


def machine_info(device: str) -> dict[str, Any]:
    import pycolmap
    import torch

    return {"cpus": os.cpu_count(), "load_average_1min_at_start": os.getloadavg()[0],
            "torch": torch.__version__, "torch_threads": torch.get_num_threads(),
            "device": device,
            "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
            "pycolmap": pycolmap.__version__, "python": platform.python_version(),
            "platform": platform.platform()}


def write_speed(results: Mapping[str, Any], out_dir: str | Path) -> Path:
    """``out_dir/speed.json`` and ``speed.md``; the JSON's path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    safe = write_json(out / "speed.json", results)
    (out / "speed.md").write_text(speed_markdown(safe))
    return out / "speed.json"
