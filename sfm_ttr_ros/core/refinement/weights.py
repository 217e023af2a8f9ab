"""The encoder's weights across windows: where each window starts, what it keeps.

One :class:`WeightPolicy` per :class:`~sfm_ttr_ros.core.pipeline.SfmTTR`, after
``TTRConfig.weight_policy`` (:data:`WEIGHT_POLICIES`):

* ``reset``: every window starts from the start-up weights (the paper's per-sequence
  refinement, Sec. 3.3, one window at a time);
* ``continue``: every window starts from the last ACCEPTED window's weights; a refused,
  rolled-back or failed window leaves them as they were.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

from sfm_ttr_ros.core.models.base import DepthModel
from sfm_ttr_ros.core.refinement.encoder import restore_encoder, snapshot_encoder
from sfm_ttr_ros.core.refinement.refinement_config import WEIGHT_POLICIES

__all__ = ["WEIGHT_POLICIES", "WeightPolicy"]


class WeightPolicy:
    """The start-up snapshot and the rollback point of the refining window."""

    def __init__(self, model: DepthModel, on_reset: Callable[[], None] | None = None):
        self.model = model
        self.original = snapshot_encoder(model)  # the start-up weights
        self._on_reset = on_reset  # called once the start-up weights are back (reset)

    def reset(self) -> None:
        """Back to the start-up weights."""
        restore_encoder(self.model, self.original)
        if self._on_reset is not None:
            self._on_reset()

    def load_start(self, weight_policy: str) -> None:
        """A window begins: load the weights it starts from (under ``reset`` the start-up
        weights; under ``continue`` the model keeps the weights it has)."""
        if weight_policy == "reset":
            self.reset()

    def rollback_point(self, weight_policy: str) -> dict:
        """The weights before the window (what :meth:`refuse` restores), taken just before its
        first step; under ``reset`` the start-up weights."""
        return self.original if weight_policy == "reset" else snapshot_encoder(self.model)

    @contextmanager
    def restored_on_error(self, start: dict) -> Iterator[None]:
        """A window that raises while refining or judging leaves the weights before it
        (``start``, :meth:`rollback_point`)."""
        try:
            yield
        except Exception:
            self.refuse(start)
            raise

    def refuse(self, start: dict) -> None:
        """A refined window is not kept (rolled back, or refused by a check): the weights before
        it come back."""
        restore_encoder(self.model, start)
