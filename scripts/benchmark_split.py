#!/usr/bin/env python3
"""A split on Ray against the same split in one process: wall time and metrics.

Generates N KITTI-size drives (``sfm-ttr generate --frames F --seed k``, each under its own
root: the generator's intrinsics differ with the seed), writes their split file, then runs

* sequential: ``sfm-ttr benchmark --split FILE --workers 1 --threads S`` (in process), and
* parallel:   ``sfm-ttr benchmark --split FILE --workers W --threads T`` (a local Ray instance),

both with ``--overwrite`` (nothing reused), timing each command end to end (process start to
exit: Ray's start and stop included). It writes a JSON with both wall times, their ratio against
the target, the per-sequence metrics of both runs and their largest difference, and the time
split of the sequential run (SfM, refinement, prediction, the rest) for the scale estimate of
docs/cluster.md.

    .venv/bin/python scripts/benchmark_split.py --out /tmp/split_bench \\
        --json docs/benchmarks/split/results.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DRIVE = "2011_09_26_drive_0001_sync"


def sfm_ttr(*argv: str, log: Path | None = None) -> float:
    """Run ``python -m sfm_ttr_ros ARGV``; its wall time in seconds."""
    cmd = [sys.executable, "-m", "sfm_ttr_ros", *argv]
    print("$", " ".join(cmd), flush=True)
    t0 = time.perf_counter()
    with open(log, "w") if log else open(os.devnull, "w") as fh:
        proc = subprocess.run(cmd, cwd=REPO, stdout=fh, stderr=subprocess.STDOUT)
    seconds = time.perf_counter() - t0
    if proc.returncode not in (0, 1):
        raise SystemExit(f"command failed ({proc.returncode}); log: {log}")
    return seconds


def generate(data: Path, drives: int, frames: int, width: int, height: int) -> Path:
    lines = []
    for k in range(1, drives + 1):
        root = data / f"seed{k}"
        if not (root / "raw" / "2011_09_26" / DRIVE / "image_02" / "data").is_dir():
            sfm_ttr("generate", "--kitti-raw", str(root / "raw"), "--kitti-gt", str(root / "gt"),
                    "--frames", str(frames), "--width", str(width), "--height", str(height),
                    "--seed", str(k))
        lines.append(f"kitti {DRIVE} raw=seed{k}/raw gt=seed{k}/gt name=seed{k}")
    split = data / "split.txt"
    split.write_text("\n".join(lines) + "\n")
    return split


def metric_difference(a: dict, b: dict) -> float:
    """Largest absolute difference of any metric of any mode of any sequence."""
    worst = 0.0
    rows_b = {q["id"]: q for q in b["sequences"]}
    for q in a["sequences"]:
        r = rows_b[q["id"]]
        for mode, m in q.get("modes", {}).items():
            for k in ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3"):
                x, y = m.get(k), r["modes"][mode].get(k)
                if x is not None and y is not None:
                    worst = max(worst, abs(x - y))
    return worst


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default="/tmp/sfm_ttr_split_bench", help="work folder")
    p.add_argument("--json", default=None, help="write the figures here too")
    p.add_argument("--drives", type=int, default=6)
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--width", type=int, default=1242)
    p.add_argument("--height", type=int, default=375)
    p.add_argument("--modes", nargs="+", default=["no_ttr", "sfm_ttr_online"])
    p.add_argument("--params-file", default=str(REPO / "params" / "kitti.yaml"))
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--parallel-threads", type=int, default=1)
    p.add_argument("--sequential-threads", type=int, default=2)
    p.add_argument("--target", type=float, default=0.75,
                   help="parallel / sequential wall time to reach (default 0.75)")
    args = p.parse_args()
    out = Path(args.out)
    data = out / "data"
    data.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    split = generate(data, args.drives, args.frames, args.width, args.height)
    gen_s = time.perf_counter() - t0
    common = ["benchmark", "--split", str(split), "--params-file", args.params_file,
              "--modes", *args.modes, "--overwrite", "--figure-frames", "0"]
    runs = {}
    for name, workers, threads in (("sequential", 1, args.sequential_threads),
                                   ("parallel", args.workers, args.parallel_threads)):
        argv = [*common, "--out", str(out / name), "--workers", str(workers),
                "--threads", str(threads)]
        wall = sfm_ttr(*argv, log=out / f"{name}.log")
        res = json.loads((out / name / "results.json").read_text())
        runs[name] = {"command": "sfm-ttr " + " ".join(argv), "workers": workers,
                      "threads": threads, "wall_s": wall, "engine_s": res["engine"]["seconds"],
                      "counts": res["counts"], "pooled": res["pooled"], "time": res["time"],
                      "sequences": {q["id"]: {"seconds": q.get("seconds"),
                                              "host": q.get("host"),
                                              "modes": q.get("modes")}
                                    for q in res["sequences"]}}
        print(f"{name}: {wall:.1f} s", flush=True)
        if res["counts"]["done"] != args.drives:
            raise SystemExit(f"{name}: {res['counts']} (see {out / name / 'results.md'})")
    seq_res = json.loads((out / "sequential" / "results.json").read_text())
    par_res = json.loads((out / "parallel" / "results.json").read_text())
    ratio = runs["parallel"]["wall_s"] / runs["sequential"]["wall_s"]
    commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True,
                            text=True).stdout.strip()
    doc = {
        "date": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"), "commit": commit,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "platform": platform.platform()},
        "drives": args.drives, "frames": args.frames, "size": [args.width, args.height],
        "modes": args.modes, "params_file": args.params_file, "generate_s": gen_s,
        "runs": runs, "ratio_parallel_over_sequential": ratio, "target": args.target,
        "target_met": ratio <= args.target,
        "max_metric_difference": metric_difference(seq_res, par_res),
    }
    text = json.dumps(doc, indent=2) + "\n"
    (out / "benchmark_split.json").write_text(text)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(text)
    print(f"sequential {runs['sequential']['wall_s']:.1f} s, parallel "
          f"{runs['parallel']['wall_s']:.1f} s: ratio {ratio:.3f} (target <= {args.target}); "
          f"largest metric difference {doc['max_metric_difference']:.3g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
