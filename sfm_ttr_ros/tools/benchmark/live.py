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
from sfm_ttr_ros.core.stream.window_runner import StreamSettings, WindowStats
from sfm_ttr_ros.data.sequence import ImageSequence
from sfm_ttr_ros.tools.benchmark.runners import (
    ModeRun,
    feed_odometry,
    feed_stamp,
    log,
    window_record,
)

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
    forward = bare_forward_s(ttr.model, seq.frame(indices[0]).image)
    live = _LiveRun(run, indices, progress)
    feed_odometry(ttr, seq, indices, rate)
    online = StreamRefiner(ttr, copy.deepcopy(settings), on_live=live.on_live,
                           on_window=live.on_window, logger=log)
    live.online = online
    online.start()
    try:
        fed_s = _feed(seq, indices, rate, live, progress)
    finally:
        online.stop(timeout=None)  # wait: pycolmap must be out of the workspace before close
        ttr.close()
    live.evaluate()
    live.add_cut_short_windows()
    run.seconds = fed_s
    _record(live, ttr.config.refinement.loss, cfg.weight_policy, rate, forward)
    run.extra["metric"] = ttr.metric_status().values()


class _LiveRun:
    """What one ``sfm_ttr_live`` run collects: the live thread's served depths (evaluated by
    the feeder), the window thread's windows and their time line."""

    def __init__(self, run: ModeRun, indices: Sequence[int], progress) -> None:
        self.run, self.indices, self.progress = run, indices, progress
        self.online: StreamRefiner | None = None  # set before it starts
        self.latencies: list[float] = []
        self.versions: list[int] = []
        self.windows = {"windows": 0, "windows_refined": 0, "windows_rolled_back": 0,
                        "window_log": []}
        self.arrivals: list[float] = []  # time.monotonic() of the k-th frame fed
        self.timeline: list[dict] = []  # one row per window, see window_timeline
        self.served: deque[LiveOutput] = deque()  # evaluated by the feeder after the feed
        self.held = 0  # bytes of the served depths waiting in ``served``

    def on_live(self, out: LiveOutput) -> None:  # the live thread: hand over only
        self.latencies.append(out.latency_s)
        self.versions.append(out.version)
        self.held += out.depth.nbytes
        self.served.append(out)

    def evaluate(self, until: float | None = None) -> None:
        """Evaluate served depths (GT read + metrics, ~15 ms each): all of them after the
        feed (``until`` None); during it only while more than DEFER_EVAL_BYTES are held, and
        while time allows: the node spends no CPU on evaluation, the feeder should not either."""
        while self.served and (until is None or (self.held > DEFER_EVAL_BYTES
                                                 and until - time.monotonic() > EVAL_SLACK_S)):
            out = self.served.popleft()
            self.held -= out.depth.nbytes
            self.run.add(out.frame.index, out.depth, out.version > 0,
                         "" if out.version > 0 else "start_up_weights")

    def on_window(self, ws: WindowStats) -> None:
        windows = self.windows
        windows["windows"] += 1
        windows["windows_refined"] += int(ws.refined)
        windows["windows_rolled_back"] += int(ws.reason_key == Unrefined.ROLLED_BACK)
        # the stream numbers frames in arrival order: name k is the k-th frame fed
        windows["window_log"].append(window_record(ws, lambda n: self.indices[int(n)]))
        self.timeline.append(window_timeline(ws, self.arrivals,
                                             self.online.served_at.get(ws.index, {})))
        for k, v in ws.timings.items():
            self.run.timings[k] += float(v)
        if self.progress:
            what = "refined: now served" if ws.refined else f"not refined ({ws.reason})"
            self.progress(f"sfm_ttr_live: window {ws.index} {what}")

    def add_cut_short_windows(self) -> None:
        """Windows whose weights were served while they refined but that the end of the feed
        cut short (stop cancels the running window): their interim weights are on the time
        line too."""
        done = {row["window"] for row in self.timeline}
        for index, marks in sorted(self.online.served_at.items()):
            if index not in done and marks.get("names"):
                self.timeline.append(interim_timeline(index, marks, self.arrivals))


def _feed(seq: ImageSequence, indices: Sequence[int], rate: float, live: _LiveRun,
          progress) -> float:
    """Each frame at its due time to the live output and to the windows, as the node's image
    callback does; returns the seconds from the first frame until every live frame is out."""
    online = live.online
    t_start = time.monotonic()
    for k, i in enumerate(indices):
        frame = seq.frame(i)  # read before its due time
        frame.stamp = feed_stamp(seq, indices, k, rate)  # a camera at the feed rate
        due = t_start + k / rate
        live.evaluate(until=due)
        delay = due - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        arrival = time.monotonic()
        live.arrivals.append(arrival)
        online.submit_live(frame, arrival)
        online.submit(frame, seq.intrinsics)
        if progress and k % 100 == 99:
            progress(f"sfm_ttr_live: {k + 1}/{len(indices)} frames fed, "
                     f"{online.serving.version} = served weights' version")
    online.live.drain(timeout=30.0)
    return time.monotonic() - t_start


def _record(live: _LiveRun, loss: str, policy: str, rate: float, forward: float) -> None:
    """The run's live figures: skipped frames, windows, latency, counters, time line."""
    run, online = live.run, live.online
    lat = np.asarray(live.latencies, np.float64)
    c = online.counters()
    run.not_published.update({f"live_{k}": v for k, v in c["live"]["skipped"].items()})
    run.extra.update(live.windows)
    run.extra.update({
        "policy": policy,
        "loss": loss,  # the parameter file's, as the node runs it
        "rate_hz": rate,
        "frames": len(live.indices),
        "latency_p50_s": float(np.percentile(lat, 50)) if lat.size else float("nan"),
        "latency_p95_s": float(np.percentile(lat, 95)) if lat.size else float("nan"),
        "latency_max_s": float(lat.max()) if lat.size else float("nan"),
        "forward_s": forward,
        "warm_up_s": online.warm_up_s,
        "live_counters": c["live"],
        "stream_counters": {k: v for k, v in c.items() if k != "live"},
        "served_versions": sorted(set(live.versions)),
        **timeline_summary(live.timeline),
    })
    log.info("sfm_ttr_live: %d frames at %.1f Hz, latency p50/p95/max %.3f/%.3f/%.3f s, "
             "bare forward %.3f s", len(live.indices), rate, run.extra["latency_p50_s"],
             run.extra["latency_p95_s"], run.extra["latency_max_s"], forward)


def window_timeline(ws: WindowStats, arrivals: Sequence[float], served: dict) -> dict:
    """One window's time line in seconds after its LAST frame arrived (the stream names frames
    by arrival: name k is the k-th frame fed): when its first frame arrived
    (``first_frame_arrival``, negative), the worker took the window up (``closed``), SfM ended
    (``sfm_done``), the refinement ended (``refined``), its first interim weights or else its
    accepted weights were swapped into serving (``first_served``), its accepted weights were
    (``served``), its outputs were ready (``finished``); None for what did not happen.
    ``first_served`` is the window's "last frame -> first weights"; ``sfm_mapping`` how its
    SfM was mapped under ``sfm.mode`` streaming ("continued" / "fresh"; "" batch).
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
            "sfm_mapping": ws.sfm_mapping,
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
    return {"window": index, "accepted": None, "reason_key": "cut_short", "sfm_mapping": "",
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
