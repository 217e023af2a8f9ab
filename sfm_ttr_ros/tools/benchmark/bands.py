"""Error by ground-truth depth: the benchmark's ``bands`` (0-10, 10-20, 20-40, 40-80 m) and the
error-against-depth figure (the paper's Fig. 4: Izquierdo & Civera, CVPR 2023, where photometric
refinement helps below ~10 m and SfM-TTR beyond).

Every evaluated frame's prediction is the one the evaluation computes its metrics from
(:func:`sfm_ttr_ros.core.evaluation.scaled_prediction`: resized to the GT NaN-safely, per-image
median scaling, clamped to the depth range), and each pixel it evaluates (valid GT, finite
prediction) is put in the depth bin of its GT depth: the bands hold the frame's pixels. Unlike
the overall metrics (means over frames of per-frame metrics), the band numbers are POOLED over
the pixels of all frames: abs rel = mean |d − d*| / d*, RMSE = sqrt(mean (d − d*)²) over the
band's pixels, ``pixels`` = their count, so a band seen in few frames is not over-weighted."""

from __future__ import annotations

import math
from collections.abc import Mapping

import cv2
import numpy as np

from sfm_ttr_ros.core.evaluation import EvalConfig, scaled_prediction

#: The error-against-depth figure, written next to figure.png
ERROR_FIGURE = "error_by_depth.png"
#: The coarse bands of results.json, metres: [lo, hi)
DEPTH_BANDS = ((0.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, 80.0))
#: The fine bins of the figure (and ``error_by_depth``): 0.5 m to 10 m, 1 m to 20 m, then 2 m.
BIN_EDGES = np.concatenate([np.arange(0.0, 10.0, 0.5), np.arange(10.0, 20.0, 1.0),
                            np.arange(20.0, 80.0 + 1e-9, 2.0)])


def band_name(lo: float, hi: float) -> str:
    return f"{lo:g}-{hi:g}"


class DepthBands:
    """Accumulates per-pixel errors of one mode's frames in the fine depth bins."""

    def __init__(self, eval_config: EvalConfig | None = None):
        self.config = eval_config or EvalConfig()
        n = len(BIN_EDGES) - 1
        self.count = np.zeros(n, np.int64)
        self.abs_rel = np.zeros(n)  # sums
        self.sq_err = np.zeros(n)

    def add(self, pred: np.ndarray, gt: np.ndarray) -> None:
        """One frame: its evaluated pixels (:func:`scaled_prediction`), by GT depth; nothing for a
        frame the evaluation skips."""
        scaled = scaled_prediction(pred, gt, self.config)
        if scaled.skip is not None:
            return
        g, d = scaled.values()
        idx = np.searchsorted(BIN_EDGES, g, side="right") - 1
        ok = (idx >= 0) & (idx < len(self.count))
        idx, g, d = idx[ok], g[ok], d[ok]
        self.count += np.bincount(idx, minlength=len(self.count))
        self.abs_rel += np.bincount(idx, np.abs(d - g) / g, minlength=len(self.count))
        self.sq_err += np.bincount(idx, (d - g) ** 2, minlength=len(self.count))

    def _metrics(self, sel: np.ndarray) -> dict[str, float | int]:
        n = int(self.count[sel].sum())
        if n == 0:
            return {"abs_rel": math.nan, "rmse": math.nan, "pixels": 0}
        return {"abs_rel": float(self.abs_rel[sel].sum() / n),
                "rmse": float(math.sqrt(self.sq_err[sel].sum() / n)), "pixels": n}

    def bands(self) -> dict[str, dict[str, float | int]]:
        """``{"0-10": {"abs_rel", "rmse", "pixels"}, ...}`` for :data:`DEPTH_BANDS`."""
        lo_edges = BIN_EDGES[:-1]
        return {band_name(lo, hi): self._metrics((lo_edges >= lo) & (lo_edges < hi))
                for lo, hi in DEPTH_BANDS}

    def by_depth(self) -> dict[str, list]:
        """The fine bins: ``edges`` (n + 1), ``abs_rel``, ``rmse``, ``pixels`` (n each)."""
        rows = [self._metrics(np.arange(len(self.count)) == i) for i in range(len(self.count))]
        return {"edges": [float(e) for e in BIN_EDGES],
                **{k: [r[k] for r in rows] for k in ("abs_rel", "rmse", "pixels")}}


# -- the figure ---------------------------------------------------------------------------------

_FONT = cv2.FONT_HERSHEY_SIMPLEX
_COLOURS = [(90, 90, 90), (200, 110, 30), (40, 160, 40), (30, 30, 220), (180, 60, 180),
            (0, 170, 220), (130, 90, 40), (120, 200, 120)]  # BGR, one per mode


def _nice_step(span: float, ticks: int = 6) -> float:
    raw = max(span, 1e-9) / ticks
    e = 10 ** math.floor(math.log10(raw))
    return next(m * e for m in (1, 2, 2.5, 5, 10) if m * e >= raw)


def error_by_depth_figure(curves: Mapping[str, Mapping[str, list]], title: str = "",
                          metric: str = "abs_rel", min_pixels: int = 50,
                          size: tuple[int, int] = (900, 520)) -> np.ndarray:
    """The error of every mode against GT depth, BGR uint8 (the paper's Fig. 4).

    ``curves``: mode → :meth:`DepthBands.by_depth`. One line per mode over the fine bins with
    at least ``min_pixels`` pixels (bin centres), the x axis up to the deepest such bin; the
    GT pixel count per bin as grey bars along the bottom (share of the tallest bin)."""
    width, height = size
    img = np.full((height, width, 3), 255, np.uint8)
    left, right, top, bottom = 60, 170, 34, 46
    pw, ph = width - left - right, height - top - bottom
    first = next(iter(curves.values()), None)
    if first is None:
        return img
    edges = np.asarray(first["edges"], np.float64)
    pixels = np.asarray(first["pixels"], np.float64)
    used = pixels >= min_pixels
    if not used.any():
        cv2.putText(img, "no depth bin has enough GT pixels", (left, top + 40), _FONT, 0.5,
                    (0, 0, 0), 1, cv2.LINE_AA)
        return img
    x_max = float(edges[1:][used].max())
    centres = (edges[:-1] + edges[1:]) / 2
    ys = [np.asarray(c[metric], np.float64) for c in curves.values()]
    finite = np.concatenate([y[used & np.isfinite(y)] for y in ys]) if ys else np.zeros(0)
    y_max = float(finite.max()) * 1.1 if finite.size else 1.0

    def px(x: float, y: float) -> tuple[int, int]:
        return (int(round(left + x / x_max * pw)), int(round(top + ph - y / y_max * ph)))

    # GT pixel distribution
    share = pixels / max(pixels.max(), 1)
    for i in np.nonzero(used)[0]:
        x0, _ = px(edges[i], 0)
        x1, _ = px(min(edges[i + 1], x_max), 0)
        cv2.rectangle(img, (x0, top + ph - int(share[i] * ph * 0.25)), (max(x0, x1 - 1),
                      top + ph), (225, 225, 225), -1)
    # axes and ticks
    cv2.rectangle(img, (left, top), (left + pw, top + ph), (0, 0, 0), 1)
    step = _nice_step(x_max)
    for k in range(int(x_max / step) + 1):
        x = k * step
        p = px(x, 0)
        cv2.line(img, p, (p[0], p[1] + 4), (0, 0, 0), 1)
        cv2.putText(img, f"{x:g}", (p[0] - 8, p[1] + 18), _FONT, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    ystep = _nice_step(y_max, 5)
    for k in range(int(y_max / ystep) + 1):
        y = k * ystep
        p = px(0, y)
        cv2.line(img, (p[0] - 4, p[1]), p, (0, 0, 0), 1)
        cv2.line(img, (p[0] + 1, p[1]), (left + pw - 1, p[1]), (240, 240, 240), 1)
        cv2.putText(img, f"{y:.3g}", (4, p[1] + 4), _FONT, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "GT depth [m] (grey: share of GT pixels)", (left + pw // 2 - 140,
                height - 10), _FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, title or f"{metric} by depth", (left, 22), _FONT, 0.5, (0, 0, 0), 1,
                cv2.LINE_AA)
    # one line per mode, legend on the right
    for k, (mode, y) in enumerate(zip(curves, ys, strict=True)):
        colour = _COLOURS[k % len(_COLOURS)]
        pts = [px(float(c), float(v)) for c, v, u in zip(centres, y, used, strict=True)
               if u and math.isfinite(v) and c <= x_max]
        for a, b in zip(pts, pts[1:], strict=False):
            cv2.line(img, a, b, colour, 2, cv2.LINE_AA)
        for p in pts:
            cv2.circle(img, p, 3, colour, -1, cv2.LINE_AA)
        ly = top + 14 + 20 * k
        cv2.line(img, (left + pw + 10, ly - 4), (left + pw + 30, ly - 4), colour, 2)
        cv2.putText(img, mode, (left + pw + 36, ly), _FONT, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
    return img
