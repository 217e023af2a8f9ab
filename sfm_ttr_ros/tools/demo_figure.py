"""The demo's figure (``figure.png``): one frame of the drive, its ground truth and each
output's depth, chosen to be representative and saying so.

The frame is the one of median per-frame change of abs rel from no TTR to the windowed output
(``~/depth_refined``) over the frames both were scored on (:func:`choose_frame`): neither the
best frame nor the worst, and its caption states its change and the range over all frames, so
the figure shows what refinement typically does to one frame and where that frame stands.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class FigureFrame:
    """The chosen frame (``name``: ``sec.nanosec``), its rank among ``count`` frames ordered
    by change (1 = the worst), abs rel before and after, and the range of the change (relative,
    positive = lower error than no TTR)."""

    name: str
    rank: int
    count: int
    before: float
    after: float
    worst: float
    best: float

    @property
    def change(self) -> float:
        return (self.before - self.after) / self.before

    @property
    def stamp_ns(self) -> int:
        sec, nanosec = self.name.split(".")
        return int(sec) * 1_000_000_000 + int(nanosec)

    def caption(self) -> list[str]:
        """The figure's lines about the choice (each within the legend's 80 characters)."""
        return [f"median frame by abs rel change ({self.rank} of {self.count}):",
                f"  abs rel {self.before:.3f} -> {self.after:.3f} ({self.change:+.1%}; "
                "+ = lower error)",
                f"  all frames: {self.worst:+.1%} (worst) to {self.best:+.1%} (best)"]


def choose_frame(base_rows: list[dict], refined_rows: list[dict]) -> FigureFrame | None:
    """The frame of median relative change of abs rel (``per_frame`` rows of no TTR and of the
    windowed output, by frame name); with an even count the lower of the two middle ones (the
    side of less gain). None without a frame both scored with a positive abs rel."""
    refined = {r["name"]: r["abs_rel"] for r in refined_rows}
    pairs = [(r["name"], r["abs_rel"], refined[r["name"]]) for r in base_rows
             if r["name"] in refined and r["abs_rel"] > 0 and np.isfinite(refined[r["name"]])]
    if not pairs:
        return None
    ranked = sorted(pairs, key=lambda p: ((p[1] - p[2]) / p[1], p[0]))
    k = (len(ranked) - 1) // 2
    name, before, after = ranked[k]
    gains = [(b - a) / b for _, b, a in ranked]
    return FigureFrame(name, k + 1, len(ranked), float(before), float(after),
                       float(gains[0]), float(gains[-1]))


def draw_figure(out: Path, bag: Path, drive: str, cfg, image_topic: str,
                sources: dict[str, tuple[Path, str]], frame: FigureFrame) -> Path | None:
    """``out/figure.png``: ``frame``'s image, GT and each output's depth (``sources``: name ->
    (bag, topic); a live frame the node skipped under load has none: left out), with the
    caption of the choice; None when the drive bag has no GT for it."""
    import cv2

    from msg_adapters.image import image_to_depth
    from sfm_ttr_ros.ros.bag import bag_rgb, read_bag
    from sfm_ttr_ros.ros.bag_evaluation import pred_topics
    from sfm_ttr_ros.ros.kitti_bag import DEPTH_GT_TOPIC
    from sfm_ttr_ros.tools.benchmark import qualitative_figure

    stamp = frame.stamp_ns
    gt_msg = next((m for _, _, s, m in read_bag(bag, [DEPTH_GT_TOPIC]) if s == stamp), None)
    if gt_msg is None:
        return None
    image = next(bag_rgb(m) for _, _, s, m in read_bag(bag, [image_topic]) if s == stamp)
    found = {k: next((m for _, _, s, m in read_bag(p, pred_topics(p, topic)) if s == stamp),
                     None)
             for k, (p, topic) in sources.items()}
    preds = {k: image_to_depth(m) for k, m in found.items() if m is not None}
    gt = np.nan_to_num(image_to_depth(gt_msg), nan=0.0)
    title = "\n".join([f"{drive} frame {frame.name}", *frame.caption()])
    fig_path = out / "figure.png"
    cv2.imwrite(str(fig_path), qualitative_figure(image, gt, preds, cfg, title=title))
    return fig_path
