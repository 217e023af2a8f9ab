"""The figures ``scripts/gpu_window_check.sh`` must print, and the one measurement of them that
no other tool makes: a captured step's cost across windows.

:func:`graph_windows`: one window's refinement repeated ``windows`` times from the same start
weights (restored in place, as the weight policy does), ``step_mode`` auto: per window the host
seconds spent capturing (the first window's capture; ~0 from the second on, when the kept graph
is re-armed: core/refinement/graph_cache.py), the mode and whether the graph was reused, and
the device memory reserved after the 2nd and the last window (no growth: the graph's memory
pool is made once).

:func:`summary_table`: the issue's figures in one table, from
:func:`~sfm_ttr_ros.tools.step_profile.check_summary`: captured and eager step ms, the
graph-vs-eager loss difference, capture cost per window, memory after 2 and N windows, live
p95 while refining (graph against eager; the generated drive and hololens_000), SfM seconds per
stage with pycolmap's SIFT and the torch SIFT, last frame to first served weights.
"""

from __future__ import annotations

from typing import Any

from sfm_ttr_ros.core.refinement.refinement_config import RefinementConfig


def _reserved_mb(device) -> float | None:
    import torch

    if getattr(device, "type", "") != "cuda":
        return None
    torch.cuda.synchronize(device)
    return round(torch.cuda.memory_reserved(device) / 2**20, 1)


def graph_windows(model, supervision, photometric, cfg: RefinementConfig,
                  windows: int = 10) -> dict[str, Any]:
    """The module docstring's measurement; the model's weights are put back afterwards."""
    import dataclasses

    from sfm_ttr_ros.core.refinement.encoder import (
        refine_encoder,
        restore_encoder,
        snapshot_encoder,
    )

    start = snapshot_encoder(model)
    run = dataclasses.replace(cfg, step_mode="auto")
    rows, memory = [], {}
    try:
        for k in range(1, windows + 1):
            restore_encoder(model, start)
            res = refine_encoder(model, supervision, run, photometric=photometric)
            rows.append({"window": k, "step_mode": res.step_mode,
                         "reason": res.step_mode_reason, "reused": res.graph_reused,
                         "capture_ms": round(res.capture_s * 1e3, 3),
                         "seconds": round(res.seconds, 4)})
            if k in (2, windows):
                memory[f"reserved_mb_after_{k}"] = _reserved_mb(model.device)
    finally:
        restore_encoder(model, start)
    later = [r["capture_ms"] for r in rows[1:]]
    return {"windows": rows, **memory,
            "capture_ms_first": rows[0]["capture_ms"] if rows else None,
            "capture_ms_later_max": max(later) if later else None}


def _get(d, *keys):
    for k in keys:
        if not isinstance(d, dict):
            return None
        d = d.get(k)
    return d


def _fmt(v, unit: str = "", scale: float = 1.0) -> str:
    if v is None:
        return "-"
    if isinstance(v, float | int) and not isinstance(v, bool):
        return f"{v * scale:.3g}{unit}"
    return str(v)


def summary_rows(s: dict[str, Any]) -> list[tuple[str, str, str]]:
    """(figure, value, target) rows of the issue's figures from a check summary."""
    timing = _get(s, "timing", "timing") or _get(s, "profile", "profile") or {}
    win = s.get("windows") or {}
    sfm = _get(s, "timing", "sfm") or {}
    rows = [
        ("captured step ms (replay)", _fmt(_get(timing, "auto", "steady_ms_per_step")), "<= 5"),
        ("eager step ms", _fmt(_get(timing, "eager", "steady_ms_per_step")), ""),
        ("graph vs eager loss, max rel diff", _fmt(_get(timing, "auto", "max_rel_loss_diff")),
         "~1e-5"),
        ("capture ms, 1st window", _fmt(win.get("capture_ms_first")), ""),
        ("capture ms, windows 2.., max", _fmt(win.get("capture_ms_later_max")), "<= 10"),
        ("reserved MB after 2 windows", _fmt(win.get("reserved_mb_after_2")), ""),
        ("reserved MB after last window", _fmt(win.get(
            f"reserved_mb_after_{len(win.get('windows') or [])}")), "= after 2"),
    ]
    for label, bench in (("drive", "bench"), ("hololens_000", "holo")):
        for mode in ("graph", "eager"):
            rows.append((f"live p95 ms while refining, {label}, {mode}",
                         _fmt(_get(s, f"{bench}_{mode}", "sfm_ttr_live", "latency_p95_s"),
                              "", 1e3), "<= 30, graph <= eager"))
        rows.append((f"last frame -> first served weights s, {label}",
                     _fmt(_get(s, f"{bench}_graph", "sfm_ttr_live",
                               "last_frame_to_first_weights_s")), ""))
    for kind in ("colmap", "torch"):
        t = _get(sfm, kind, "timings") or {}
        stages = ", ".join(f"{k} {v:.2f}" for k, v in t.items()) or "-"
        rows.append((f"SfM s per stage, {kind} SIFT", stages, ""))
    return rows


def summary_table(s: dict[str, Any]) -> list[str]:
    """:func:`summary_rows` as a Markdown table."""
    lines = ["| figure | value | target |", "| --- | --- | --- |"]
    lines += [f"| {a} | {b} | {c} |" for a, b, c in summary_rows(s)]
    return lines
