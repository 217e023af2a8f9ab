"""The benchmark's window timeline, OpenCV only: per frame the abs rel of every mode
along the sequence, and under it one strip per windowed mode with each window's outcome —
refined (green), refused by a window check (red, its reason key written in), other unrefined
(grey) — so a rejected window can be read against what it would have done to its frames."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import cv2
import numpy as np

from sfm_ttr_ros.core.outcomes import CHECKS

TIMELINE_FIGURE = "windows.png"
_FONT = cv2.FONT_HERSHEY_SIMPLEX
_COLOURS = [(60, 60, 60), (200, 120, 0), (0, 140, 255), (180, 0, 180), (0, 160, 0),
            (0, 0, 200), (128, 128, 0)]  # BGR, one per mode
_REFINED, _REJECTED, _OTHER = (120, 200, 120), (90, 90, 230), (200, 200, 200)


def _outcome_colour(window: Mapping[str, Any]) -> tuple[int, int, int]:
    if window.get("refined"):
        return _REFINED
    return _REJECTED if window.get("reason_key") in CHECKS else _OTHER


def window_timeline_figure(abs_rel: Mapping[str, Mapping[int, float]],
                           window_logs: Mapping[str, Sequence[Mapping[str, Any]]],
                           first: int, last: int, title: str = "",
                           labels: Sequence[str] | None = None,
                           width: int = 1200, plot_height: int = 260) -> np.ndarray:
    """BGR image: ``abs_rel[mode][frame index]`` as lines over frames ``first..last``, one
    outcome strip per mode of ``window_logs`` (``window_record`` dicts), and, with ``labels``
    (one per frame from ``first``), the sequence's segment labels along the top."""
    left, right, top, strip = 60, 170, 40 + (18 if labels else 0), 22
    modes = list(abs_rel)
    height = top + plot_height + 30 + strip * len(window_logs) + 10
    img = np.full((height, width, 3), 255, np.uint8)
    span = max(1, last - first)
    plot_w = width - left - right

    def x_of(i: float) -> int:
        return int(round(left + (i - first) / span * plot_w))

    values = [v for m in modes for v in abs_rel[m].values() if v is not None and np.isfinite(v)]
    hi = max(0.05, float(np.percentile(values, 99)) * 1.1) if values else 1.0

    def y_of(v: float) -> int:
        return int(round(top + plot_height - min(v, hi) / hi * plot_height))

    cv2.putText(img, title[:150], (left, 18), _FONT, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    if labels:
        start = 0
        for k in range(1, len(labels) + 1):
            if k == len(labels) or labels[k] != labels[start]:
                x0, x1 = x_of(first + start - 0.5), x_of(first + k - 0.5)
                cv2.rectangle(img, (x0, top - 16), (x1, top - 2), (235, 235, 235), -1)
                cv2.rectangle(img, (x0, top - 16), (x1, top - 2), (150, 150, 150), 1)
                cv2.putText(img, labels[start][: max(1, (x1 - x0) // 7)], (x0 + 2, top - 5),
                            _FONT, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
                start = k
    cv2.rectangle(img, (left, top), (left + plot_w, top + plot_height), (0, 0, 0), 1)
    for frac in (0.25, 0.5, 0.75, 1.0):
        y = y_of(hi * frac)
        cv2.line(img, (left, y), (left + plot_w, y), (225, 225, 225), 1)
        cv2.putText(img, f"{hi * frac:.2f}", (4, y + 4), _FONT, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "abs rel", (4, top - 4 if not labels else top + 12), _FONT, 0.35,
                (0, 0, 0), 1, cv2.LINE_AA)
    for k, mode in enumerate(modes):
        colour = _COLOURS[k % len(_COLOURS)]
        pts = [(x_of(i), y_of(v)) for i, v in sorted(abs_rel[mode].items())
               if v is not None and np.isfinite(v)]
        if len(pts) > 1:
            cv2.polylines(img, [np.array(pts, np.int32)], False, colour, 1, cv2.LINE_AA)
        cv2.putText(img, mode[:24], (left + plot_w + 8, top + 14 + 16 * k), _FONT, 0.4, colour,
                    1, cv2.LINE_AA)
    y = top + plot_height + 30
    for mode, log in window_logs.items():
        cv2.putText(img, mode[:24], (left + plot_w + 8, y + 14), _FONT, 0.35, (0, 0, 0), 1,
                    cv2.LINE_AA)
        for w in log:
            frames = [i for i in w.get("frames", []) if first <= i <= last]
            if not frames:
                continue
            x0, x1 = x_of(min(frames) - 0.5), x_of(max(frames) + 0.5)
            cv2.rectangle(img, (x0, y), (x1, y + strip - 4), _outcome_colour(w), -1)
            cv2.rectangle(img, (x0, y), (x1, y + strip - 4), (90, 90, 90), 1)
            if not w.get("refined"):
                key = str(w.get("reason_key", "")).replace("check_", "")
                cv2.putText(img, key[: max(1, (x1 - x0) // 6)], (x0 + 2, y + 12), _FONT, 0.3,
                            (0, 0, 0), 1, cv2.LINE_AA)
        y += strip
    cv2.putText(img, "frame", (left + plot_w // 2, top + plot_height + 22), _FONT, 0.4,
                (0, 0, 0), 1, cv2.LINE_AA)
    for i in np.linspace(first, last, 6):
        cv2.putText(img, f"{int(i)}", (x_of(i) - 8, top + plot_height + 12), _FONT, 0.35,
                    (0, 0, 0), 1, cv2.LINE_AA)
    return img
