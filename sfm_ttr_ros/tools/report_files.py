"""The report files that ``sfm-ttr benchmark``, ``sfm-ttr demo``, ``--split`` and ``sfm-ttr
evaluate`` write, written one way wherever they report the same thing.

* ``results.json``: :func:`write_json` (strict JSON: NaN / inf as null, numpy scalars and arrays
  as numbers and lists, paths as strings; indented by 2, newline at the end);
* ``results.md``: :func:`metric_table` (the KITTI metrics, one row per method, 4 decimals),
  :func:`gain_table` (the relative gains against a baseline, in %) and :func:`markdown_table`
  (any other table: ``sfm-ttr speed``'s);
* ``per_frame.csv``: :func:`write_per_frame_csv` (``index``, ``name``, then per method
  ``<method>_abs_rel``, ``<method>_rmse`` and whatever else it knows per frame).
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sfm_ttr_ros.core.evaluation import METRICS, format_table

#: The per-method columns of the benchmark's per_frame.csv.
PER_FRAME_COLUMNS = ("abs_rel", "rmse", "refined", "reason")


def json_safe(v):
    """``v`` with every value strict JSON can hold: NaN / inf -> None, numpy -> Python, paths ->
    strings, dict keys -> strings (recursively)."""
    if isinstance(v, dict):
        return {str(k): json_safe(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [json_safe(x) for x in v]
    if isinstance(v, np.ndarray):
        return json_safe(v.tolist())
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, Path):
        return str(v)
    return v


def write_json(path: str | Path, doc: Mapping[str, Any]) -> dict[str, Any]:
    """Write ``doc`` made :func:`json_safe` to ``path``; returns what was written."""
    safe = json_safe(dict(doc))
    Path(path).write_text(json.dumps(safe, indent=2) + "\n")
    return safe


def metric_table(results: Mapping[str, Mapping[str, Any]], decimals: int = 4) -> str:
    """The Markdown table of the KITTI metrics and ``frames`` of each method (a metric that is
    None or missing shows as n/a)."""
    rows = {}
    for method, r in results.items():
        rows[method] = {k: (math.nan if r.get(k) is None else r.get(k)) for k in METRICS}
        rows[method]["frames"] = r.get("frames")
    return format_table(rows, decimals=decimals)


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> list[str]:
    """Markdown lines of a table: ``header``, the first column left-aligned and the others
    right-aligned, one line per row (cells as given, already formatted)."""
    return ["| " + " | ".join(header) + " |", "|---|" + "---:|" * (len(header) - 1),
            *("| " + " | ".join(str(c) for c in row) + " |" for row in rows)]


def format_gain(v) -> str:
    """A relative gain as a signed percentage (n/a for None / NaN)."""
    return "n/a" if v is None or not math.isfinite(float(v)) else f"{100 * float(v):+.1f} %"


def gain_table(gains: Mapping[str, Mapping[str, Any]],
               title: str = "Relative gain against no_ttr (positive = better):") -> list[str]:
    """Markdown lines: ``title`` and one row of :func:`format_gain` per method (none for no
    gains)."""
    if not gains:
        return []
    lines = [title, "", "| method | " + " | ".join(METRICS) + " |",
             "|---|" + "---:|" * len(METRICS)]
    for m, g in gains.items():
        lines.append(f"| {m} | " + " | ".join(format_gain(g.get(k)) for k in METRICS) + " |")
    return [*lines, ""]


def _csv_cell(column: str, value: Any) -> Any:
    if column == "refined":
        return int(bool(value))
    if value is None:
        return ""
    if isinstance(value, float | np.floating):
        return f"{value:.6f}"
    return value


def write_per_frame_csv(path: str | Path, frames: Sequence[tuple[int, str]],
                        per_frame: Mapping[str, Mapping[int, Mapping[str, Any]]],
                        columns: Sequence[str] = PER_FRAME_COLUMNS) -> None:
    """``per_frame.csv``: one row per ``(index, name)`` of ``frames``, then for each method of
    ``per_frame`` (method -> frame index -> its values) its ``columns`` (numbers with 6
    decimals, empty where the method has no value for the frame, ``refined`` as 0 / 1)."""
    header = ["index", "name", *(f"{m}_{c}" for m in per_frame for c in columns)]
    with open(path, "w", newline="") as fh:
        wr = csv.writer(fh)
        wr.writerow(header)
        for index, name in frames:
            row: list[Any] = [index, name]
            for rows in per_frame.values():
                values = rows.get(index, {})
                row += [_csv_cell(c, values.get(c)) for c in columns]
            wr.writerow(row)
