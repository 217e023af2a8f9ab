"""A split's results: ``OUT/results.json``, ``OUT/results.md`` and ``OUT/per_frame.csv``.

* One row per sequence: status (done, failed with its reason, or not run when interrupted),
  where it ran, attempts, frames, and per mode the KITTI metrics, refined frames and seconds.
* The split's metrics per mode pooled over all evaluated frames of the done sequences, the
  paper's way (each metric is the mean over frames, so the pool is the frame-weighted mean of
  the sequences' means; frames SfM could not use count with the prediction the mode published,
  unrefined), and their gain against ``no_ttr``.
* The counts: sequences done (computed now or reused from an earlier run), failed, not run,
  retried (and the retries).
* Where the time went, summed over the sequences: SfM, alignment, refinement, prediction per
  mode, and the rest of each task (reading images, evaluation, figures, the network's set-up).
* ``per_frame.csv``: every sequence's ``per_frame.csv`` one after the other, a ``sequence``
  column first.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from sfm_ttr_ros.core.evaluation import METRICS, format_table, relative_gain
from sfm_ttr_ros.tools.split.cache import sequence_dir
from sfm_ttr_ros.tools.split.spec import SequenceSpec

#: Timings shown in the time table (benchmark stages; ``run``'s window has the same names).
STAGES = ("sfm", "align", "refine", "predict_before", "predict_after", "predict", "check")


def pooled_metrics(rows: Sequence[Mapping[str, Any]], modes: Sequence[str]
                   ) -> dict[str, dict[str, Any]]:
    """Per mode: every metric's mean over all evaluated frames of ``rows`` (sequence rows),
    with ``frames``, ``sequences``, ``refined_frames`` and ``processed_frames``."""
    out: dict[str, dict[str, Any]] = {}
    for mode in modes:
        parts = [r["modes"][mode] for r in rows if mode in r.get("modes", {})]
        parts = [p for p in parts if p.get("frames")]
        frames = sum(int(p["frames"]) for p in parts)
        pooled: dict[str, Any] = {
            m: (sum(p[m] * p["frames"] for p in parts) / frames if frames else math.nan)
            for m in METRICS}
        pooled.update(frames=frames, sequences=len(parts),
                      refined_frames=sum(int(p.get("refined_frames") or 0) for p in parts),
                      processed_frames=sum(int(p.get("processed_frames") or 0) for p in parts))
        out[mode] = pooled
    return out


def time_split(rows: Sequence[Mapping[str, Any]], modes: Sequence[str]) -> dict[str, Any]:
    """Seconds summed over ``rows``: per mode its stages and total, and the tasks' total, the
    opening of the sequences (a bag's decoding) and the rest (images read, evaluation, figures,
    network set-up: a task's time outside its modes)."""
    per_mode: dict[str, dict[str, float]] = {}
    for mode in modes:
        acc: dict[str, float] = {"seconds": 0.0}
        for r in rows:
            m = r.get("modes", {}).get(mode) or {}
            acc["seconds"] += float(m.get("seconds") or 0.0)
            for k, v in (m.get("timings") or {}).items():
                if k in STAGES:
                    acc[k] = acc.get(k, 0.0) + float(v)
        per_mode[mode] = acc
    tasks = sum(float(r.get("task_seconds") or 0.0) for r in rows)
    opening = sum(float(r.get("open_seconds") or 0.0) for r in rows)
    in_modes = sum(m["seconds"] for m in per_mode.values())
    return {"modes": per_mode, "tasks": tasks, "open": opening,
            "other": max(0.0, tasks - in_modes - opening)}


def merge_per_frame(out: Path, ids: Sequence[str]) -> int:
    """``out/per_frame.csv`` from the sequences' own, in ``ids`` order; rows written."""
    header: list[str] = ["sequence"]
    rows: list[dict[str, str]] = []
    for sid in ids:
        path = sequence_dir(out, sid) / "per_frame.csv"
        if not path.is_file():
            continue
        with open(path, newline="") as fh:
            reader = csv.DictReader(fh)
            for col in reader.fieldnames or []:
                if col not in header:
                    header.append(col)
            rows += [{"sequence": sid, **row} for row in reader]
    with open(out / "per_frame.csv", "w", newline="") as fh:
        wr = csv.DictWriter(fh, fieldnames=header, restval="")
        wr.writeheader()
        wr.writerows(rows)
    return len(rows)


def build_results(specs: Sequence[SequenceSpec], records: Mapping[str, dict[str, Any]],
                  reused: set[str], modes: Sequence[str], *, split_file: str, command: str,
                  kind: str, engine: Mapping[str, Any], retried: Mapping[str, int],
                  interrupted: bool, settings: Mapping[str, Any]) -> dict[str, Any]:
    """results.json's content (module docstring); ``records`` = the stored record of every
    sequence that ended (done or failed), by id."""
    sequences = []
    for s in specs:
        rec = records.get(s.id)
        base = {"id": s.id, "source": s.describe(), "lines": list(s.lines)}
        if rec is None:
            key = "interrupted" if interrupted else "not_run"
            sequences.append({**base, "status": "not_run", "reason": key.replace("_", " "),
                              "reason_key": key})
            continue
        row = rec.get("row") or {}
        sequences.append({**base, "status": rec["status"], "reason": rec.get("reason", ""),
                          "reason_key": rec.get("reason_key", ""),
                          "reused": s.id in reused, "attempts": rec.get("attempts", 1),
                          "retries": int(retried.get(s.id, 0)), "host": rec.get("host", ""),
                          "seconds": rec.get("seconds", 0.0), **row})
    done = [q for q in sequences if q["status"] == "done"]
    pooled = pooled_metrics(done, modes)
    results: dict[str, Any] = {
        "split": split_file, "command_kind": kind, "modes": list(modes),
        "counts": {
            "sequences": len(specs), "done": len(done),
            "computed": sum(1 for q in done if not q.get("reused")),
            "reused": sum(1 for q in done if q.get("reused")),
            "failed": sum(1 for q in sequences if q["status"] == "failed"),
            "not_run": sum(1 for q in sequences if q["status"] == "not_run"),
            "retried": sum(1 for n in retried.values() if n),
            "retries": int(sum(retried.values())),
        },
        "interrupted": interrupted,
        "pooled": pooled,
    }
    if "no_ttr" in modes:
        results["relative_gain"] = {m: relative_gain(pooled["no_ttr"], pooled[m])
                                    for m in modes if m != "no_ttr"}
    results["time"] = time_split(done, modes)
    results["sequences"] = sequences
    results["engine"] = dict(engine)
    results["settings"] = dict(settings)
    results["command"] = command
    return results


def _f(v, fmt: str = ".4f") -> str:
    return "n/a" if v is None or (isinstance(v, float) and not math.isfinite(v)) \
        else format(v, fmt)


def results_markdown(res: Mapping[str, Any]) -> str:
    modes = res["modes"]
    c = res["counts"]
    lines = [f"# SfM-TTR split: {res['split']}", "",
             f"{c['sequences']} sequences: {c['done']} done ({c['computed']} computed, "
             f"{c['reused']} reused from an earlier run), {c['failed']} failed, {c['not_run']} "
             f"not run; {c['retried']} retried after a lost worker ({c['retries']} retries)"
             + (". INTERRUPTED: the table holds the sequences that ended." if res["interrupted"]
                else "."), "",
             "Pooled over every evaluated frame of the done sequences (the paper's way):", "",
             format_table({m: {k: (math.nan if res["pooled"][m].get(k) is None
                                   else res["pooled"][m][k]) for k in (*METRICS, "frames")}
                           for m in modes}, decimals=4)]
    gains = res.get("relative_gain") or {}
    if gains:
        lines += ["Relative gain against no_ttr (positive = better):", "",
                  "| method | " + " | ".join(METRICS) + " |",
                  "|---|" + "---:|" * len(METRICS)]
        for m, g in gains.items():
            lines.append(f"| {m} | " + " | ".join(
                "n/a" if not math.isfinite(g.get(k, math.nan)) else f"{100 * g[k]:+.1f} %"
                for k in METRICS) + " |")
        lines.append("")
    lines += ["Per sequence (abs rel / RMSE per mode; refined frames of the last mode):", "",
              "| sequence | status | frames | GT frames | "
              + " | ".join(modes) + " | refined | s | attempts | where |",
              "|---|---|---:|---:|" + "---:|" * len(modes) + "---:|---:|---:|---|"]
    for q in res["sequences"]:
        if q["status"] != "done":
            reason = str(q.get("reason", "")).replace("|", "/").replace("\n", " ")
            cells = [q["id"], f"{q['status']}: {reason}", "", "", *([""] * len(modes)), "",
                     f"{q.get('seconds', 0):.1f}" if "seconds" in q else "",
                     str(q.get("attempts", "")), q.get("host", "")]
            lines.append("| " + " | ".join(cells) + " |")
            continue
        cells = [f"{_f(q['modes'][m].get('abs_rel'))} / {_f(q['modes'][m].get('rmse'), '.3f')}"
                 for m in modes]
        last = q["modes"][modes[-1]]
        status = "done (reused)" if q.get("reused") else "done"
        lines.append(f"| {q['id']} | {status} | {q.get('frames_total')} | "
                     f"{q.get('frames_with_gt')} | " + " | ".join(cells)
                     + f" | {last.get('refined_frames', 0)}/{last.get('processed_frames', 0)} | "
                     f"{q.get('seconds', 0):.1f} | {q.get('attempts', 1)} | {q.get('host', '')} |")
    t = res["time"]
    lines += ["", "Where the time went (seconds summed over the done sequences' tasks):", "",
              "| mode | total | " + " | ".join(STAGES) + " |",
              "|---|---:|" + "---:|" * len(STAGES)]
    for m, acc in t["modes"].items():
        lines.append(f"| {m} | {acc['seconds']:.1f} | "
                     + " | ".join(f"{acc[s]:.1f}" if s in acc else "-" for s in STAGES) + " |")
    lines += ["", f"Tasks {t['tasks']:.1f} s in all: opening the sequences {t['open']:.1f} s, "
              f"outside the modes (reading images, evaluation, figures, network set-up) "
              f"{t['other']:.1f} s. Engine: {res['engine'].get('where', '')}, wall "
              f"{res['engine'].get('seconds', 0):.1f} s.", "",
              "Each sequence's own results: sequences/<id>/ (results.md, per_frame.csv, "
              "figures); failures with their traceback: failed/<id>.json.", "",
              "Command:", "", "```", str(res.get("command", "")), "```", ""]
    return "\n".join(lines)


def write_results(out: Path, results: dict[str, Any]) -> None:
    from sfm_ttr_ros.tools.report_files import write_json

    out = Path(out)
    write_json(out / "results.json", results)
    (out / "results.md").write_text(results_markdown(results))
    merge_per_frame(out, [q["id"] for q in results["sequences"] if q["status"] == "done"])
