"""The benchmark's ``sfm_ttr_live`` mode: the node's live path, timed as a camera would feed it.

Frames arrive in real time at ``rate`` Hz (each is read from disk before its due time, so the
disk is not measured); each goes to :meth:`StreamRefiner.submit_live` (served at once by the
serving copy of the network) and to :meth:`StreamRefiner.submit` (the background windows that
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

from sfm_ttr_ros.core.outcomes import Unrefined
from sfm_ttr_ros.core.pipeline import SfmTTR, TTRConfig
from sfm_ttr_ros.core.stream.live import LiveOutput
from sfm_ttr_ros.core.stream.refiner import StreamRefiner
from sfm_ttr_ros.core.stream.windows import StreamSettings, WindowStats
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
    """Feed ``indices`` at ``rate`` Hz through an :class:`StreamRefiner`; evaluate live depth."""
    if not rate > 0:
        raise ValueError(f"rate must be positive, got {rate}")
    ttr = SfmTTR(model, copy.deepcopy(cfg))
    first = seq.frame(indices[0])
    forward = bare_forward_s(ttr.model, first.image)
    latencies: list[float] = []
    versions: list[int] = []
    windows = {"windows": 0, "windows_refined": 0, "windows_rolled_back": 0, "window_log": []}

    arrivals: list[float] = []  # time.monotonic() of the k-th frame fed
    timeline: list[dict] = []  # one row per window, see window_timeline
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
        windows["windows_rolled_back"] += int(ws.reason_key == Unrefined.ROLLED_BACK)
        # the stream numbers frames in arrival order: name k is the k-th frame fed
        windows["window_log"].append(window_record(ws, lambda n: indices[int(n)]))
        timeline.append(window_timeline(ws, arrivals, online.served_at.get(ws.index, {})))
        for k, v in ws.timings.items():
            run.timings[k] += float(v)
        if progress:
            what = "refined: now served" if ws.refined else f"not refined ({ws.reason})"
            progress(f"sfm_ttr_live: window {ws.index} {what}")

    online = StreamRefiner(ttr, copy.deepcopy(settings), on_live=on_live, on_window=on_window,
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
            arrivals.append(arrival)
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
    # windows whose weights were served while they refined but that the end of the feed cut
    # short (stop cancels the running window): their interim weights are on the time line too
    done = {row["window"] for row in timeline}
    for index, marks in sorted(online.served_at.items()):
        if index not in done and marks.get("names"):
            timeline.append(interim_timeline(index, marks, arrivals))
    run.seconds = fed_s
    lat = np.asarray(latencies, np.float64)
    c = online.counters()
    run.not_published.update({f"live_{k}": v for k, v in c["live"]["skipped"].items()})
    run.extra.update(windows)
    run.extra.update({
        "policy": cfg.weight_policy,
        "loss": ttr.config.refinement.loss,  # the parameter file's, as the node runs it
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
        **timeline_summary(timeline),
    })
    log.info("sfm_ttr_live: %d frames at %.1f Hz, latency p50/p95/max %.3f/%.3f/%.3f s, "
             "bare forward %.3f s", len(indices), rate, run.extra["latency_p50_s"],
             run.extra["latency_p95_s"], run.extra["latency_max_s"], forward)


def window_timeline(ws: WindowStats, arrivals: Sequence[float], served: dict) -> dict:
    """One window's time line in seconds after its LAST frame arrived (the stream names frames
    by arrival: name k is the k-th frame fed): when its first frame arrived
    (``first_frame_arrival``, negative), the worker took the window up (``closed``), SfM ended
    (``sfm_done``), the refinement ended (``refined``), its first interim weights or else its
    accepted weights were swapped into serving (``first_served``), its accepted weights were
    (``served``), its outputs were ready (``finished``); None for what did not happen.
    ``served``: the window's marks of :attr:`StreamRefiner.served_at`.
    ``since_feed_start`` = ``first_served`` counted from the first frame of the feed."""
    last = arrivals[int(ws.names[-1])] if ws.names else float("nan")
    t = ws.timings
    sfm_done = ws.started_at + t.get("predict_before", 0.0) + t.get("sfm", 0.0)
    refined = sfm_done + t.get("align", 0.0) + t.get("refine", 0.0)
    first = served.get("interim", served.get("final"))

    def since(v: float | None, origin: float) -> float | None:
        return None if v is None or not np.isfinite(v) else float(v - origin)

    return {"window": ws.index, "accepted": ws.refined, "reason_key": ws.reason_key or "",
            "first_frame_arrival": since(arrivals[int(ws.names[0])], last) if ws.names else None,
            "closed": since(ws.started_at, last),
            "sfm_done": since(sfm_done, last) if "sfm" in t else None,
            "refined": since(refined, last) if "refine" in t else None,
            "first_served": since(first, last), "served": since(served.get("final"), last),
            "finished": since(ws.finished_at, last),
            "since_feed_start": since(first, arrivals[0]) if arrivals else None}


def interim_timeline(index: int, marks: dict, arrivals: Sequence[float]) -> dict:
    """The time line row of a window that served interim weights but did not finish before the
    feed ended (``accepted`` None; only its first serving is known)."""
    names = marks["names"]
    last = arrivals[int(names[-1])]
    first = marks.get("interim")
    return {"window": index, "accepted": None, "reason_key": "cut_short",
            "first_frame_arrival": float(arrivals[int(names[0])] - last), "closed": None,
            "sfm_done": None, "refined": None,
            "first_served": None if first is None else float(first - last), "served": None,
            "finished": None,
            "since_feed_start": None if first is None else float(first - arrivals[0])}


def timeline_summary(timeline: Sequence[dict]) -> dict:
    """The time line's headline figures: from the feed's first frame to the first refined
    weights served (``first_weights_s``), and the medians from a window's last frame to its
    first served weights and to its accepted weights (over the windows that had them)."""
    first = [r["since_feed_start"] for r in timeline if r["since_feed_start"] is not None]
    to_any = [r["first_served"] for r in timeline if r["first_served"] is not None]
    to_final = [r["served"] for r in timeline if r["served"] is not None]

    def median(v: list[float]) -> float | None:
        return float(np.median(v)) if v else None

    return {"timeline": list(timeline), "first_weights_s": min(first) if first else None,
            "last_frame_to_first_weights_s": median(to_any),
            "last_frame_to_weights_s": median(to_final)}
