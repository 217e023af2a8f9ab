"""The benchmark's ``sfm_ttr_live`` mode: the node's live path, timed as a camera would feed it.

Frames arrive in real time at ``rate`` Hz (each is read from disk before its due time, so the
disk is not measured); each goes to :meth:`OnlineRefiner.submit_live` (served at once by the
serving copy of the network) and to :meth:`OnlineRefiner.submit` (the background windows that
keep refining it), exactly as the node's image callback does. The depth evaluated for a frame
is the one served live; its latency is from its arrival to the moment its depth is ready (the
node then adds the message conversion, about 2-5 ms at KITTI size: BENCHMARKS.md).
"""

from __future__ import annotations

import copy
import time
from collections import deque
from collections.abc import Sequence

import numpy as np

from sfm_ttr_ros.core.live import LiveOutput
from sfm_ttr_ros.core.online import OnlineRefiner
from sfm_ttr_ros.core.pipeline import SfmTTR, TTRConfig
from sfm_ttr_ros.core.stream import StreamSettings, WindowStats
from sfm_ttr_ros.data.sequence import ImageSequence
from sfm_ttr_ros.tools.benchmark.runners import ModeRun, log, window_record

#: Frames timed for the network's bare forward pass before the run starts.
FORWARD_PROBES = 10
#: The feeder evaluates served depths only while more than this is left before the next frame.
EVAL_SLACK_S = 0.03
#: Served depths held for evaluation after the feed; beyond this many bytes the feeder
#: evaluates between frames (GT read + metrics, ~15 ms a frame of CPU the node would not spend).
DEFER_EVAL_BYTES = 1 << 30


def bare_forward_s(model, image: np.ndarray, probes: int = FORWARD_PROBES) -> float:
    """Median seconds of one prediction (resize, network, resize back) of ``image``."""
    model.predict([image])  # warm-up
    times = []
    for _ in range(probes):
        t0 = time.perf_counter()
        model.predict([image])
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def run_live(run: ModeRun, seq: ImageSequence, indices: Sequence[int], model,
             cfg: TTRConfig, settings: StreamSettings, progress, rate: float = 10.0) -> None:
    """Feed ``indices`` at ``rate`` Hz through an :class:`OnlineRefiner`; evaluate live depth."""
    if not rate > 0:
        raise ValueError(f"rate must be positive, got {rate}")
    ttr = SfmTTR(model, copy.deepcopy(cfg))
    first = seq.frame(indices[0])
    forward = bare_forward_s(ttr.model, first.image)
    latencies: list[float] = []
    versions: list[int] = []
    windows = {"windows": 0, "windows_refined": 0, "windows_rolled_back": 0, "window_log": []}

    served: deque[LiveOutput] = deque()  # evaluated by the feeder after the feed
    held = [0]  # bytes of the served depths waiting in ``served``

    def on_live(out: LiveOutput) -> None:  # the live thread: hand over only
        latencies.append(out.latency_s)
        versions.append(out.version)
        held[0] += out.depth.nbytes
        served.append(out)

    def evaluate(until: float | None = None) -> None:
        """Evaluate served depths (GT read + metrics, ~15 ms each): all of them after the
        feed (``until`` None); during it only while more than DEFER_EVAL_BYTES are held, and
        while time allows: the node spends no CPU on evaluation, the feeder should not either."""
        while served and (until is None or (held[0] > DEFER_EVAL_BYTES
                                            and until - time.monotonic() > EVAL_SLACK_S)):
            out = served.popleft()
            held[0] -= out.depth.nbytes
            run.add(out.frame.index, out.depth, out.version > 0,
                    "" if out.version > 0 else "start_up_weights")

    def on_window(ws: WindowStats) -> None:
        windows["windows"] += 1
        windows["windows_refined"] += int(ws.refined)
        windows["windows_rolled_back"] += int(ws.reason_key == "rolled_back")
        # the stream numbers frames in arrival order: name k is the k-th frame fed
        windows["window_log"].append(window_record(ws, lambda n: indices[int(n)]))
        for k, v in ws.timings.items():
            run.timings[k] += float(v)
        if progress:
            what = "refined: now served" if ws.refined else f"not refined ({ws.reason})"
            progress(f"sfm_ttr_live: window {ws.index} {what}")

    online = OnlineRefiner(ttr, copy.deepcopy(settings), on_live=on_live, on_window=on_window,
                           logger=log)
    online.start()
    t_start = time.monotonic()
    try:
        for k, i in enumerate(indices):
            frame = seq.frame(i)  # read before its due time
            due = t_start + k / rate
            evaluate(until=due)
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            arrival = time.monotonic()
            online.submit_live(frame, arrival)
            online.submit(frame, seq.intrinsics)
            if progress and k % 100 == 99:
                progress(f"sfm_ttr_live: {k + 1}/{len(indices)} frames fed, "
                         f"{online.serving.version} = served weights' version")
        online.live.drain(timeout=30.0)
        fed_s = time.monotonic() - t_start
    finally:
        online.stop(timeout=None)  # wait: pycolmap must be out of the workspace before close
        ttr.close()
    evaluate()
    run.seconds = fed_s
    lat = np.asarray(latencies, np.float64)
    c = online.counters()
    run.not_published.update({f"live_{k}": v for k, v in c["live"]["skipped"].items()})
    run.extra.update(windows)
    run.extra.update({
        "policy": cfg.weight_policy,
        "loss": cfg.refinement.loss,  # the parameter file's, as the node runs it
        "rate_hz": rate,
        "frames": len(indices),
        "latency_p50_s": float(np.percentile(lat, 50)) if lat.size else float("nan"),
        "latency_p95_s": float(np.percentile(lat, 95)) if lat.size else float("nan"),
        "latency_max_s": float(lat.max()) if lat.size else float("nan"),
        "forward_s": forward,
        "warm_up_s": online.warm_up_s,
        "live_counters": c["live"],
        "stream_counters": {k: v for k, v in c.items() if k != "live"},
        "served_versions": sorted(set(versions)),
    })
    log.info("sfm_ttr_live: %d frames at %.1f Hz, latency p50/p95/max %.3f/%.3f/%.3f s, "
             "bare forward %.3f s", len(indices), rate, run.extra["latency_p50_s"],
             run.extra["latency_p95_s"], run.extra["latency_max_s"], forward)
