"""Live abs rel around a drive's bad segments (recovery within two windows).

Reads ``per_frame.csv`` of ``sfm-ttr benchmark`` runs on generated scenario drives and their
``segments.txt`` labels, and for every segment of a ``--bad`` kind lists one mode's mean abs rel
over the window of frames before the segment, over the segment, and over each of the windows
after it (``--window`` frames each). Runs are grouped (``--run GROUP=DIR``, several runs per
group; e.g. the drive with the truck, and the same drive without it made with ``sfm-ttr generate
--replace truck=drive``); with ``--no-ttr GROUP=DIR`` (a ``--modes no_ttr`` run of the group's
drive) every block is also given as a ratio to the network alone on the same frames, which
takes the road's own difficulty out of "back to its level before".

    .venv/bin/python scripts/studies/recovery_table.py \\
        --segments /tmp/hard/raw/.../image_02/segments.txt \\
        --run truck=b/live_hard_1 --run truck=b/live_hard_2 --no-ttr truck=b/nottr_hard \\
        --run no_truck=b/live_hard_nt_1 --no-ttr no_truck=b/nottr_hard_nt \\
        --bad turn truck --out recovery.json
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts" / "studies"))
from policy_curve import read_curve  # noqa: E402

from sfm_ttr_ros.core.errors import InputError  # noqa: E402
from sfm_ttr_ros.data.kitti import read_segments  # noqa: E402


def read_abs_rel(run: Path, mode: str) -> dict[int, float]:
    """Frame index -> ``mode``'s abs rel for every GT frame of a run (its ``per_frame.csv``)."""
    idx, val = read_curve(run, mode)
    return dict(zip(idx.tolist(), val.tolist(), strict=True))


def bad_spans(labels: list[str], kinds: set[str]) -> list[tuple[str, int, int]]:
    """(kind, first frame, last frame + 1) of every run of consecutive frames of a bad kind."""
    spans, start = [], 0
    for i in range(1, len(labels) + 1):
        if i == len(labels) or labels[i] != labels[start]:
            if labels[start] in kinds:
                spans.append((labels[start], start, i))
            start = i
    return spans


def block_mean(values: dict[int, float], lo: int, hi: int) -> float | None:
    got = [values[i] for i in range(lo, hi) if i in values]
    return float(np.mean(got)) if got else None


def span_blocks(start: int, end: int, window: int, after: int,
                n_frames: int) -> list[tuple[str, int, int]]:
    """The blocks of one bad span: the window before it, the span, and ``after`` windows."""
    blocks = [("before", max(0, start - window), start), ("segment", start, end)]
    for k in range(after):
        lo = end + k * window
        if lo >= n_frames:
            break
        blocks.append((f"after_{k + 1}", lo, min(n_frames, lo + window)))
    return blocks


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--segments", type=Path, required=True, help="segments.txt of the drive")
    ap.add_argument("--run", action="append", required=True, metavar="GROUP=DIR")
    ap.add_argument("--no-ttr", action="append", default=[], metavar="GROUP=DIR")
    ap.add_argument("--mode", default="sfm_ttr_live")
    ap.add_argument("--bad", nargs="+", default=["turn", "truck"], help="segment kinds")
    ap.add_argument("--window", type=int, default=15)
    ap.add_argument("--after", type=int, default=3, help="windows after each bad segment")
    ap.add_argument("--out", type=Path, required=True, help="JSON; a .md table beside it")
    args = ap.parse_args(argv)

    def pairs(items: list[str]) -> list[tuple[str, Path]]:
        out = []
        for item in items:
            group, sep, path = item.partition("=")
            if not sep:
                raise SystemExit(f"expected GROUP=DIR, got {item!r}")
            out.append((group, Path(path)))
        return out

    try:
        labels = read_segments(args.segments)
    except InputError as exc:
        raise SystemExit(str(exc)) from None
    runs: dict[str, list[dict[int, float]]] = defaultdict(list)
    for group, path in pairs(args.run):
        runs[group].append(read_abs_rel(path, args.mode))
    base = {group: read_abs_rel(path, "no_ttr") for group, path in pairs(args.no_ttr)}

    result: dict = {"mode": args.mode, "window": args.window, "segments": []}
    lines = [f"| {args.mode} | segment | block | frames | "
             + " | ".join(f"{g} (runs)" for g in runs)
             + (" | " + " | ".join(f"{g} / no_ttr" for g in runs if g in base) if base else "")
             + " |"]
    lines.append("| --- " * (4 + len(runs) + sum(g in base for g in runs)) + "|")
    for kind, start, end in bad_spans(labels, set(args.bad)):
        entry = {"kind": kind, "frames": [start, end - 1], "blocks": []}
        for name, lo, hi in span_blocks(start, end, args.window, args.after, len(labels)):
            block = {"block": name, "frames": [lo, hi - 1], "groups": {}}
            cells, ratios = [], []
            for group, group_runs in runs.items():
                means = [block_mean(r, lo, hi) for r in group_runs]
                means = [m for m in means if m is not None]
                ref = block_mean(base[group], lo, hi) if group in base else None
                block["groups"][group] = {
                    "runs": means, "mean": float(np.mean(means)) if means else None,
                    "no_ttr": ref,
                    "ratio_to_no_ttr": [m / ref for m in means] if ref else None}
                cells.append(", ".join(f"{m:.3f}" for m in means) or "n/a")
                if group in base:
                    ratios.append(", ".join(f"{m / ref:.2f}" for m in means) if ref else "n/a")
            entry["blocks"].append(block)
            lines.append(f"| | {kind} {start}–{end - 1} | {name} | {lo}–{hi - 1} | "
                         + " | ".join(cells) + (" | " + " | ".join(ratios) if ratios else "")
                         + " |")
        result["segments"].append(entry)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    args.out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
