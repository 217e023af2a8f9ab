"""The shared report writer (tools/report_files.py): strict JSON, the metric and gain tables and the
per-frame CSV the benchmark and the demo both write."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from sfm_ttr_ros.core.evaluation import METRICS
from sfm_ttr_ros.tools.report_files import (
    format_gain,
    gain_table,
    json_safe,
    metric_table,
    write_json,
    write_per_frame_csv,
)


def test_json_is_strict_and_numpy_safe(tmp_path):
    doc = {"nan": math.nan, "inf": np.float32(np.inf), "n": np.int64(3), "x": np.float64(0.5),
           "arr": np.array([1.0, np.nan]), "path": Path("a/b"), 2: (1, None)}
    written = write_json(tmp_path / "r.json", doc)
    text = (tmp_path / "r.json").read_text()
    assert text.endswith("}\n") and "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == written == {"nan": None, "inf": None, "n": 3, "x": 0.5,
                                           "arr": [1.0, None], "path": "a/b", "2": [1, None]}
    assert json_safe([np.bool_(True)]) == [True]


def test_metric_and_gain_tables():
    row = {**{m: 0.1234567 for m in METRICS}, "frames": 5}
    table = metric_table({"a": row, "b": {**row, "rmse": None}})
    assert "| a | 0.1235 | 0.1235 | 0.1235 |" in table
    assert "| b | 0.1235 | 0.1235 | n/a |" in table and table.endswith("| 5 |\n")
    lines = gain_table({"b": {"abs_rel": 0.25, "rmse": math.nan}})
    assert lines[0] == "Relative gain against no_ttr (positive = better):"
    assert lines[-2].startswith("| b | +25.0 % | n/a | n/a |") and lines[-1] == ""
    assert gain_table({}) == [] and format_gain(None) == "n/a" and format_gain(-0.1) == "-10.0 %"


def test_per_frame_csv(tmp_path):
    path = tmp_path / "per_frame.csv"
    per_frame = {"no_ttr": {3: {"abs_rel": 0.5, "rmse": np.float32(2.0), "refined": False,
                                "reason": "window_failed"}},
                 "sfm_ttr": {3: {"abs_rel": None, "rmse": 1.25, "refined": True, "reason": ""},
                             4: {"abs_rel": 0.1, "rmse": 1.0, "refined": True}}}
    write_per_frame_csv(path, [(3, "0003"), (4, "0004")], per_frame)
    rows = list(csv.reader(open(path)))
    assert rows[0] == ["index", "name", "no_ttr_abs_rel", "no_ttr_rmse", "no_ttr_refined",
                       "no_ttr_reason", "sfm_ttr_abs_rel", "sfm_ttr_rmse", "sfm_ttr_refined",
                       "sfm_ttr_reason"]
    assert rows[1] == ["3", "0003", "0.500000", "2.000000", "0", "window_failed", "",
                       "1.250000", "1", ""]
    assert rows[2] == ["4", "0004", "", "", "0", "", "0.100000", "1.000000", "1", ""]
    write_per_frame_csv(path, [(4, "0004")], per_frame, columns=("abs_rel",))
    assert list(csv.reader(open(path))) == [["index", "name", "no_ttr_abs_rel",
                                             "sfm_ttr_abs_rel"], ["4", "0004", "", "0.100000"]]
