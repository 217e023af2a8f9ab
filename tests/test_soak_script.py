"""scripts/soak_node.py's report helpers (the soak itself runs for minutes: BENCHMARKS.md §6,
§7)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]


def load_soak():
    path = REPO_ROOT / "scripts" / "soak_node.py"
    spec = importlib.util.spec_from_file_location("soak_node", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["soak_node"] = module
    try:
        spec.loader.exec_module(module)
    finally:
        sys.modules.pop("soak_node", None)
    return module


def test_rss_maxima_per_bucket_show_growth_or_a_level():
    soak = load_soak()
    rss = [(0.0, 700.0), (10.0, 1050.0), (29.9, 1200.0), (30.0, 1190.0), (45.0, 1230.0),
           (60.0, 1100.0), (95.0, 900.0)]
    assert soak.rss_maxima(rss, 30.0) == [1200.0, 1230.0, 1100.0, 900.0]
    assert soak.rss_maxima([], 30.0) == []
