"""Streaming SfM against the batch reconstructor on the same windows: cost, fit and scale
(only the tests use it: tests/test_streaming_sfm.py).

For windows side by side (a stream cut every ``window_size`` frames), interleaved in one
process (window w streamed, then window w by the batch :class:`SfmReconstructor`, which keeps
its database across windows as the pipeline does):

* the front end's cost per frame (extract, match, verify) and the streaming mapping's cost per
  window, split into what runs as frames arrive and what runs after the window's last frame;
* each window's registered frames, 3D points and mean reprojection error r_lj (Sec. 3.1);
* with ground-truth depth: each window's alignment scale s = median(D_gt / D_sfm) over its
  observations (the one-scale fit of the SfM tests), the depth error after it, and the ratio
  of s between consecutive windows (1 when the windows share the map's scale).
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.sfm.reconstruction import SfmReconstructor
from sfm_ttr_ros.core.sfm.result import SfmResult
from sfm_ttr_ros.core.sfm.sfm_config import SfmConfig
from sfm_ttr_ros.core.sfm.streaming_map import StreamingSfm


def window_figures(result: SfmResult, seconds: float,
                   depths: dict[str, np.ndarray] | None) -> dict:
    """One window's figures: ok, registered, points, mean r_lj, seconds, and with ground
    truth the scale median(D_gt / D_sfm) and the median relative depth error after it."""
    out = {"ok": result.ok, "reason": result.reason, "registered": result.num_registered,
           "frames": result.num_frames, "points": result.num_points,
           "reprojection_error": result.reprojection_error, "seconds": seconds,
           "scale": float("nan"), "depth_error": float("nan")}
    if not depths or not result.frames:
        return out
    sfm, gt = [], []
    for name, obs in result.frames.items():
        px = np.rint(obs.pixels).astype(int)
        h, w = depths[name].shape
        inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        g = np.zeros(len(px))
        g[inside] = depths[name][px[inside, 1], px[inside, 0]]
        valid = (g > 0) & (obs.depths > 0)
        sfm.append(obs.depths[valid])
        gt.append(g[valid])
    sfm, gt = np.concatenate(sfm), np.concatenate(gt)
    if sfm.size:
        s = float(np.median(gt / sfm))
        out["scale"] = s
        out["depth_error"] = float(np.median(np.abs(s * sfm - gt) / gt))
    return out


def scale_ratios(windows: list[dict]) -> list[float]:
    """s(w + 1) / s(w) for consecutive windows (NaN where a scale is missing)."""
    return [b["scale"] / a["scale"] for a, b in zip(windows, windows[1:], strict=False)]


def compare_streaming_with_batch(frames: Sequence[Frame], intrinsics: Intrinsics,
                                 window_size: int,
                                 depths: dict[str, np.ndarray] | None = None,
                                 config: SfmConfig | None = None) -> dict:
    """Stream ``frames`` through :class:`StreamingSfm` and the batch reconstructor, window by
    window (windows side by side), and return both sides' figures (see the module doc) and the
    streamed windows' results."""
    if window_size < 2 or len(frames) < window_size:
        raise InputError(f"need windows of >= 2 frames and at least one window: "
                         f"{len(frames)} frames, window_size {window_size}")
    config = config or SfmConfig()
    report: dict = {"stream": [], "batch": [], "frontend": [], "stream_results": []}
    with StreamingSfm(config) as stream, SfmReconstructor(config) as batch:
        for start in range(0, len(frames) - window_size + 1, window_size):
            window = list(frames[start:start + window_size])
            for f in window:  # frames arrive: front end (+ registration into the map)
                report["frontend"].append(stream.admit(f, intrinsics))
            t0 = time.perf_counter()
            result = stream.reconstruct(window, intrinsics)
            report["stream_results"].append(result)
            figures = window_figures(result, time.perf_counter() - t0, depths)
            figures["map_on_admit"] = result.timings.get("map_on_admit", 0.0)
            figures["mapping"] = (result.mapping, result.mapping_reason)
            report["stream"].append(figures)
            t0 = time.perf_counter()
            result = batch.reconstruct(window, intrinsics)
            figures = window_figures(result, time.perf_counter() - t0, depths)
            figures.update({k: result.timings.get(k, 0.0) for k in ("extract", "match", "map")})
            report["batch"].append(figures)
        report["continuations"] = stream.continuations
        report["fresh_mappings"] = stream.fresh_mappings
        report["frames_held"] = len(stream.frontend.features)
    for side in ("stream", "batch"):
        report[f"{side}_scale_ratios"] = scale_ratios(report[side])
    per_frame = report["frontend"]
    report["frontend_mean"] = {k: float(np.mean([getattr(t, k) for t in per_frame]))
                               for k in ("extract", "match", "verify", "total")}
    return report
