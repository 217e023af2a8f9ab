"""The benchmark's qualitative figure, drawn with OpenCV only: per frame the image, the GT, each
mode's depth (one colour scale), abs-rel error maps at the GT pixels and predicted-vs-GT
density plots."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import cv2
import numpy as np

from sfm_ttr_ros.core.evaluation import EvalConfig, scaled_prediction, valid_mask
from sfm_ttr_ros.core.visualize import colorize_depth, colorize_error

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
    scaled = {k: scaled_prediction(v, gt, cfg).depth for k, v in preds.items()}
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


def pick_figure_frames(gt_indices: Sequence[int], n: int) -> list[int]:
    if n <= 0 or not gt_indices:
        return []
    n = min(n, len(gt_indices))
    pos = [round((k + 1) * (len(gt_indices) + 1) / (n + 1)) - 1 for k in range(n)]
    return sorted({gt_indices[min(max(p, 0), len(gt_indices) - 1)] for p in pos})
