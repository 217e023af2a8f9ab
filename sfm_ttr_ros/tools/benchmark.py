"""``sfm-ttr benchmark``: the same frames, the same network, three ways.

* ``no_ttr``: the network's plain prediction (the original weights).
* ``sfm_ttr_online``: every frame pushed through :class:`~sfm_ttr_ros.core.stream.StreamProcessor`
  exactly as the ROS node feeds it (same windows, keyframes, overlap and accounting; no ROS
  transport), then :meth:`~sfm_ttr_ros.core.stream.StreamProcessor.flush` at the end of the stream
  (the node's idle flush). The depth of each frame is the one the node would publish.
* ``sfm_ttr_offline``: one :meth:`~sfm_ttr_ros.core.pipeline.SfmTTR.process_window` over the whole
  sequence, the paper's setting (or consecutive chunks of ``offline_max_frames`` frames, each
  from the original weights, when the sequence is too long for one reconstruction).

Each mode starts from a fresh copy of the original weights (``model_factory()``). Every frame
that has ground truth is evaluated (KITTI protocol, :mod:`sfm_ttr_ros.core.evaluation`); frames that
SfM could not use count with the prediction the mode published for them (unrefined), as in the
paper. The online and offline windows read their settings from the node's parameter file
(``params/kitti.yaml`` by default, see :func:`default_params_file`), so the benchmark measures
what the node does.

Outputs in ``out_dir``: ``results.json`` (per mode: the metrics, ``frames``,
``seconds_per_frame``, ``refined_frames``, per-stage timings; the relative gains against
``no_ttr``; the settings, the model, the command line), ``results.md`` (the same as tables),
``per_frame.csv`` (abs rel and RMSE of every GT frame in every mode) and ``figure.png`` (for a
few frames: image, depth of each mode on one colour scale, abs-rel error maps at the GT pixels
and predicted-vs-GT density plots, drawn with OpenCV).
"""

from __future__ import annotations

import copy
import csv
import json
import logging
import math
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sfm_ttr_ros.core.evaluation import (
    ERROR_METRICS,
    METRICS,
    EvalConfig,
    Evaluator,
    format_table,
    relative_gain,
    valid_mask,
)
from sfm_ttr_ros.core.frames import InputError
from sfm_ttr_ros.core.pipeline import SfmTTR, TTRConfig
from sfm_ttr_ros.core.stream import (
    FrameOutput,
    StreamProcessor,
    StreamSettings,
    WindowStats,
    reason_key_of,
)
from sfm_ttr_ros.core.visualize import colorize_depth, colorize_error
from sfm_ttr_ros.data.sequence import ImageSequence

log = logging.getLogger(__name__)

MODES = ("no_ttr", "sfm_ttr_online", "sfm_ttr_offline")
NODE_NAME = "refiner"
PARAMS_FILE = "kitti.yaml"
PACKAGE = "sfm_ttr_ros"
#: The top-level stages of a window (WindowResult.timings also holds ``sfm_*`` sub-stages).
STAGES = ("predict_before", "sfm", "align", "refine", "predict_after")


def _stderr(line: str) -> None:
    print(f"sfm-ttr benchmark: {line}", file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------------------------
# The node's parameter file
# ---------------------------------------------------------------------------------------------


def default_params_file(name: str = PARAMS_FILE) -> Path:
    """``params/<name>``: beside the package in a source checkout (or an editable install),
    else in the package's ament share folder (colcon / pip install of the ROS package);
    :class:`InputError` when neither exists."""
    tried = [Path(__file__).resolve().parents[2] / "params" / name]
    try:
        from ament_index_python.packages import get_package_share_directory

        tried.append(Path(get_package_share_directory(PACKAGE)) / "params" / name)
    except Exception:  # not installed, no AMENT_PREFIX_PATH, no ament_index_python
        pass
    for p in tried:
        if p.is_file():
            return p
    raise InputError(f"parameter file {name} not found (looked in "
                     f"{', '.join(str(p) for p in tried)}); pass --params-file")


def _flatten(d: Mapping, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def read_params_file(path: str | Path, node_name: str = NODE_NAME) -> dict[str, Any]:
    """The ``ros__parameters`` a ROS 2 parameter file gives node ``node_name`` (wildcard
    sections ``/**`` first, then the node's own), checked as the node would check them: every
    key a declared parameter, of the declared type (a double written as ``1`` is an error, as it
    is for rclpy) and within its range. Nested mappings are flattened with dots."""
    import yaml

    from sfm_ttr_ros.ros import params as node_params

    path = Path(path)
    if not path.is_file():
        raise InputError(f"parameter file not found: {path}")
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as exc:
        raise InputError(f"cannot read parameter file {path}: {exc}") from exc
    if not isinstance(doc, Mapping):
        raise InputError(f"{path}: expected a mapping of node names to ros__parameters")
    wild, own = {}, {}
    for section, body in doc.items():
        s = str(section).strip()
        if not isinstance(body, Mapping) or "ros__parameters" not in body:
            continue
        params = body["ros__parameters"]
        if not isinstance(params, Mapping):
            raise InputError(f"{path}: ros__parameters of {s!r} is not a mapping")
        if s in ("/**", "**"):
            wild.update(_flatten(params))
        elif s.lstrip("/").split("/")[-1] == node_name:
            own.update(_flatten(params))
    values = {**wild, **own}
    if not values:
        raise InputError(f"{path}: no ros__parameters for node {node_name!r}")
    for key, value in values.items():
        spec = node_params.SPECS.get(key)
        if spec is None:
            raise InputError(f"{path}: {key!r} is not a parameter of the {node_name} node")
        if spec.dynamic_typing:
            continue
        want = type(spec.default)
        ok = isinstance(value, want) and (want is bool or not isinstance(value, bool))
        if not ok:
            hint = " (write doubles as 1.0, not 1)" if want is float else ""
            raise InputError(f"{path}: {key} must be a {want.__name__}, got {value!r}{hint}")
        if spec.lo is not None and not isinstance(value, bool | str) \
                and not spec.lo <= value <= spec.hi:
            raise InputError(f"{path}: {key}={value} is out of range [{spec.lo}, {spec.hi}]")
    return values


def settings_from_params(values: Mapping[str, Any]):
    """(TTRConfig, StreamSettings, ModelConfig) for the node parameters ``values`` (missing
    ones take the node's defaults), exactly as the node builds them."""
    from sfm_ttr_ros.ros import params as node_params

    full = {**node_params.DEFAULTS, **values}
    err = node_params.validate(full)
    if err:
        raise InputError(f"bad parameters: {err}")
    return (node_params.build_ttr_config(full), node_params.build_stream_settings(full),
            node_params.build_model_config(full))


# ---------------------------------------------------------------------------------------------
# Per-mode bookkeeping
# ---------------------------------------------------------------------------------------------


class _ModeRun:
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
        self.per_frame: dict[int, dict[str, Any]] = {}
        self.figure_depths: dict[int, np.ndarray] = {}
        self.refined = 0
        self.reasons: dict[str, int] = defaultdict(int)
        self.seen: set[int] = set()
        self.depth_dir = depth_dir
        self.seconds = 0.0
        self.timings: dict[str, float] = defaultdict(float)
        self.extra: dict[str, Any] = {}
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
            row.update({m: (r.metrics[m] if r is not None else None) for m in METRICS})
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
        out["lost_frames"] = len(self.expected - self.seen)
        out["skipped"] = s["skipped"]
        out["skipped_frames"] = s["skipped_frames"]
        out["invalid_pred"] = s["invalid_pred"]
        out["ratio_median"] = s["ratio_median"]
        out["ratio_std"] = s["ratio_std"]
        out["timings"] = dict(self.timings)
        out.update(self.extra)
        return out


# ---------------------------------------------------------------------------------------------
# The three modes
# ---------------------------------------------------------------------------------------------


def _run_no_ttr(run: _ModeRun, seq: ImageSequence, indices: Sequence[int], model,
                cfg: TTRConfig, progress) -> None:
    ttr = SfmTTR(model, copy.deepcopy(cfg))
    try:
        b = max(1, cfg.predict_batch)
        for k in range(0, len(indices), b):
            frames = [seq.frame(i) for i in indices[k:k + b]]
            t0 = time.perf_counter()
            depths = ttr.predict([f.image for f in frames])
            dt = time.perf_counter() - t0
            run.seconds += dt
            run.timings["predict"] += dt
            for f, d in zip(frames, depths, strict=True):
                run.add(f.index, d, False, "no_ttr")
            if progress and (k // b) % 10 == 9:
                progress(f"no_ttr: {min(k + b, len(indices))}/{len(indices)} frames")
    finally:
        ttr.close()


def _run_online(run: _ModeRun, seq: ImageSequence, indices: Sequence[int], model,
                cfg: TTRConfig, settings: StreamSettings, progress) -> None:
    ttr = SfmTTR(model, copy.deepcopy(cfg))
    dropped: list[tuple[Any, str]] = []
    windows = {"windows": 0, "windows_refined": 0}

    def seq_index(stream_name: str) -> int:  # the stream names frames by a running counter
        return indices[int(stream_name)]

    def on_window(ws: WindowStats) -> None:
        windows["windows"] += 1
        windows["windows_refined"] += int(ws.refined)
        for k, v in ws.timings.items():
            run.timings[k] += float(v)
        if progress:
            span = f"{seq_index(ws.names[0])}-{seq_index(ws.names[-1])}" if ws.names else "-"
            what = "refined" if ws.refined else f"not refined ({ws.reason})"
            secs = sum(ws.timings.get(k, 0.0) for k in STAGES)
            progress(f"sfm_ttr_online: window {ws.index} (frames {span}, {ws.new_frames} new) "
                     f"{what}; {ws.registered}/{len(ws.names)} registered, {ws.points} points, "
                     f"{secs:.1f} s")

    def on_drop(frame, key: str, message: str) -> None:
        dropped.append((frame, key))

    def take(outs: list[FrameOutput]) -> None:
        for o in outs:
            run.add(o.frame.index, o.depth, o.refined, o.reason_key)

    stream = StreamProcessor(ttr, copy.deepcopy(settings), on_window=on_window,
                             on_drop=on_drop, logger=log)
    try:
        for i in indices:
            f = seq.frame(i)
            t0 = time.perf_counter()
            outs = stream.push(f, seq.intrinsics)
            run.seconds += time.perf_counter() - t0
            take(outs)
        t0 = time.perf_counter()
        outs = stream.flush()
        run.seconds += time.perf_counter() - t0
        take(outs)
        # Frames the stream dropped were never published by the node; they still count, with
        # the latest weights' prediction, under their drop reason.
        for frame, key in dropped:
            if frame is not None and frame.index not in run.seen:
                log.warning("sfm_ttr_online: frame %d dropped by the stream (%s): evaluated "
                            "with an unrefined prediction", frame.index, key)
                run.add(frame.index, ttr.predict([frame.image])[0], False, f"dropped:{key}")
    finally:
        ttr.close()
    counters = stream.counters()
    run.extra.update(windows)
    run.extra["stream_counters"] = counters


def _run_offline(run: _ModeRun, seq: ImageSequence, indices: Sequence[int], model,
                 cfg: TTRConfig, max_frames: int, progress) -> None:
    cfg = copy.deepcopy(cfg)
    cfg.reset_each_window = False  # chunks reset explicitly below
    ttr = SfmTTR(model, cfg)
    n = len(indices)
    size = n if max_frames <= 0 else max(1, max_frames)
    chunks = [list(indices[k:k + size]) for k in range(0, n, size)]
    info: list[dict[str, Any]] = []
    try:
        for c, chunk in enumerate(chunks):
            if c:
                ttr.reset_model()  # every chunk is a sequence of its own: original weights
            frames = [seq.frame(i) for i in chunk]
            if progress:
                progress(f"sfm_ttr_offline: window {c + 1}/{len(chunks)} over {len(frames)} "
                         f"frames ({chunk[0]}-{chunk[-1]})")
            t0 = time.perf_counter()
            try:
                res = ttr.process_window(frames, seq.intrinsics)
            except InputError:
                raise
            except Exception as exc:  # as the stream does: the frames go out unrefined
                msg = f"window failed: {type(exc).__name__}: {exc}"
                log.error("sfm_ttr_offline: %s", msg)
                ttr.reset_model()
                depths = ttr.predict([f.image for f in frames])
                run.seconds += time.perf_counter() - t0
                for f, d in zip(frames, depths, strict=True):
                    run.add(f.index, d, False, "window_error")
                info.append({"frames": len(frames), "refined": False, "reason": msg})
                continue
            run.seconds += time.perf_counter() - t0
            for k, v in res.timings.items():
                run.timings[k] += float(v)
            for f in frames:
                run.add(f.index, res.depths[f.name], res.refined,
                        "" if res.refined else reason_key_of(res))
            info.append(res.summary())
            if progress:
                what = "refined" if res.refined else f"not refined ({res.reason})"
                progress(f"sfm_ttr_offline: {what}; {info[-1]['registered']}/{len(frames)} "
                         f"registered, {info[-1]['points']} points, "
                         f"{time.perf_counter() - t0:.1f} s")
            del frames, res
    finally:
        ttr.close()
    run.extra["windows"] = len(chunks)
    run.extra["windows_refined"] = sum(int(w["refined"]) for w in info)
    run.extra["registered_frames"] = sum(int(w.get("registered", 0)) for w in info)
    run.extra["offline_windows"] = info


# ---------------------------------------------------------------------------------------------
# The figure (OpenCV only)
# ---------------------------------------------------------------------------------------------

_FONT = cv2.FONT_HERSHEY_SIMPLEX
_BG = (255, 255, 255)
_HEADER = 22


def _labelled(img: np.ndarray, label: str, width: int, height: int) -> np.ndarray:
    """``img`` fitted into a width x height cell under a one-line label."""
    cell = np.full((height + _HEADER, width, 3), _BG, np.uint8)
    if img is not None and img.size:
        h, w = img.shape[:2]
        s = min(width / w, height / h)
        nw, nh = max(1, round(w * s)), max(1, round(h * s))
        interp = cv2.INTER_AREA if s < 1 else cv2.INTER_NEAREST
        small = cv2.resize(img, (nw, nh), interpolation=interp)
        y0, x0 = _HEADER + (height - nh) // 2, (width - nw) // 2
        cell[y0:y0 + nh, x0:x0 + nw] = small
    cv2.putText(cell, label[: max(8, width // 8)], (4, 16), _FONT, 0.45, (0, 0, 0), 1,
                cv2.LINE_AA)
    return cell


def _scaled_pred(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray,
                 cfg: EvalConfig) -> np.ndarray:
    """The prediction as the evaluation sees it: resized, median-scaled, clamped."""
    p = np.asarray(pred, np.float64)
    if p.shape != gt.shape:
        p = cv2.resize(p, (gt.shape[1], gt.shape[0]), interpolation=cv2.INTER_LINEAR)
    if cfg.median_scaling:
        sel = mask & np.isfinite(p)
        if sel.any() and np.median(p[sel]) > 0:
            p = p * (np.median(gt[sel]) / np.median(p[sel]))
    return np.clip(p, cfg.min_depth, cfg.max_depth)


def _nice_ticks(lo: float, hi: float) -> list[float]:
    ticks = []
    e = math.floor(math.log10(lo))
    while 10**e <= hi * 10:
        for m in (1, 2, 5):
            v = m * 10.0**e
            if lo <= v <= hi:
                ticks.append(v)
        e += 1
    return ticks


def scatter_panel(gt: np.ndarray, pred: np.ndarray, size: int, lo: float, hi: float,
                  max_points: int = 200_000) -> np.ndarray:
    """A log-log density plot of ``pred`` (y) against ``gt`` (x), ``size`` x ``size`` BGR,
    with the identity line (white) and the δ < 1.25 band (grey)."""
    size = max(64, int(size))
    img = np.full((size, size, 3), 40, np.uint8)
    margin = 28
    plot = size - margin - 6
    lo, hi = max(lo, 1e-6), max(hi, lo * 1.01)
    llo, lhi = math.log(lo), math.log(hi)

    def to_px(v):
        return (np.log(np.clip(v, lo, hi)) - llo) / (lhi - llo) * (plot - 1)

    g, p = np.asarray(gt, np.float64).ravel(), np.asarray(pred, np.float64).ravel()
    ok = np.isfinite(g) & np.isfinite(p) & (g > 0) & (p > 0)
    g, p = g[ok], p[ok]
    if g.size > max_points:
        sel = np.random.default_rng(0).choice(g.size, max_points, replace=False)
        g, p = g[sel], p[sel]
    x0, y0 = margin, 6  # plot's top-left corner
    if g.size:
        hist, _, _ = np.histogram2d(to_px(p), to_px(g), bins=plot, range=[[0, plot], [0, plot]])
        hist = np.log1p(hist[::-1])  # row 0 = top = largest prediction
        norm = (hist / hist.max() * 255).astype(np.uint8)
        dens = cv2.applyColorMap(norm, cv2.COLORMAP_VIRIDIS)
        dens[hist == 0] = 25
        img[y0:y0 + plot, x0:x0 + plot] = dens
    else:
        img[y0:y0 + plot, x0:x0 + plot] = 25

    def line(a, b, colour):
        xa, xb = to_px(np.array([a[0], b[0]]))
        ya, yb = to_px(np.array([a[1], b[1]]))
        cv2.line(img, (int(x0 + xa), int(y0 + plot - 1 - ya)),
                 (int(x0 + xb), int(y0 + plot - 1 - yb)), colour, 1, cv2.LINE_AA)

    line((lo, lo), (hi, hi), (255, 255, 255))
    line((lo, lo * 1.25), (hi / 1.25, hi), (150, 150, 150))
    line((lo * 1.25, lo), (hi, hi / 1.25), (150, 150, 150))
    for t in _nice_ticks(lo, hi):
        v = float(to_px(np.array([t]))[0])
        label = f"{t:g}"
        cv2.putText(img, label, (int(x0 + v) - 6, size - 14), _FONT, 0.33, (220, 220, 220), 1,
                    cv2.LINE_AA)
        cv2.putText(img, label, (2, int(y0 + plot - 1 - v) + 4), _FONT, 0.33, (220, 220, 220),
                    1, cv2.LINE_AA)
    cv2.putText(img, "GT [m]", (size // 2 - 18, size - 3), _FONT, 0.35, (220, 220, 220), 1,
                cv2.LINE_AA)
    cv2.putText(img, "pred", (x0 + 4, y0 + 12), _FONT, 0.35, (220, 220, 220), 1, cv2.LINE_AA)
    return img


def _sparse(img: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Dilate a colour map of sparse GT pixels so that it survives the downscaling."""
    if mask.mean() < 0.2:
        return cv2.dilate(img, np.ones((3, 3), np.uint8))
    return img


def qualitative_figure(image: np.ndarray, gt: np.ndarray, preds: Mapping[str, np.ndarray],
                       eval_config: EvalConfig | None = None, title: str = "",
                       panel_width: int = 640) -> np.ndarray:
    """One block of the paper-style figure for one frame, BGR uint8.

    Columns: the image / GT / a legend, then one column per prediction in ``preds`` (e.g.
    ``{"no_ttr": before, "sfm_ttr_online": after}``). Rows: the depth (median-scaled as the
    evaluation does, one inverse-depth colour scale for all: the GT's 5th-95th percentiles),
    the abs-rel error at the GT pixels the evaluation uses (one scale for all, 0 to the first
    prediction's 95th percentile), and the predicted-vs-GT density plot (log-log)."""
    cfg = eval_config or EvalConfig()
    gt = np.asarray(gt, np.float64)
    mask = valid_mask(gt, cfg)
    h, w = gt.shape
    img = np.asarray(image)
    if img.shape[:2] != gt.shape:
        img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    pw = min(int(panel_width), w)
    ph = max(1, round(h * pw / w))
    sh = min(pw, max(ph, 256))  # scatter row height
    scaled = {k: _scaled_pred(v, gt, mask, cfg) for k, v in preds.items()}
    if mask.any():
        vmin, vmax = (float(v) for v in np.percentile(gt[mask], (5, 95)))
        vmax = max(vmax, vmin * 1.01)
        lo, hi = (float(v) for v in np.percentile(gt[mask], (0.5, 99.5)))
        for p in scaled.values():  # the plots' range holds the GT and (most of) every prediction
            sel = mask & np.isfinite(p)
            if sel.any():
                plo, phi = np.percentile(p[sel], (1, 99))
                lo, hi = min(lo, float(plo)), max(hi, float(phi))
        lo, hi = max(lo, cfg.min_depth), min(hi, cfg.max_depth)
    else:
        vmin = vmax = None
        lo, hi = cfg.min_depth, cfg.max_depth
    gt_masked = np.where(mask, gt, 0.0)
    emax = None
    row_depth, row_err, row_sc = [], [], []
    row_depth.append(_labelled(cv2.cvtColor(img, cv2.COLOR_RGB2BGR), "image", pw, ph))
    gt_col = _sparse(colorize_depth(gt_masked, vmin, vmax), mask) if mask.any() else None
    row_err.append(_labelled(gt_col, "ground truth", pw, ph))
    legend = np.full((sh, pw, 3), _BG, np.uint8)
    lines = title.splitlines() if title else []
    for k, p in scaled.items():
        sel = mask & np.isfinite(p)
        if sel.any():
            err = np.abs(p[sel] - gt[sel]) / gt[sel]
            if emax is None:
                emax = max(float(np.percentile(err, 95)), 1e-3)
            lines.append(f"{k}: abs rel {float(np.mean(err)):.4f}")
        label_depth = f"depth {k}"
        row_depth.append(_labelled(colorize_depth(p, vmin, vmax), label_depth, pw, ph))
        e = colorize_error(p, gt_masked, vmax=emax) if mask.any() else None
        row_err.append(_labelled(_sparse(e, mask) if e is not None else None,
                                 f"abs rel error {k} (0-{emax or 0:.2f})", pw, ph))
        sc = scatter_panel(gt[sel], p[sel], sh, lo, hi) if sel.any() else None
        row_sc.append(_labelled(sc, f"pred vs GT {k}", pw, sh))
    for j, text in enumerate(lines):
        cv2.putText(legend, text[: pw // 8], (6, 20 + 20 * j), _FONT, 0.45, (0, 0, 0), 1,
                    cv2.LINE_AA)
    row_sc.insert(0, _labelled(legend, "", pw, sh))
    rows = [np.hstack(r) for r in (row_depth, row_err, row_sc)]
    return np.vstack(rows)


def _pick_figure_frames(gt_indices: Sequence[int], n: int) -> list[int]:
    if n <= 0 or not gt_indices:
        return []
    n = min(n, len(gt_indices))
    pos = [round((k + 1) * (len(gt_indices) + 1) / (n + 1)) - 1 for k in range(n)]
    return sorted({gt_indices[min(max(p, 0), len(gt_indices) - 1)] for p in pos})


# ---------------------------------------------------------------------------------------------
# The benchmark
# ---------------------------------------------------------------------------------------------


def json_safe(v):
    if isinstance(v, dict):
        return {str(k): json_safe(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [json_safe(x) for x in v]
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, Path):
        return str(v)
    return v


def _config_dict(obj) -> dict:
    from dataclasses import asdict, is_dataclass

    return asdict(obj) if is_dataclass(obj) else dict(obj)


def describe_model(model) -> dict[str, Any]:
    """Class, input size and parameter counts of a depth network."""
    enc = sum(p.numel() for p in model.encoder.parameters())
    total = sum(p.numel() for p in model.parameters())
    return {"class": type(model).__name__, "input_size": list(getattr(model, "input_size", ())),
            "parameters": int(total), "encoder_parameters": int(enc)}


def run_benchmark(
    seq: ImageSequence,
    model_factory: Callable[[], Any],
    ttr_config: TTRConfig | None = None,
    stream_settings: StreamSettings | None = None,
    out_dir: str | Path = "benchmark",
    modes: Sequence[str] = MODES,
    eval_config: EvalConfig | None = None,
    *,
    start: int = 0,
    max_frames: int = 0,
    offline_max_frames: int = 0,
    figure_frames: int = 2,
    save_depth: bool = False,
    model_description: Mapping[str, Any] | None = None,
    settings_info: Mapping[str, Any] | None = None,
    command: str | None = None,
    progress: Callable[[str], None] | None = _stderr,
) -> dict[str, Any]:
    """Run ``modes`` over frames ``start .. start+max_frames`` (0 = to the end) of ``seq`` and
    write ``results.json``, ``results.md``, ``per_frame.csv`` and ``figure.png`` to
    ``out_dir``; returns the ``results.json`` content.

    ``model_factory()`` must return a new network with the original weights at every call (one
    per mode). ``ttr_config`` / ``stream_settings`` default to the node's ``params/kitti.yaml``.
    ``offline_max_frames`` > 0 splits the offline mode into chunks of that many frames.
    ``save_depth`` also writes every depth as ``out_dir/depth/<mode>/<frame>.npy`` (network
    units, for ``sfm-ttr evaluate --pred``). ``progress`` gets one line per step (None: quiet).
    """
    modes = list(dict.fromkeys(modes))
    bad = [m for m in modes if m not in MODES]
    if not modes or bad:
        raise InputError(f"unknown mode(s) {bad}; choose from {', '.join(MODES)}")
    if start < 0 or max_frames < 0 or offline_max_frames < 0:
        raise InputError("start, max_frames and offline_max_frames must be >= 0")
    if ttr_config is None or stream_settings is None:
        cfg_p, settings_p, _ = settings_from_params(read_params_file(default_params_file()))
        ttr_config = ttr_config or cfg_p
        stream_settings = stream_settings or settings_p
    eval_config = eval_config or EvalConfig()
    n_all = len(seq)
    if start >= n_all:
        raise InputError(f"--start {start} is past the end of the sequence ({n_all} frames)")
    stop = n_all if max_frames <= 0 else min(n_all, start + max_frames)
    indices = list(range(start, stop))
    names = seq.names
    gt_indices = [i for i in indices if names[i] in seq.gt_paths]
    if not gt_indices:
        raise InputError(f"none of the {len(indices)} frames {start}-{stop - 1} of {seq.name} has "
                         "ground truth: nothing to evaluate (check --kitti-gt / --gt-depth)")
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the output folder {out}: {exc}") from exc
    fig_idx = _pick_figure_frames(gt_indices, figure_frames)
    if progress:
        progress(f"{seq.name}: {len(indices)} frames ({start}-{stop - 1}), {len(gt_indices)} "
                 f"with ground truth; modes {', '.join(modes)}; output {out}")

    runs: dict[str, _ModeRun] = {}
    description = dict(model_description or {})
    for mode in modes:
        model = model_factory()
        if "class" not in description:
            description.update(describe_model(model))
        run = _ModeRun(mode, seq, indices, fig_idx, eval_config,
                       out / "depth" / mode if save_depth else None)
        if progress:
            progress(f"{mode}: start")
        t0 = time.perf_counter()
        if mode == "no_ttr":
            _run_no_ttr(run, seq, indices, model, ttr_config, progress)
        elif mode == "sfm_ttr_online":
            _run_online(run, seq, indices, model, ttr_config, stream_settings, progress)
        else:
            _run_offline(run, seq, indices, model, ttr_config, offline_max_frames, progress)
        runs[mode] = run
        del model
        s = run.summary(len(indices))
        if s["lost_frames"]:
            log.error("%s: %d frame(s) never came out", mode, s["lost_frames"])
        if progress:
            progress(f"{mode}: done in {time.perf_counter() - t0:.1f} s "
                     f"({s['seconds_per_frame']:.2f} s/frame), abs rel {s['abs_rel']:.4f}, "
                     f"RMSE {s['rmse']:.3f}, {s['refined_frames']}/{len(indices)} refined, "
                     f"{s['frames']} evaluated")

    results: dict[str, Any] = {
        "sequence": seq.name,
        "frames_total": len(indices),
        "frames_with_gt": len(gt_indices),
        "first_frame": start,
        "modes": modes,
    }
    for mode, run in runs.items():
        results[mode] = run.summary(len(indices))
    if "no_ttr" in runs:
        results["relative_gain"] = {m: relative_gain(results["no_ttr"], results[m])
                                    for m in modes if m != "no_ttr"}
    results["settings"] = {
        "eval": _config_dict(eval_config),
        "ttr": _config_dict(ttr_config),
        "stream": _config_dict(stream_settings),
        "offline_max_frames": offline_max_frames,
        **dict(settings_info or {}),
    }
    results["model"] = description
    results["command"] = command if command is not None else " ".join(sys.argv)
    results["figure_frames"] = [names[i] for i in fig_idx]
    results = json_safe(results)
    (out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    (out / "results.md").write_text(results_markdown(results))
    _write_per_frame(out / "per_frame.csv", seq, gt_indices, runs)
    if fig_idx:
        blocks = []
        for i in fig_idx:
            gt = seq.gt(names[i])
            preds = {m: r.figure_depths[i] for m, r in runs.items() if i in r.figure_depths}
            if gt is None or not preds:
                continue
            blocks.append(qualitative_figure(seq.frame(i).image, gt, preds, eval_config,
                                             title=f"{seq.name}\nframe {names[i]}"))
        if blocks:
            width = max(b.shape[1] for b in blocks)
            blocks = [np.pad(b, ((0, 8), (0, width - b.shape[1]), (0, 0)),
                             constant_values=255) for b in blocks]
            if not cv2.imwrite(str(out / "figure.png"), np.vstack(blocks)):
                raise InputError(f"cannot write {out / 'figure.png'}")
    if progress:
        progress(f"results in {out}/results.json, results.md, per_frame.csv, figure.png")
    return results


def _write_per_frame(path: Path, seq: ImageSequence, gt_indices: Sequence[int],
                     runs: Mapping[str, _ModeRun]) -> None:
    cols = ["index", "name"]
    for m in runs:
        cols += [f"{m}_abs_rel", f"{m}_rmse", f"{m}_refined", f"{m}_reason"]
    with open(path, "w", newline="") as fh:
        wr = csv.writer(fh)
        wr.writerow(cols)
        for i in gt_indices:
            row: list[Any] = [i, seq.names[i]]
            for r in runs.values():
                pf = r.per_frame.get(i, {})
                for key in ("abs_rel", "rmse"):
                    v = pf.get(key)
                    row.append("" if v is None else f"{v:.6f}")
                row += [int(bool(pf.get("refined"))), pf.get("reason", "")]
            wr.writerow(row)


def _fmt_gain(v) -> str:
    return "n/a" if v is None or not math.isfinite(float(v)) else f"{100 * float(v):+.1f} %"


def results_markdown(results: Mapping[str, Any]) -> str:
    """``results.md``: the metric table, the gains against no_ttr, time and the figure."""
    modes = [m for m in results.get("modes", MODES) if m in results]
    ev = results.get("settings", {}).get("eval", {})
    lines = [f"# SfM-TTR benchmark: {results.get('sequence', '')}", ""]
    model = results.get("model", {})
    lines.append(
        f"{results.get('frames_total')} frames, {results.get('frames_with_gt')} with ground "
        f"truth; model {model.get('type', '')} {model.get('class', '')} "
        f"{'x'.join(str(v) for v in model.get('input_size', []))}; Eigen crop "
        f"{'on' if ev.get('eigen_crop') else 'off'}, median scaling "
        f"{'on' if ev.get('median_scaling', True) else 'off'}, depth cap "
        f"{ev.get('max_depth', 80)} m.")
    lines += ["", format_table({m: {k: (math.nan if results[m].get(k) is None
                                         else results[m].get(k))
                                     for k in (*METRICS, 'frames')} for m in modes},
                               decimals=4)]
    gains = results.get("relative_gain") or {}
    if gains:
        lines += ["Relative gain against no_ttr (positive = better):", "",
                  "| method | " + " | ".join(METRICS) + " |",
                  "|---|" + "---:|" * len(METRICS)]
        for m, g in gains.items():
            lines.append(f"| {m} | " + " | ".join(_fmt_gain(g.get(k)) for k in METRICS) + " |")
        lines.append("")
    stages = ("sfm", "align", "refine", "predict_before", "predict_after", "predict")
    lines += ["| method | s/frame | refined frames | windows (refined) | "
              + " | ".join(f"{s} s" for s in stages) + " |",
              "|---|" + "---:|" * (3 + len(stages))]
    for m in modes:
        r = results[m]
        t = r.get("timings", {})
        win = f"{r['windows']} ({r.get('windows_refined', 0)})" if "windows" in r else "-"
        spf = r.get("seconds_per_frame")
        lines.append(f"| {m} | {spf:.2f} | {r.get('refined_frames', 0)}/"
                     f"{r.get('processed_frames', 0)} | {win} | "
                     + " | ".join(f"{t[s]:.1f}" if s in t else "-" for s in stages) + " |")
    lines += ["", "Lower is better for " + ", ".join(ERROR_METRICS)
              + "; higher for a1-a3. Frames SfM could not use count with the prediction the "
              "mode published for them.", ""]
    if results.get("figure_frames"):
        lines += [f"![qualitative results, frames {', '.join(results['figure_frames'])}]"
                  "(figure.png)", ""]
    lines += ["Command:", "", "```", str(results.get("command", "")), "```", ""]
    return "\n".join(lines)
