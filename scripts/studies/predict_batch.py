"""Time and memory of a window's predictions by ``ttr.predict_batch`` (the node's memory).

A window predicts its frames twice (before and after refinement) through
:meth:`~sfm_ttr_ros.core.pipeline.SfmTTR.predict`, ``predict_batch`` frames per forward pass.
For each batch size this runs, in a fresh process (so that the high-water mark is its own), the
default network over ``--frames`` random images of ``--size`` in batches of that size with
``--threads`` torch threads, and prints the best of ``--repeats`` times and the RSS high-water
mark above the RSS before the first pass (the transient a window's prediction adds).

    .venv/bin/python scripts/studies/predict_batch.py --threads 1 --batches 8 4 2 1
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time


def _status(key: str) -> int:
    with open("/proc/self/status", encoding="ascii") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1]) // 1024
    raise KeyError(key)


def measure(batch: int, frames: int, size: tuple[int, int], threads: int, repeats: int,
            channels_last: bool) -> dict:
    """One batch size, in this process: {seconds, transient_mib}."""
    import numpy as np
    import torch

    from sfm_ttr_ros.core.models.registry import ModelConfig, build_model

    torch.set_num_threads(threads)
    model = build_model(ModelConfig(channels_last=channels_last))
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 255, (*size, 3), dtype=np.uint8) for _ in range(frames)]
    model.predict(images[:1])  # one-time costs out of the figures
    before = _status("VmRSS")
    with open("/proc/self/clear_refs", "w", encoding="ascii") as fh:
        fh.write("5")  # resets VmHWM to the current RSS
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        for i in range(0, frames, batch):
            model.predict(images[i:i + batch])
        best = min(best, time.perf_counter() - t0)
    return {"batch": batch, "seconds": round(best, 3), "transient_mib": _status("VmHWM") - before}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[8, 4, 2, 1])
    ap.add_argument("--frames", type=int, default=15, help="a window's frames")
    ap.add_argument("--size", type=int, nargs=2, default=(375, 1242), metavar=("H", "W"))
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-channels-last", dest="channels_last", action="store_false")
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)  # the child process
    args = ap.parse_args()
    if args.one:
        print(json.dumps(measure(args.one, args.frames, tuple(args.size), args.threads,
                                 args.repeats, args.channels_last)))
        return 0
    print(f"{args.frames} frames {args.size[1]}x{args.size[0]}, {args.threads} thread(s)")
    for b in args.batches:
        cmd = [sys.executable, __file__, "--one", str(b), "--frames", str(args.frames),
               "--size", *map(str, args.size), "--threads", str(args.threads),
               "--repeats", str(args.repeats)] + ([] if args.channels_last
                                                  else ["--no-channels-last"])
        row = json.loads(subprocess.run(cmd, check=True, capture_output=True,
                                        text=True).stdout.strip().splitlines()[-1])
        print(f"predict_batch {b}: {row['seconds']:.3f} s, +{row['transient_mib']} MiB RSS")
    return 0


if __name__ == "__main__":
    sys.exit(main())
