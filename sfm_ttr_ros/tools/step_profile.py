"""Where a window's refinement step spends its time, per step mode
(``refinement.step_mode``, core/refinement/graph_step.py), with ``torch.profiler``.

What it checks: that a window's refinement on a GPU is host-bound eagerly and not as one CUDA
graph (docs/decisions.md, "The refinement step on CUDA"). Measured here, per mode,
on one window of a sequence (SfM, alignment and supervision as the pipeline makes them:
:meth:`~sfm_ttr_ros.core.pipeline.SfmTTR.refinement_inputs`), every mode from the same weights:

* ``host_ms``: each step's host time (between the ends of consecutive steps; step 1 from the
  call), ``steady_ms_per_step``: the steps after the warm-up and the capture, from the end of
  step W = GRAPH_WARM_UP_STEPS + 1 to the device's end (synchronised once);
* ``launches``: per step, kernel launches on CUDA (``cudaLaunchKernel`` and the like; a graph
  replay is one ``cudaGraphLaunch``, counted apart), ``aten::`` ops on the CPU; per step = the
  profiler's host-side ``ProfilerStep`` ranges (kineto category ``user_annotation``; with CUDA
  tracing each also appears on the device's timeline as ``gpu_user_annotation``, not a step),
  which end at each step's ``on_step``; only host-side events are counted;
* ``device_busy_ms``: the sum of the device's kernel, copy and set times (categories
  ``kernel``, ``gpu_memcpy``, ``gpu_memset``; never annotation spans), CUDA only, and per
  step;
* ``step_mode`` / ``reason``: which path ran (eager, static, graph) and why.

:func:`step_benchmark` is the notes' micro-benchmark on the real step (Eq. (5) at ``points``
random points of ``frames`` random frames, every encoder parameter trained) per mode, without
the profiler; :func:`sfm_features` times a window's SfM with pycolmap's SIFT and with the torch
SIFT (batched on CUDA). ``scripts/profile_refinement.py`` is the command line.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.outcomes import Stop
from sfm_ttr_ros.core.refinement.encoder import (
    refine_encoder,
    restore_encoder,
    snapshot_encoder,
)
from sfm_ttr_ros.core.refinement.graph_step import GRAPH_WARM_UP_STEPS
from sfm_ttr_ros.core.refinement.refinement_config import RefinementConfig
from sfm_ttr_ros.core.refinement.supervision import FrameSupervision

#: Host-side launch calls of the CUDA runtime and driver that start kernels one by one.
KERNEL_LAUNCHES = ("cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel", "cuLaunchKernelEx",
                   "cudaLaunchCooperativeKernel")
GRAPH_LAUNCHES = ("cudaGraphLaunch", "cuGraphLaunch")
MODES = ("eager", "auto", "static")
#: Kineto categories of host-side events (ranges, ops, runtime calls) and of the device's work
HOST_CATEGORIES = ("cpu_op", "user_annotation", "cuda_runtime", "cuda_driver")
DEVICE_WORK = ("kernel", "gpu_memcpy", "gpu_memset")


def _sync(device) -> None:
    import torch

    if getattr(device, "type", str(device)) == "cuda":
        torch.cuda.synchronize(device)


def _median(values: Sequence[float]) -> float | None:
    return float(statistics.median(values)) if values else None


def _timed_refinement(model, supervision, photometric, cfg: RefinementConfig,
                      on_step: Callable[[int], None] | None = None) -> dict[str, Any]:
    """One refinement from the model's current weights, each step's end on the host clock;
    ``steady_ms_per_step`` from the end of step W (warm-up + capture) to the synchronised
    end."""
    marks: list[float] = []

    def step_done(k: int) -> None:
        marks.append(time.perf_counter())
        if on_step is not None:
            on_step(k)

    t0 = time.perf_counter()
    res = refine_encoder(model, supervision, cfg, photometric=photometric, on_step=step_done)
    _sync(model.device)
    t_end = time.perf_counter()
    host = np.diff([t0, *marks]) * 1e3
    w = GRAPH_WARM_UP_STEPS + 1
    steady = (t_end - marks[w - 1]) * 1e3 / (len(marks) - w) if len(marks) > w else None
    return {"step_mode": res.step_mode, "reason": res.step_mode_reason,
            "steps": res.steps_done, "seconds": round(t_end - t0, 4),
            "host_ms": [round(float(v), 3) for v in host],
            "steady_ms_per_step": steady,
            "losses": [float(v) for v in res.loss_history]}


def trace_events(prof) -> list[dict[str, Any]]:
    """The profiler's complete events as its Chrome trace writes them (``name``, ``cat``: the
    kineto category, ``ts`` / ``dur`` in us): the category is what tells a host-side range
    from its copy on the device's timeline."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "trace.json"
        prof.export_chrome_trace(str(path))
        events = json.loads(path.read_text()).get("traceEvents", [])
    return [e for e in events if e.get("ph") == "X"]


def step_ranges(events: Sequence[dict[str, Any]]) -> list[tuple[float, float]]:
    """The ``ProfilerStep#k`` ranges on the host clock (category ``user_annotation``; their
    copies on the device's timeline, ``gpu_user_annotation``, are not steps)."""
    return sorted((e["ts"], e["ts"] + e["dur"]) for e in events
                  if e.get("cat") == "user_annotation"
                  and str(e.get("name", "")).startswith("ProfilerStep"))


def _count_per_step(events: Sequence[dict[str, Any]], names: Callable[[str], bool]
                    ) -> list[int]:
    """Per host-side ``ProfilerStep`` range, the host-side events (:data:`HOST_CATEGORIES`)
    whose name ``names`` accepts."""
    steps = step_ranges(events)
    counts = [0] * len(steps)
    starts = [s for s, _ in steps]
    for e in events:
        if e.get("cat") not in HOST_CATEGORIES or not names(str(e.get("name", ""))):
            continue
        i = int(np.searchsorted(starts, e["ts"], side="right")) - 1
        if 0 <= i < len(steps) and e["ts"] <= steps[i][1]:
            counts[i] += 1
    return counts


def _device_busy_ms(events: Sequence[dict[str, Any]]) -> float | None:
    """The sum of the device's kernel, copy and set durations (:data:`DEVICE_WORK`; never the
    annotations drawn on its timeline), ms; None without any."""
    spans = [float(e["dur"]) for e in events if e.get("cat") in DEVICE_WORK]
    return sum(spans) / 1e3 if spans else None


def profile_refinement(model, supervision, photometric, cfg: RefinementConfig
                       ) -> dict[str, Any]:
    """:func:`_timed_refinement` under ``torch.profiler`` (module docstring: launches per step,
    device busy time)."""
    from torch.profiler import ProfilerAction, ProfilerActivity, profile

    cuda = model.device.type == "cuda"
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=activities, schedule=lambda step: ProfilerAction.RECORD) as prof:
        out = _timed_refinement(model, supervision, photometric, cfg, lambda k: prof.step())
    events = trace_events(prof)
    if cuda:
        launches = _count_per_step(events, lambda n: n in KERNEL_LAUNCHES)
        out["graph_launches"] = _count_per_step(events, lambda n: n in GRAPH_LAUNCHES)
        out["launches_kind"] = "CUDA kernel launches"
    else:
        launches = _count_per_step(events, lambda n: n.startswith("aten::"))
        out["launches_kind"] = "aten ops (CPU)"
    out["launches"] = launches[:out["steps"]]  # the last range is the tail after the last step
    out["launches_steady_median"] = _median(out["launches"][GRAPH_WARM_UP_STEPS + 1:])
    busy = _device_busy_ms(events) if cuda else None
    out["device_busy_ms"] = busy
    out["device_busy_ms_per_step"] = busy / out["steps"] if busy and out["steps"] else None
    return out


def compare_modes(model, supervision, photometric, cfg: RefinementConfig,
                  modes: Sequence[str] = MODES, profiled: bool = True) -> dict[str, Any]:
    """Every mode of ``modes`` (``step_mode`` values) from the same start-up weights; each
    mode's losses against the first mode's (max relative difference)."""
    start = snapshot_encoder(model)
    out: dict[str, Any] = {}
    try:
        for mode in modes:
            restore_encoder(model, start)
            run = dataclasses.replace(cfg, step_mode=mode)
            out[mode] = (profile_refinement if profiled else _timed_refinement)(
                model, supervision, photometric, run)
    finally:
        restore_encoder(model, start)
    ref = np.asarray(out[modes[0]]["losses"]) if modes else np.zeros(0)
    for mode in modes:
        got = np.asarray(out[mode]["losses"])
        out[mode]["max_rel_loss_diff"] = (float(np.max(np.abs(got - ref) / np.abs(ref)))
                                          if got.shape == ref.shape and got.size else None)
    return out


def synthetic_supervision(model, frames: int, points: int, seed: int = 0
                          ) -> list[FrameSupervision]:
    """``frames`` random images at the network's input size, each with ``points`` random
    pixels whose targets are the network's depth there times 1.1 (Eq. (5) has a gradient)."""
    from sfm_ttr_ros.core.geometry import sample_at
    from sfm_ttr_ros.core.models.base import warm_up_image

    rng = np.random.default_rng(seed)
    h, w = warm_up_image(model).shape[:2]
    out = []
    for i in range(frames):
        image = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        px = np.c_[rng.uniform(0, w - 1, points), rng.uniform(0, h - 1, points)]
        depth = model.predict(image)[0]
        out.append(FrameSupervision(f"s{i}", image, px, 1.1 * sample_at(depth, px),
                                    np.ones(points)))
    return out


def step_benchmark(model, steps: int = 200, points: int = 600, frames: int = 4,
                   modes: Sequence[str] = ("eager", "auto"), lr: float = 1e-5
                   ) -> dict[str, Any]:
    """The notes' micro-benchmark on the real step: Eq. (5) (``loss: sfm``) at ``points``
    random points, every encoder parameter trained, per mode (no profiler)."""
    sup = synthetic_supervision(model, frames, points)
    cfg = RefinementConfig(steps=steps, lr=lr, loss="sfm", min_points=1)
    runs = compare_modes(model, sup, [], cfg, modes, profiled=False)
    return {m: {k: v for k, v in r.items() if k not in ("losses", "host_ms")} |
            {"host_ms_median": _median(r["host_ms"][GRAPH_WARM_UP_STEPS + 1:])}
            for m, r in runs.items()} | {"points": points, "frames": frames, "steps": steps}


def sfm_features(frames, intrinsics, sfm_cfg, features: Sequence[str] = ("colmap", "torch"),
                 device: str | None = None) -> dict[str, Any]:
    """A window's batch SfM (``sfm.mode`` batch: the streaming front end takes pycolmap's SIFT
    only) with each feature kind (``sfm.features``), twice on fresh databases: the first pays
    the one-time costs, the second is reported (seconds by stage, registered frames, points,
    reprojection error)."""
    from sfm_ttr_ros.core.sfm.reconstruction import SfmReconstructor

    out = {}
    for kind in features:
        cfg = dataclasses.replace(sfm_cfg, features=kind, mode="batch")
        for _ in range(2):
            with SfmReconstructor(cfg, feature_device=device) as rec:
                t0 = time.perf_counter()
                res = rec.reconstruct(frames, intrinsics)
                seconds = time.perf_counter() - t0
        out[kind] = {"seconds": round(seconds, 3), "ok": res.ok,
                     "registered": res.num_registered, "points": res.num_points,
                     "reprojection_error": res.reprojection_error,
                     "timings": {k: round(float(v), 4) for k, v in res.timings.items()}}
    return out


# -- the command line ------------------------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="profile_refinement.py",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--kitti-raw", required=True, help="KITTI raw root (sfm-ttr generate)")
    p.add_argument("--kitti-gt", default=None)
    p.add_argument("--drive", default="2011_09_26_drive_0001_sync")
    p.add_argument("--start", type=int, default=0, help="the window's first frame")
    p.add_argument("--window", type=int, default=0, help="frames (0 = window_size)")
    p.add_argument("--params-file", default="", help="default: params/kitti.yaml")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="a parameter or config field, as sfm-ttr's --set (device=cuda)")
    p.add_argument("--modes", nargs="*", default=["eager", "auto"], choices=MODES,
                   help="step modes to run from the same weights (auto = graph on CUDA)")
    p.add_argument("--steps", type=int, default=0, help="refinement steps (0 = the settings')")
    p.add_argument("--no-profile", action="store_true", help="time only, no torch.profiler")
    p.add_argument("--micro-steps", type=int, default=0, help="micro-benchmark steps (0 = none)")
    p.add_argument("--micro-points", type=int, default=600)
    p.add_argument("--micro-frames", type=int, default=4)
    p.add_argument("--sfm-features", nargs="*", default=[], choices=("colmap", "torch"),
                   help="time the window's SfM with these features")
    p.add_argument("--windows", type=int, default=0,
                   help="the window refined this many times with the graph: capture cost and "
                        "memory per window (tools/gpu_check.py; 0 = not)")
    p.add_argument("--out", default="", help="JSON report, rewritten after each part "
                                             "(default: stdout only)")
    return p


def _settings(args):
    from sfm_ttr_ros.core.params import build
    from sfm_ttr_ros.tools.benchmark import default_params_file
    from sfm_ttr_ros.tools.cli_args import parameter_values

    # only the file and --set: this --steps (0 = the settings') is no PARAM_FLAGS flag and
    # goes over --set, below
    files = argparse.Namespace(params_file=args.params_file, set=args.set)
    _, values = parameter_values(files, None if args.params_file else default_params_file())
    if args.steps:
        values["refinement.steps"] = args.steps
    return build(values)


def _environment(model) -> dict[str, Any]:
    import torch

    dev = model.device
    return {"torch": torch.__version__, "device": str(dev),
            "device_name": torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu",
            "threads": torch.get_num_threads()}


def run(args) -> dict[str, Any]:
    """The report of one command line (module docstring)."""
    from sfm_ttr_ros.core.pipeline import SfmTTR
    from sfm_ttr_ros.data.sequence import open_kitti
    from sfm_ttr_ros.tools.cli_args import build_model_for

    s = _settings(args)
    seq = open_kitti(args.kitti_raw, args.drive, args.kitti_gt)
    n = args.window or s.stream.window_size
    if args.start < 0 or args.start + n > len(seq):
        raise InputError(f"frames {args.start}..{args.start + n - 1} are not all in the "
                         f"{len(seq)}-frame sequence")
    frames = seq.frames(args.start, args.start + n)
    model = build_model_for(s)
    report: dict[str, Any] = {"environment": _environment(model), "frames": n,
                              "image_size": list(frames[0].image.shape[1::-1])}
    ttr = SfmTTR(model, s.ttr)
    try:
        ttr.warm_up()
        t0 = time.perf_counter()
        inputs = ttr.refinement_inputs(frames, seq.intrinsics)
        report["window_inputs_seconds"] = round(time.perf_counter() - t0, 3)
        cfg = ttr.config.refinement
        if isinstance(inputs, Stop):
            report["stop"] = inputs.text
        elif args.modes:
            report["loss"], report["steps"] = cfg.loss, cfg.steps
            report["profile" if not args.no_profile else "timing"] = compare_modes(
                model, *inputs, cfg, args.modes, profiled=not args.no_profile)
            save(args.out, report)
        if args.windows and not isinstance(inputs, Stop):
            from sfm_ttr_ros.tools.gpu_check import graph_windows

            report["windows"] = graph_windows(model, *inputs, cfg, args.windows)
            save(args.out, report)
    finally:
        ttr.close()
    if args.micro_steps:
        report["micro"] = step_benchmark(model, args.micro_steps, args.micro_points,
                                         args.micro_frames, args.modes or ("eager", "auto"))
        save(args.out, report)
    if args.sfm_features:
        report["sfm"] = sfm_features(frames, seq.intrinsics, s.ttr.sfm, args.sfm_features)
    return report


def save(out: str, report: dict[str, Any]) -> None:
    """Write ``report`` to ``out`` now (nothing when ``out`` is empty): a part stopped by its
    time limit leaves what it measured so far."""
    if out:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(json.dumps(report, indent=1, default=str) + "\n")


def summary_lines(report: dict[str, Any]) -> list[str]:
    """A few lines for people: per mode, what ran and its cost per step."""
    lines = [f"{report['environment']['device_name']}, torch {report['environment']['torch']},"
             f" {report['frames']} frames of {report['image_size']}"]
    if "stop" in report:
        lines.append(f"window not refined: {report['stop']}")
    for key in ("profile", "timing", "micro"):
        for mode, r in (report.get(key) or {}).items():
            if not isinstance(r, dict):
                continue
            ms = r.get("steady_ms_per_step")
            lines.append(
                f"{key} {mode}: ran {r['step_mode']}"
                + (f" ({r['reason']})" if r.get("reason") else "")
                + (f", {ms:.1f} ms/step steady" if ms else "")
                + (f", {r['launches_steady_median']:.0f} {r['launches_kind']}/step"
                   if r.get("launches_steady_median") is not None else "")
                + (f", device busy {r['device_busy_ms_per_step']:.2f} ms/step"
                   if r.get("device_busy_ms_per_step") else ""))
    for kind, r in (report.get("sfm") or {}).items():
        lines.append(f"sfm {kind}: {r['seconds']:.2f} s, {r['registered']} registered, "
                     f"{r['points']} points")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        report = run(args)
    except InputError as exc:
        print(f"profile_refinement: {exc}", file=sys.stderr)
        return 2
    print("\n".join(summary_lines(report)))
    save(args.out, report)
    return 0


# -- scripts/gpu_window_check.sh's summary ---------------------------------------------------

def _mode_summary(r: dict[str, Any]) -> dict[str, Any]:
    keys = ("step_mode", "reason", "steps", "steady_ms_per_step", "launches_steady_median",
            "launches_kind", "device_busy_ms_per_step", "max_rel_loss_diff", "seconds")
    return {k: r.get(k) for k in keys if k in r}


def _bench_summary(path: Path) -> dict[str, Any] | None:
    """A benchmark's results.json in short: per mode accuracy, seconds per frame, the
    refinement's seconds, how the windows' steps ran, live latency and first weights."""
    if not path.is_file():
        return None
    r = json.loads(path.read_text())
    out = {}
    for mode in r.get("modes", []):
        m = r[mode]
        modes: dict[str, int] = {}
        for w in m.get("window_log", []):
            modes[w.get("step_mode") or "none"] = modes.get(w.get("step_mode") or "none", 0) + 1
        out[mode] = {"abs_rel": m.get("abs_rel"), "rmse": m.get("rmse"),
                     "seconds_per_frame": m.get("seconds_per_frame"),
                     "refine_s": (m.get("timings") or {}).get("refine"),
                     "windows": m.get("windows"), "windows_refined": m.get("windows_refined"),
                     "step_modes": modes}
        for k in ("latency_p95_s", "first_weights_s", "last_frame_to_first_weights_s"):
            if k in m:
                out[mode][k] = m[k]
    return out


def check_summary(out: str | Path) -> dict[str, Any]:
    """What ``scripts/gpu_window_check.sh`` measured, from the files it wrote in ``out``: the
    device, each part's exit status and seconds, per step mode the profile's and timing's
    figures, the micro-benchmark, the SfM per feature kind, the two benchmarks in short."""
    out = Path(out)
    res: dict[str, Any] = {}
    for name in ("device", "profile", "timing"):
        p = out / f"{name}.json"
        res[name] = json.loads(p.read_text()) if p.is_file() else None
    parts = out / "parts.jsonl"
    res["parts"] = [json.loads(line) for line in parts.read_text().splitlines()
                    if line.strip()] if parts.is_file() else []
    res["windows"] = (res["profile"] or {}).get("windows")
    for name in ("profile", "timing"):
        r = res[name] or {}
        res[name] = {key: {m: _mode_summary(v) for m, v in r[key].items()
                           if isinstance(v, dict)}
                     for key in ("profile", "timing", "micro") if key in r} | (
            {"sfm": r["sfm"]} if "sfm" in r else {}) | (
            {"stop": r["stop"]} if "stop" in r else {})
    for bench in ("bench_graph", "bench_eager", "holo_graph", "holo_eager"):
        res[bench] = _bench_summary(out / bench / "results.json")
    return res


def write_check_summary(out: str | Path) -> Path:
    """:func:`check_summary` written to ``out/check.json`` and its figures' table
    (:func:`~sfm_ttr_ros.tools.gpu_check.summary_table`) to ``out/figures.md``; the JSON's
    path."""
    from sfm_ttr_ros.tools.gpu_check import summary_table

    summary = check_summary(out)
    path = Path(out) / "check.json"
    path.write_text(json.dumps(summary, indent=1, default=str) + "\n")
    (Path(out) / "figures.md").write_text("\n".join(summary_table(summary)) + "\n")
    return path
