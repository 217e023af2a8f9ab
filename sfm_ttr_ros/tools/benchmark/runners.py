"""The benchmark's modes over the same frames (see :mod:`sfm_ttr_ros.tools.benchmark`):
``no_ttr`` (the network alone), ``<method>_online`` (the node's stream, no ROS transport) and
``<method>_offline`` (one window over the whole sequence, or chunks) for the three refinement
objectives (``refinement.loss``): ``sfm_ttr`` (Eq. 5), ``ph_ttr`` (photometric TTR
with the SfM poses) and ``hybrid``; and the per-mode bookkeeping (:class:`ModeRun`) that
evaluates each published depth, overall and by depth band."""

from __future__ import annotations

import copy
import dataclasses
import logging
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.evaluation import METRICS, EvalConfig, Evaluator, mean_over_frames
from sfm_ttr_ros.core.frames import Frame
from sfm_ttr_ros.core.metric.scale import in_metres
from sfm_ttr_ros.core.outcomes import Unrefined
from sfm_ttr_ros.core.pipeline import SfmTTR, TTRConfig
from sfm_ttr_ros.core.stream.records import FramePose
from sfm_ttr_ros.core.stream.window_runner import (
    FrameOutput,
    StreamSettings,
    WindowRunner,
    WindowStats,
)
from sfm_ttr_ros.data.sequence import ImageSequence
from sfm_ttr_ros.tools.benchmark.bands import DepthBands
from sfm_ttr_ros.tools.benchmark.path import path_report

log = logging.getLogger("sfm_ttr_ros.tools.benchmark")

#: What the node gives: its windows with the parameter file's objective and weight policy as
#: they are (the ``<method>_*`` modes override the objective; this one overrides nothing).
NODE_MODE = "node_online"
#: What ``sfm-ttr benchmark`` runs when no --modes are given: the network alone, what the node
#: gives, and the paper's Eq. (5) online (the node's windows) and offline (one window).
DEFAULT_MODES = ("no_ttr", NODE_MODE, "sfm_ttr_online", "sfm_ttr_offline")
#: Method prefix of a windowed mode → the ``refinement.loss`` it runs with, whatever the
#: parameter file says (the same windows and settings, only the objective differs).
METHOD_LOSS = {"sfm_ttr": "sfm", "ph_ttr": "photometric", "hybrid": "hybrid"}
#: The photometric (Ph-TTR) and hybrid twins of the SfM-TTR modes.
LOSS_MODES = ("ph_ttr_online", "hybrid_online", "ph_ttr_offline", "hybrid_offline")
#: Every mode (``sfm_ttr_live`` runs in real time at --rate: tools/benchmark/live.py).
MODES = (*DEFAULT_MODES, "sfm_ttr_live", *LOSS_MODES)
#: The top-level stages of a window (WindowResult.timings also holds ``sfm_*`` sub-stages).
STAGES = ("predict_before", "sfm", "align", "refine", "predict_after")


@dataclasses.dataclass
class StreamTaps:
    """What a caller measures around the node's stream in :func:`run_online` (the speed
    measurement, :mod:`.speed`), none of it changing what the stream does: the window pipeline
    it builds (``make_ttr``), sinks the stream calls inside its push (``on_output``,
    ``on_window``), the node's subscription callback timed with each push (``prepare`` outside
    the clock returns what ``receive`` takes inside it), ``attach`` once the stream exists (before
    the warm-up), and ``pushed`` with the seconds of every push and of the final flush."""

    make_ttr: Callable[[Any, TTRConfig], SfmTTR] = SfmTTR
    on_output: Callable[[FrameOutput], None] | None = None
    on_window: Callable[[WindowStats], None] | None = None
    prepare: Callable[[Frame], Any] | None = None
    receive: Callable[[Frame, Any], None] | None = None
    attach: Callable[[WindowRunner, SfmTTR], None] | None = None
    pushed: Callable[[float], None] | None = None


class ModeRun:
    """Evaluates one mode's depths frame by frame and keeps what the outputs need."""

    def __init__(self, mode: str, seq: ImageSequence, indices: Sequence[int],
                 figure_indices: Sequence[int], eval_config: EvalConfig,
                 depth_dir: Path | None):
        self.mode = mode
        self.seq = seq
        self.names = seq.names
        self.expected = set(indices)
        self.figure_indices = set(figure_indices)
        self.evaluator = Evaluator(eval_config)
        self.bands = DepthBands(eval_config)
        self.per_frame: dict[int, dict[str, Any]] = {}
        self.figure_depths: dict[int, np.ndarray] = {}
        self.refined = 0
        self.reasons: dict[str, int] = defaultdict(int)
        self.seen: set[int] = set()
        self.depth_dir = depth_dir
        self.seconds = 0.0
        self.timings: dict[str, float] = defaultdict(float)
        self.extra: dict[str, Any] = {}
        #: Frames the mode itself skipped and counted by reason (the live server's queue
        #: overflow, ...): not published, so not evaluated, but not lost either.
        self.not_published: Counter[str] = Counter()
        if depth_dir is not None:
            depth_dir.mkdir(parents=True, exist_ok=True)

    def add(self, index: int, depth: np.ndarray, refined: bool, reason: str = "") -> None:
        if index in self.seen or index not in self.expected:
            log.error("%s: frame %d published twice or not expected: ignored", self.mode, index)
            return
        self.seen.add(index)
        name = self.names[index]
        if refined:
            self.refined += 1
        else:
            self.reasons[reason or "unrefined"] += 1
        if self.depth_dir is not None:
            np.save(self.depth_dir / f"{name}.npy", np.asarray(depth, np.float32))
        if index in self.figure_indices:
            self.figure_depths[index] = np.array(depth, np.float32, copy=True)
        row: dict[str, Any] = {"refined": bool(refined), "reason": reason}
        gt = self.seq.gt(name)
        if gt is not None:
            r = self.evaluator.add(name, depth, gt)
            if r is not None:
                self.bands.add(depth, gt)
            row.update({m: (r.metrics[m] if r is not None else None) for m in METRICS})
            row["ratio"] = r.ratio if r is not None else None
        self.per_frame[index] = row

    def summary(self, num_frames: int) -> dict[str, Any]:
        s = self.evaluator.summary()
        out: dict[str, Any] = {m: s[m] for m in METRICS}
        out["frames"] = s["frames"]
        out["seconds_per_frame"] = self.seconds / max(1, num_frames)
        out["seconds"] = self.seconds
        out["refined_frames"] = self.refined
        out["unrefined_frames"] = dict(self.reasons)
        out["processed_frames"] = len(self.seen)
        out["not_published"] = dict(self.not_published)
        out["lost_frames"] = len(self.expected - self.seen) - sum(self.not_published.values())
        out["skipped"] = s["skipped"]
        out["skipped_frames"] = s["skipped_frames"]
        out["invalid_pred"] = s["invalid_pred"]
        out["ratio_median"] = s["ratio_median"]
        out["ratio_std"] = s["ratio_std"]
        out["timings"] = dict(self.timings)
        # the frames a window refined (a keyframe rule leaves others unrefined): their means
        covered = [r for r in self.per_frame.values() if r["refined"] and r.get("abs_rel")
                   is not None]
        out["covered"] = mean_over_frames(covered)
        out["bands"] = self.bands.bands()
        out["error_by_depth"] = self.bands.by_depth()
        out.update(self.extra)
        return out


# ---------------------------------------------------------------------------------------------
# The three modes
# ---------------------------------------------------------------------------------------------


def run_no_ttr(run: ModeRun, seq: ImageSequence, indices: Sequence[int], model,
                cfg: TTRConfig, progress) -> None:
    cfg = copy.deepcopy(cfg)
    cfg.refinement.loss = "sfm"  # never refines: a loss this model cannot run must not stop it
    ttr = SfmTTR(model, cfg)
    try:
        b = ttr.predictor.effective_batch
        for k in range(0, len(indices), b):
            frames = [seq.frame(i) for i in indices[k:k + b]]
            t0 = time.perf_counter()
            depths = ttr.predictor.predict([f.image for f in frames])
            dt = time.perf_counter() - t0
            run.seconds += dt
            run.timings["predict"] += dt
            for f, d in zip(frames, depths, strict=True):
                run.add(f.index, d, False, "no_ttr")
            if progress and (k // b) % 10 == 9:
                progress(f"no_ttr: {min(k + b, len(indices))}/{len(indices)} frames")
    finally:
        ttr.close()


def window_record(ws: WindowStats, frame_index: Callable[[str], int]) -> dict[str, Any]:
    """One window of a windowed mode for results.json: its frames (sequence
    indices), outcome and reason key, what the window checks measured, and how its refinement
    steps ran (``step_mode``: graph, or eager / static with the reason); ``sfm_mapping``:
    under ``sfm.mode`` streaming "continued" or "fresh" with the reason (["", ""] batch)."""
    res = ws.result
    check = res.check.summary() if res is not None and res.check is not None else None
    return {"index": ws.index, "frames": [frame_index(n) for n in ws.names],
            "new_frames": ws.new_frames, "refined": ws.refined, "reason_key": ws.reason_key or "",
            "registered": ws.registered, "points": ws.points, "scale": ws.scale,
            "sfm_attempts": list(res.sfm.attempts) if res is not None and res.sfm else [],
            "seconds": sum(float(ws.timings.get(k, 0.0)) for k in STAGES),
            "timings": {k: float(v) for k, v in ws.timings.items()}, "check": check,
            "predictions": dict(ws.predictions),
            "metric_estimate": ws.metric_estimate, "metric_reason": ws.metric_reason,
            "step_mode": ws.step_mode,
            "sfm_mapping": [ws.sfm_mapping, ws.sfm_mapping_reason]}


def feed_stamp(seq: ImageSequence, indices: Sequence[int], k: int, rate: float | None) -> float:
    """The stamp of the ``k``-th fed frame: the sequence's own, or with a feed ``rate`` (Hz) the
    time it is fed at (a camera at that rate; the keyframe rule reads stamps)."""
    if rate is None:
        return float(seq.stamps[indices[k]])
    return float(seq.stamps[indices[0]]) + k / rate


def feed_odometry(ttr: SfmTTR, seq: ImageSequence, indices: Sequence[int],
                  rate: float | None = None) -> None:
    """The sequence's camera positions (its ``poses.txt``) at its frames' stamps, as the node
    gets them on ``odom``: the odometry source of ``metric.source: odometry``."""
    if seq.poses is None:
        return
    for k, i in enumerate(indices):
        ttr.odometry.add(feed_stamp(seq, indices, k, rate), seq.poses[i][:3, 3])


def run_online(run: ModeRun, seq: ImageSequence, indices: Sequence[int], model,
               cfg: TTRConfig, settings: StreamSettings, progress,
               rate: float | None = None, taps: StreamTaps | None = None) -> None:
    """Every frame through the node's :class:`WindowRunner`, synchronously (each frame
    waits for the one before: the windows' accuracy at any speed), or with ``rate`` (Hz) in
    virtual time: frames arrive at that rate while the worker spends its measured time on each
    (:func:`_push_in_virtual_time`), as the node's keyframe rule sees a camera. ``taps``: what
    a caller measures around the pushes (:class:`StreamTaps`)."""
    taps = taps or StreamTaps()
    ttr = taps.make_ttr(model, copy.deepcopy(cfg))
    dropped: list[tuple[Any, str]] = []
    windows: dict[str, Any] = {"windows": 0, "windows_refined": 0, "window_log": []}
    path_poses: list[FramePose] = []  # the stream's camera path, against the poses (``path``)

    def seq_index(stream_name: str) -> int:  # the stream names frames by a running counter
        return indices[int(stream_name)]

    def on_window(ws: WindowStats) -> None:
        windows["windows"] += 1
        windows["windows_refined"] += int(ws.refined)
        windows["window_log"].append(window_record(ws, seq_index))
        path_poses.extend(ws.path_poses)
        for k, v in ws.timings.items():
            run.timings[k] += float(v)
        if progress:
            span = f"{seq_index(ws.names[0])}-{seq_index(ws.names[-1])}" if ws.names else "-"
            what = "refined" if ws.refined else f"not refined ({ws.reason})"
            secs = sum(ws.timings.get(k, 0.0) for k in STAGES)
            progress(f"{run.mode}: window {ws.index} (frames {span}, {ws.new_frames} new) "
                     f"{what}; {ws.registered}/{len(ws.names)} registered, {ws.points} points, "
                     f"{secs:.1f} s")
        if taps.on_window is not None:
            taps.on_window(ws)

    def on_drop(frame, key: str, message: str) -> None:
        dropped.append((frame, key))

    def take(outs: list[FrameOutput]) -> None:
        for o in outs:
            depth = o.depth
            if depth is None:  # served live only (virtual time): evaluated with the weights now
                depth = in_metres(ttr.predictor.predict([seq.frame(o.frame.index).image])[0],
                                  o.metres_per_unit)
            run.add(o.frame.index, depth, o.refined, o.reason_key)

    feed_odometry(ttr, seq, indices, rate)
    stream = WindowRunner(ttr, copy.deepcopy(settings), on_output=taps.on_output,
                             on_window=on_window, on_drop=on_drop, logger=log)
    if taps.attach is not None:
        taps.attach(stream, ttr)
    # the node's worker pays these before its first frame (StreamRefiner.start): not timed
    run.extra["warm_up_s"] = ttr.warm_up()
    try:
        if rate is None:
            _push_in_order(stream, seq, indices, take, run, taps)
        else:
            _push_in_virtual_time(stream, seq, indices, rate, take, run)
        t0 = time.perf_counter()
        outs = stream.flush()
        dt = time.perf_counter() - t0
        run.seconds += dt
        if taps.pushed is not None:
            taps.pushed(dt)
        take(outs)
        # Frames the stream dropped were never published by the node; they still count, with
        # the latest weights' prediction, under their drop reason.
        for frame, key in dropped:
            if frame is not None and frame.index not in run.seen:
                log.warning("%s: frame %d dropped by the stream (%s): evaluated with an "
                            "unrefined prediction", run.mode, frame.index, key)
                run.add(frame.index, ttr.predictor.predict([frame.image])[0], False,
                        f"dropped:{key}")
    finally:
        ttr.close()
    counters = stream.counters()
    run.extra.update(windows)
    run.extra["stream_counters"] = counters
    run.extra["metric"] = ttr.metric_status().values()
    run.extra.update(path_report(path_poses, stream.path.summary(), seq.poses, seq_index))


def _push_in_order(stream: WindowRunner, seq: ImageSequence, indices: Sequence[int], take,
                   run: ModeRun, taps: StreamTaps) -> None:
    """Each frame pushed once the one before is done, each push timed (with the ``taps``'
    ``receive``, as the node's subscription callback comes before its push)."""
    for i in indices:
        f = seq.frame(i)
        message = taps.prepare(f) if taps.prepare is not None else None
        t0 = time.perf_counter()
        if taps.receive is not None:
            taps.receive(f, message)
        outs = stream.push(f, seq.intrinsics)
        dt = time.perf_counter() - t0
        run.seconds += dt
        if taps.pushed is not None:
            taps.pushed(dt)
        take(outs)


def _push_in_virtual_time(stream: WindowRunner, seq: ImageSequence, indices: Sequence[int],
                          rate: float, take, run: ModeRun) -> None:
    """Frame k arrives at k / rate s (its stamp rewritten to that time); the worker takes one
    queued frame at a time and its processing time (measured) advances the clock, so the frames
    due meanwhile are queued before its next step: the queue, the stale frames and the
    keyframe intervals of a camera at ``rate`` on this machine. The live server is not run, but
    every frame counts as served live, as in the node: a frame no window refines costs the
    worker no prediction (``take`` evaluates it outside the clock, with the weights then)."""
    clock, k, n = 0.0, 0, len(indices)
    while k < n or stream.queued():
        if not stream.queued():
            clock = max(clock, k / rate)  # idle until the next frame arrives
        while k < n and k / rate <= clock:
            frame = seq.frame(indices[k])
            frame.stamp = feed_stamp(seq, indices, k, rate)
            frame.served_live = True
            stream.submit(frame, seq.intrinsics)
            k += 1
        t0 = time.perf_counter()
        outs = stream.step(timeout=0.0)
        dt = time.perf_counter() - t0
        take(outs)
        run.seconds += dt
        clock += dt


def run_offline(run: ModeRun, seq: ImageSequence, indices: Sequence[int], model,
                 cfg: TTRConfig, max_frames: int, progress) -> None:
    cfg = copy.deepcopy(cfg)
    cfg.weight_policy = "continue"  # chunks reset explicitly below
    ttr = SfmTTR(model, cfg)
    n = len(indices)
    size = n if max_frames <= 0 else max(1, max_frames)
    chunks = [list(indices[k:k + size]) for k in range(0, n, size)]
    info: list[dict[str, Any]] = []
    try:
        for c, chunk in enumerate(chunks):
            if c:
                ttr.weights.reset()  # every chunk is a sequence of its own: original weights
            frames = [seq.frame(i) for i in chunk]
            if progress:
                progress(f"{run.mode}: window {c + 1}/{len(chunks)} over {len(frames)} "
                         f"frames ({chunk[0]}-{chunk[-1]})")
            t0 = time.perf_counter()
            try:
                res = ttr.process_window(frames, seq.intrinsics)
            except InputError:
                raise
            except Exception as exc:  # as the stream does: the frames go out unrefined
                msg = f"window failed: {type(exc).__name__}: {exc}"
                log.error("%s: %s", run.mode, msg)
                ttr.weights.reset()
                depths = ttr.predictor.predict([f.image for f in frames])
                run.seconds += time.perf_counter() - t0
                for f, d in zip(frames, depths, strict=True):
                    run.add(f.index, d, False, Unrefined.WINDOW_ERROR)
                info.append({"frames": len(frames), "refined": False, "reason": msg})
                continue
            run.seconds += time.perf_counter() - t0
            for k, v in res.timings.items():
                run.timings[k] += float(v)
            for f in frames:
                run.add(f.index, res.depths[f.name], res.refined,
                        "" if res.refined else res.reason_key)
            info.append(res.summary())
            if progress:
                what = "refined" if res.refined else f"not refined ({res.reason})"
                progress(f"{run.mode}: {what}; {info[-1]['registered']}/{len(frames)} "
                         f"registered, {info[-1]['points']} points, "
                         f"{time.perf_counter() - t0:.1f} s")
            del frames, res
    finally:
        ttr.close()
    run.extra["windows"] = len(chunks)
    run.extra["windows_refined"] = sum(int(w["refined"]) for w in info)
    run.extra["registered_frames"] = sum(int(w.get("registered", 0)) for w in info)
    run.extra["offline_windows"] = info


#: The paper's method is refined per sequence from the network's own weights: the
#: ``sfm_ttr_*`` modes start every window from the start-up weights, whatever the file says.
PAPER_POLICY = "reset"


def mode_config(mode: str, cfg: TTRConfig) -> TTRConfig:
    """``cfg`` with the ``refinement.loss`` of ``mode``'s method (:data:`METHOD_LOSS`: the
    ``sfm_ttr_*`` modes run the paper's method, Eq. (5) with every window from the start-up
    weights, even when the parameter file names another loss or policy); ``no_ttr`` and
    ``node_online`` get ``cfg`` itself."""
    for prefix, loss in METHOD_LOSS.items():
        if mode.startswith(prefix + "_"):
            out = copy.deepcopy(cfg)
            out.refinement.loss = loss
            if prefix == "sfm_ttr":
                out.weight_policy = PAPER_POLICY
            return out
    return cfg


def mode_stream(mode: str, stream: StreamSettings) -> StreamSettings:
    """The windows of an online ``mode``: the node's keyframe rule for ``node_online``, every
    frame in consecutive windows (the paper's) for the other methods."""
    return stream if mode == NODE_MODE else dataclasses.replace(stream, keyframe_policy="all")
