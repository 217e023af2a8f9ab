"""Which windows' metric estimates anchor a stream's metres (not in the paper).

A window's estimate k (metres per network unit of the weights before it, :mod:`.scale`) can be
wrong: a plane that is not the ground, a reconstruction with a bad scale. No single window is
trusted alone. Two estimates *agree* when max(a/b, b/a) ≤ 1 + ``agreement``; ``ref`` is what the
stream expects of a window's k (:meth:`~.scale.MetricScale.reference`):

* **confirming**: the first estimate is a candidate. A window that agrees with it confirms it once
  ``confirm_windows`` windows (the candidate's included) agree; one that disagrees replaces it
  (a wrong first estimate lasts one window: recovered by the third);
* **confirmed**: a window that agrees anchors the scale again (its own targets m·D_sfm). One that
  disagrees is refined toward the stream's metres instead (targets ref·ŝ·D_sfm: it does not move
  what the network learnt), or refused outright beyond ``max_jump``, and is remembered: the last
  ``reanchor_windows`` windows all disagreeing with the anchor and agreeing with their median
  re-anchor the scale on the newest of them (the anchor was wrong, or the world changed).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from sfm_ttr_ros.core.metric.metric_config import MetricConfig

#: A window's verdict: the first estimate or one that replaces an unconfirmed one; agreeing with
#: the unconfirmed candidate; agreeing with the confirmed anchor; disagreeing with it; moving it.
VERDICTS = ("candidate", "confirms", "agrees", "disagrees", "re-anchors")


def agree(a: float, b: float, tolerance: float) -> bool:
    """Whether two metric estimates agree: max(a/b, b/a) ≤ 1 + ``tolerance``."""
    return max(a / b, b / a) <= 1.0 + tolerance


@dataclass
class Verdict:
    """What a window's estimate does to the anchor (``kind`` in :data:`VERDICTS`), why, and
    the refusal of a window too far from it ("" = refined)."""

    kind: str
    reason: str = ""
    refusal: str = ""


class Anchor:
    """The anchor's state: confirmed or not, the agreeing windows so far, the recent
    disagreeing estimates, and why it last moved."""

    def __init__(self) -> None:
        self.confirmed = False
        self.agreeing = 0  # windows that agreed with the unconfirmed candidate (itself included)
        self.dissent: deque[float] = deque()  # k of the latest windows in a row that disagreed
        self.re_anchors = 0
        self.reason = ""

    def judge(self, cfg: MetricConfig, k: float, ref: float | None) -> Verdict:
        """The verdict on a window's estimate ``k`` against ``ref`` (module docstring)."""
        if ref is None:
            return Verdict("candidate", f"first estimate {k:.4g} m per unit: a candidate")
        if not self.confirmed:
            if agree(k, ref, cfg.agreement):
                return Verdict("confirms")
            return Verdict("candidate", f"estimate {k:.4g} disagrees with the unconfirmed "
                           f"{ref:.4g}: a new candidate")
        if agree(k, ref, cfg.agreement):
            return Verdict("agrees")
        recent = [*self.dissent, k][-cfg.reanchor_windows:]
        mid = float(np.median(recent))
        if (len(recent) >= cfg.reanchor_windows
                and all(agree(x, mid, cfg.agreement) for x in recent)):
            return Verdict("re-anchors", f"{len(recent)} windows agree on {mid:.4g} m per unit, "
                           f"not on the anchor's {ref:.4g}: re-anchored")
        ratio = max(k / ref, ref / k)
        if cfg.max_jump > 0 and ratio > cfg.max_jump:
            return Verdict("disagrees", refusal=(
                f"metric scale {k:.4g} m per unit is {ratio:.2f}x the {ref:.4g} of the weights "
                f"before it > metric.max_jump {cfg.max_jump:g}"))
        return Verdict("disagrees", f"estimate {k:.4g} disagrees with the anchor's {ref:.4g} "
                       f"({ratio:.2f}x): refined in the anchor's metres")

    def record(self, cfg: MetricConfig, verdict: Verdict, k: float) -> None:
        """Remember a measured window's disagreement (refused or not) for re-anchoring."""
        if verdict.kind == "disagrees":
            self.dissent.append(k)
            while len(self.dissent) > cfg.reanchor_windows:
                self.dissent.popleft()
        elif verdict.kind != "re-anchors":
            self.dissent.clear()

    def accepted(self, cfg: MetricConfig, verdict: Verdict) -> bool:
        """An accepted window's verdict moves the anchor; True when the stream's estimates
        start again from this window (a new candidate, a re-anchoring)."""
        if verdict.kind == "candidate":
            self.agreeing, self.reason = 1, verdict.reason
            self.confirmed = cfg.confirm_windows <= 1
        elif verdict.kind == "confirms":
            self.agreeing += 1
            if self.agreeing >= cfg.confirm_windows:
                self.confirmed, self.reason = True, f"confirmed by {self.agreeing} windows"
        elif verdict.kind == "re-anchors":
            self.dissent.clear()
            self.re_anchors += 1
            self.reason = verdict.reason
        return verdict.kind in ("candidate", "re-anchors")
