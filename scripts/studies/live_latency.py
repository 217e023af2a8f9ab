"""Live-serving latency with and without the background windows (where live latency goes).

Feeds the first ``--frames`` frames of a KITTI-layout drive at ``--rate`` Hz into an
:class:`~sfm_ttr_ros.core.stream.refiner.StreamRefiner` built from a parameter file, either to the
live server only (``--mode live``) or to the live server and the windows, as the node does
(``--mode both``), and prints the latency percentiles, the live skips and the windows done.
``--mode windows`` feeds the windows only (the background worker, no live serving) and ``--mode
main`` steps the same windows in the calling thread (as ``sfm_ttr_online`` does): both print each
window's stage timings, which tells what the worker thread itself costs.

    .venv/bin/python scripts/studies/live_latency.py --kitti-raw /tmp/d/raw --drive \\
        2011_09_26_drive_0001_sync --mode both --set stream.worker_nice=10
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from sfm_ttr_ros.core import params as schema
from sfm_ttr_ros.core.models import build_model
from sfm_ttr_ros.core.pipeline import SfmTTR
from sfm_ttr_ros.core.stream.refiner import StreamRefiner
from sfm_ttr_ros.data.sequence import open_kitti
from sfm_ttr_ros.ros.names import NODE_NAME


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kitti-raw", required=True)
    ap.add_argument("--drive", required=True)
    ap.add_argument("--mode", choices=("live", "both", "windows", "main"), default="both")
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--params-file", default="params/kitti.yaml")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    ap.add_argument("--torch-threads", type=int, default=0)
    args = ap.parse_args()
    if args.torch_threads:
        torch.set_num_threads(args.torch_threads)
    values = schema.read_params_file(args.params_file, NODE_NAME)
    values.update(schema.parse_overrides(args.set))
    s = schema.build(values)
    seq = open_kitti(args.kitti_raw, args.drive)
    ttr = SfmTTR(build_model(s.model), s.ttr)
    latencies: list[float] = []
    timings: list[dict] = []
    online = StreamRefiner(ttr, s.stream, on_live=lambda o: latencies.append(o.latency_s),
                           on_window=lambda ws: timings.append(ws.timings))
    frames = [seq.frame(i) for i in range(min(args.frames, len(seq)))]
    if args.mode == "main":
        for f in frames:  # each frame processed as it comes, as sfm_ttr_online does
            online.stream.submit(f, seq.intrinsics)
            online.stream.process_available()
        ttr.close()
        return _print_windows(args.mode, timings)
    online.start()
    t0 = time.monotonic()
    try:
        for k, f in enumerate(frames):
            delay = t0 + k / args.rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            if args.mode != "windows":
                online.submit_live(f)
            if args.mode != "live":
                online.submit(f, seq.intrinsics)
        online.live.drain(30)
        if args.mode == "windows":
            while online.stream.pending() and time.monotonic() - t0 < 600:
                time.sleep(0.2)
    finally:
        online.stop(None)
        ttr.close()
    if args.mode == "windows":
        return _print_windows(args.mode, timings)
    lat = np.asarray(latencies)
    c = online.counters()
    print(f"{args.mode}: {len(lat)}/{len(frames)} served, latency p50 "
          f"{np.percentile(lat, 50):.3f} s, p95 {np.percentile(lat, 95):.3f} s, max "
          f"{lat.max():.3f} s; live skipped {c['live']['skipped']}; windows done "
          f"{len(online.stream.windows)}; stream pending {c['pending']}")
    return 0


def _print_windows(mode: str, timings: list[dict]) -> int:
    for k, t in enumerate(timings):
        print(f"{mode}: window {k}: " + ", ".join(f"{n} {v:.2f} s" for n, v in t.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
