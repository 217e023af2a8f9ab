"""scripts/studies/predict_batch.py (docs/decisions.md, "Memory") on tiny images: one line per
batch size with a time and a non-negative RSS transient, each measured in its own process."""

import re
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "studies" / "predict_batch.py"


def test_predict_batch_reports_time_and_memory_per_batch_size():
    out = subprocess.run([sys.executable, str(SCRIPT), "--batches", "2", "1", "--frames", "3",
                          "--size", "64", "96", "--repeats", "1"], check=True,
                         capture_output=True, text=True, timeout=300).stdout
    rows = re.findall(r"predict_batch (\d+): ([0-9.]+) s, \+(-?\d+) MiB RSS", out)
    assert [r[0] for r in rows] == ["2", "1"], out
    assert all(float(s) > 0 and int(m) >= 0 for _, s, m in rows), out
