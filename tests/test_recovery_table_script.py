"""scripts/studies/recovery_table.py (BENCHMARKS.md §9): the blocks around each bad segment, their
means over a group's runs, and the ratio to the network alone on the same frames."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "studies" / "recovery_table.py"


def write_run(path: Path, mode: str, values: dict[int, float]) -> Path:
    path.mkdir(parents=True)
    rows = [f"index,name,{mode}_abs_rel,{mode}_rmse,{mode}_refined,{mode}_reason"]
    rows += [f"{i},{i:010d},{v:.6f},1.0,1," for i, v in sorted(values.items())]
    (path / "per_frame.csv").write_text("\n".join(rows) + "\n")
    return path


def test_blocks_around_each_bad_segment(tmp_path):
    labels = ["drive"] * 10 + ["truck"] * 5 + ["drive"] * 12
    seg = tmp_path / "segments.txt"
    seg.write_text("".join(f"{i} {lab}\n" for i, lab in enumerate(labels)))
    # live: 0.1 before, 0.4 on the truck, 0.3 then 0.2 after; frame 3 has no GT
    live = {i: 0.1 for i in range(10) if i != 3}
    live |= {i: 0.4 for i in range(10, 15)} | {i: 0.3 for i in range(15, 20)}
    live |= {i: 0.2 for i in range(20, 27)}
    live2 = {i: v + 0.1 for i, v in live.items()}
    nottr = {i: 0.5 for i in range(27)}
    run1 = write_run(tmp_path / "r1", "sfm_ttr_live", live)
    run2 = write_run(tmp_path / "r2", "sfm_ttr_live", live2)
    base = write_run(tmp_path / "b", "no_ttr", nottr)
    out = tmp_path / "rec.json"
    subprocess.run([sys.executable, str(SCRIPT), "--segments", str(seg), "--run", f"truck={run1}",
                    "--run", f"truck={run2}", "--no-ttr", f"truck={base}", "--bad", "truck",
                    "--window", "5", "--after", "3", "--out", str(out)],
                   check=True, capture_output=True, text=True, timeout=120)
    res = json.loads(out.read_text())
    (segment,) = res["segments"]
    assert segment["kind"] == "truck" and segment["frames"] == [10, 14]
    blocks = {b["block"]: b for b in segment["blocks"]}
    assert list(blocks) == ["before", "segment", "after_1", "after_2", "after_3"]
    assert blocks["before"]["frames"] == [5, 9]
    assert blocks["after_3"]["frames"] == [25, 26]  # cut at the drive's end
    g = blocks["after_1"]["groups"]["truck"]
    assert g["runs"] == pytest.approx([0.3, 0.4]) and g["mean"] == pytest.approx(0.35)
    assert g["ratio_to_no_ttr"] == pytest.approx([0.6, 0.8])
    assert blocks["before"]["groups"]["truck"]["runs"] == pytest.approx([0.1, 0.2])
    assert "| truck 10–14 | after_2 | 20–24 | 0.200, 0.300 | 0.40, 0.60 |" in \
        out.with_suffix(".md").read_text()
