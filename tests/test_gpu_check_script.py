"""scripts/gpu_window_check.sh's CPU dry run (every part, tiny sizes) and the figures table of
sfm_ttr_ros/tools/gpu_check.py."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from sfm_ttr_ros.tools import gpu_check

REPO = Path(__file__).resolve().parents[1]


def test_the_cpu_dry_run_runs_every_part_and_prints_the_figures(tmp_path):
    env = dict(os.environ, OUT=str(tmp_path / "out"), GPU_CHECK_DATA=str(tmp_path / "data"),
               PYTHON=sys.executable, PYTHONPATH=str(REPO))
    r = subprocess.run(["bash", "scripts/gpu_window_check.sh", "--cpu-dry-run"], cwd=REPO,
                       env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    out = tmp_path / "out"
    parts = [json.loads(line) for line in (out / "parts.jsonl").read_text().splitlines()]
    ended = {p["part"]: p for p in parts if "rc" in p}
    started = {p["part"] for p in parts if "started" in p}
    assert started == set(ended) - {"holo"}  # each part wrote its start as it went
    assert all(p["rc"] == 0 for p in ended.values() if "skipped" not in p), parts
    assert sum(p["limit"] for p in parts if "started" in p) <= 450 - 20  # a margin
    profile = json.loads((out / "profile.json").read_text())
    assert [w["step_mode"] for w in profile["windows"]["windows"]] == ["eager"] * 3
    figures = (out / "figures.md").read_text()
    assert "| captured step ms (replay) |" in figures and "hololens_000" in figures
    assert "SfM s per stage, colmap SIFT | extract" in figures  # timing.json's stages
    assert "done in" in r.stdout


def test_the_figures_table_reads_a_check_summary():
    s = {"timing": {"timing": {"auto": {"steady_ms_per_step": 3.71, "max_rel_loss_diff": 2e-6},
                               "eager": {"steady_ms_per_step": 23.3}},
                    "sfm": {"colmap": {"timings": {"extract": 1.2, "match": 0.4}}}},
         "windows": {"windows": [{}, {}, {}], "capture_ms_first": 310.0,
                     "capture_ms_later_max": 0.2, "reserved_mb_after_2": 900.0,
                     "reserved_mb_after_3": 900.0},
         "holo_graph": {"sfm_ttr_live": {"latency_p95_s": 0.021,
                                         "last_frame_to_first_weights_s": 4.5}},
         "holo_eager": {"sfm_ttr_live": {"latency_p95_s": 0.035}}}
    rows = {a: b for a, b, _ in gpu_check.summary_rows(s)}
    assert rows["captured step ms (replay)"] == "3.71" and rows["eager step ms"] == "23.3"
    assert rows["capture ms, windows 2.., max"] == "0.2"
    assert rows["reserved MB after last window"] == "900"
    assert rows["live p95 ms while refining, hololens_000, graph"] == "21"
    assert rows["live p95 ms while refining, hololens_000, eager"] == "35"
    assert rows["live p95 ms while refining, drive, graph"] == "-"
    assert rows["SfM s per stage, colmap SIFT"] == "extract 1.20, match 0.40"
    assert gpu_check.summary_table(s)[0] == "| figure | value | target |"
