"""Abs rel along a drive for several benchmark runs (weight policies over a drive).

Reads the ``per_frame.csv`` of ``sfm-ttr benchmark`` runs made on the same frames, averages one
mode's abs rel over consecutive blocks of frames (``--block``, e.g. one window) and draws one
curve per run, plus the first-third / last-third means in a JSON next to the figure.

    .venv/bin/python scripts/studies/policy_curve.py --runs reset=bench/reset \\
        continue=bench/continue --mode sfm_ttr_online --block 15 \\
        --out bench/policies.png
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import cv2
import numpy as np

COLOURS = [(0, 0, 0), (200, 60, 0), (0, 140, 0), (0, 0, 220), (160, 0, 160), (0, 150, 200)]


def read_curve(run: Path, mode: str) -> tuple[np.ndarray, np.ndarray]:
    """(frame index, abs rel) of ``mode`` for every GT frame of a run."""
    idx, val = [], []
    with open(run / "per_frame.csv", newline="") as fh:
        for row in csv.DictReader(fh):
            v = row.get(f"{mode}_abs_rel", "")
            if v not in ("", "None", "nan"):
                idx.append(int(row["index"]))
                val.append(float(v))
    if not idx:
        raise SystemExit(f"{run}: no {mode}_abs_rel values in per_frame.csv")
    return np.asarray(idx), np.asarray(val)


def blocks(idx: np.ndarray, val: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    keys = (idx - idx.min()) // size
    xs = np.array([idx[keys == k].mean() for k in np.unique(keys)])
    ys = np.array([val[keys == k].mean() for k in np.unique(keys)])
    return xs, ys


def thirds(idx: np.ndarray, val: np.ndarray) -> dict[str, float]:
    lo, hi = idx.min(), idx.max() + 1
    cut1, cut2 = lo + (hi - lo) / 3, lo + 2 * (hi - lo) / 3
    return {"first_third": float(val[idx < cut1].mean()),
            "middle_third": float(val[(idx >= cut1) & (idx < cut2)].mean()),
            "last_third": float(val[idx >= cut2].mean()), "all": float(val.mean())}


def draw(curves: dict[str, tuple[np.ndarray, np.ndarray]], title: str,
         size=(900, 420)) -> np.ndarray:
    w, h = size
    m = 60
    img = np.full((h, w, 3), 255, np.uint8)
    xs = np.concatenate([c[0] for c in curves.values()])
    ys = np.concatenate([c[1] for c in curves.values()])
    x0, x1 = float(xs.min()), float(xs.max()) or 1.0
    y0, y1 = 0.0, float(ys.max()) * 1.1

    def px(x, y):
        return (int(m + (x - x0) / max(x1 - x0, 1e-9) * (w - 2 * m)),
                int(h - m - (y - y0) / max(y1 - y0, 1e-9) * (h - 2 * m)))

    cv2.rectangle(img, px(x0, y0), px(x1, y1), (160, 160, 160), 1)
    for k in range(6):
        y = y0 + (y1 - y0) * k / 5
        cv2.putText(img, f"{y:.3f}", (4, px(x0, y)[1] + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (80, 80, 80), 1, cv2.LINE_AA)
    cv2.putText(img, title, (m, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "frame", (w // 2, h - 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1,
                cv2.LINE_AA)
    for n, (name, (cx, cy)) in enumerate(curves.items()):
        colour = COLOURS[n % len(COLOURS)]
        pts = np.array([px(a, b) for a, b in zip(cx, cy, strict=True)], np.int32)
        cv2.polylines(img, [pts], False, colour, 2, cv2.LINE_AA)
        cv2.putText(img, name, (w - m - 150, m + 18 * n + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    colour, 1, cv2.LINE_AA)
    return img


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", nargs="+", required=True, metavar="NAME=DIR")
    ap.add_argument("--mode", default="sfm_ttr_online")
    ap.add_argument("--baseline", default="no_ttr", help="also draw this mode of the first run")
    ap.add_argument("--baseline-run", metavar="DIR", help="take --baseline from this run's "
                    "per_frame.csv instead (e.g. a no_ttr run beside live-only runs)")
    ap.add_argument("--block", type=int, default=15, help="frames per point (one window)")
    ap.add_argument("--out", required=True, help="figure path (.png); a .json is written beside")
    args = ap.parse_args()
    curves, summary = {}, {}
    for k, item in enumerate(args.runs):
        name, _, folder = item.partition("=")
        idx, val = read_curve(Path(folder), args.mode)
        curves[name] = blocks(idx, val, args.block)
        summary[name] = thirds(idx, val)
        if k == 0 and args.baseline:
            bidx, bval = read_curve(Path(args.baseline_run or folder), args.baseline)
            curves[args.baseline] = blocks(bidx, bval, args.block)
            summary[args.baseline] = thirds(bidx, bval)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), draw(curves, f"abs rel of {args.mode} per {args.block} frames"))
    out.with_suffix(".json").write_text(json.dumps(summary, indent=2) + "\n")
    for name, s in summary.items():
        print(f"{name:>12}: first third {s['first_third']:.4f}, last third "
              f"{s['last_third']:.4f}, all {s['all']:.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
