"""The encoder's weights across windows: where each window starts, what it keeps.

One :class:`WeightPolicy` per :class:`~sfm_ttr_ros.core.pipeline.SfmTTR`, after
``TTRConfig.weight_policy`` (:data:`WEIGHT_POLICIES`):

* ``reset``: every window starts from the start-up weights (the paper's per-sequence
  refinement, Sec. 3.3, one window at a time);
* ``continue``: every window starts from the last ACCEPTED window's weights; a refused,
  rolled-back or failed window leaves them as they were;
* ``continual``: as ``continue``, with a replay of earlier accepted windows' supervision
  (Eq. (5) terms of ``replay_windows`` windows, ``replay_ratio`` of the steps) and an L2 pull
  λ·Σ‖θ − θ₀‖² toward the start-up encoder (``anchor_weight``), see
  :func:`~sfm_ttr_ros.core.refinement.encoder.refine_encoder`.

A window that starts from carried weights (``continue`` / ``continual`` after an accepted
window) runs ``carried_steps`` instead of ``refinement.steps`` when that is set.
"""

from __future__ import annotations

import dataclasses
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from sfm_ttr_ros.core.models.base import DepthModel
from sfm_ttr_ros.core.refinement.encoder import RefinementConfig, restore_encoder, snapshot_encoder
from sfm_ttr_ros.core.refinement.supervision import FrameSupervision, at_network_size

WEIGHT_POLICIES = ("reset", "continue", "continual")


class WeightSettings(Protocol):
    """The options a :class:`WeightPolicy` reads (the fields of ``TTRConfig`` it owns)."""

    refinement: RefinementConfig
    weight_policy: str
    replay_windows: int
    replay_ratio: float
    anchor_weight: float
    carried_steps: int


@dataclass
class RefinementPlan:
    """How one window refines, as its weight policy says: the refinement's settings (steps:
    ``carried_steps`` from carried weights), the replayed frames and the anchor (continual),
    and ``start``, the weights before the window (what :meth:`WeightPolicy.refuse` restores)."""

    refinement: RefinementConfig
    start: dict
    replay: list[FrameSupervision]
    replay_ratio: float
    anchor: dict | None
    anchor_weight: float


class WeightPolicy:
    """The start-up snapshot, the carried state, the continual replay and anchor, and the
    rollback point of the refining window."""

    def __init__(self, model: DepthModel, on_reset: Callable[[], None] | None = None):
        self.model = model
        self.original = snapshot_encoder(model)  # the start-up weights
        self.carried = False  # the encoder holds an accepted window's weights, not start-up's
        # continual policy: the supervision of the last replay_windows accepted windows
        self.replay: deque[list[FrameSupervision]] = deque()
        self._on_reset = on_reset  # called once the start-up weights are back (reset)

    def reset(self) -> None:
        """Back to the start-up weights."""
        restore_encoder(self.model, self.original)
        self.carried = False
        if self._on_reset is not None:
            self._on_reset()

    def begin_window(self, config: WeightSettings) -> None:
        """A window begins: under ``reset`` from the start-up weights."""
        if config.weight_policy == "reset":
            self.reset()

    def begin(self, config: WeightSettings) -> RefinementPlan:
        """The window's refinement as the policy says, taken just before its first step."""
        continual = config.weight_policy == "continual"
        refinement = config.refinement
        if self.carried and config.carried_steps > 0:
            refinement = dataclasses.replace(refinement, steps=config.carried_steps)
        return RefinementPlan(
            refinement,
            # the weights before the window; under "reset" they are the start-up weights
            start=self.original if config.weight_policy == "reset"
            else snapshot_encoder(self.model),
            replay=[s for window in self.replay for s in window] if continual else [],
            replay_ratio=config.replay_ratio,
            anchor=self.original if continual and config.anchor_weight > 0 else None,
            anchor_weight=config.anchor_weight)

    def refuse(self, plan: RefinementPlan) -> None:
        """A refined window is not kept (rolled back, or refused by a check): the weights before
        it come back; the carried state and the replay stay as they were."""
        restore_encoder(self.model, plan.start)

    def accept(self, config: WeightSettings, supervision: list[FrameSupervision]) -> None:
        """A refined window is kept: the next window starts from its weights (but under
        ``reset``) and, under ``continual``, replays its supervision."""
        self.carried = config.weight_policy != "reset"
        if config.weight_policy == "continual" and config.replay_windows > 0:
            self.replay.append(self._replay_frames(supervision))
            while len(self.replay) > config.replay_windows:
                self.replay.popleft()

    def _replay_frames(self, sup: list[FrameSupervision]) -> list[FrameSupervision]:
        """A window's supervision as the replay keeps it: with a model whose input is the image
        resized to ``input_size`` (:meth:`DepthModel.preprocess`) each image at that size
        (:func:`~sfm_ttr_ros.core.refinement.supervision.at_network_size`; 3 windows of 15 KITTI
        frames: 7 MB instead of 63 MB); other models' images (normalised, or sized by their own
        processor) as they are."""
        if (len(tuple(getattr(self.model, "input_size", ()))) != 2
                or type(self.model).preprocess is not DepthModel.preprocess):
            return list(sup)
        return [at_network_size(s, self.model) for s in sup]
