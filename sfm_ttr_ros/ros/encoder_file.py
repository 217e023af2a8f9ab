"""The refined encoder on disk: ``load_weights_path`` read at start-up, ``save_weights_path``
written at shutdown (docs/node.md, "Refined weights, shutdown"). Only the encoder is refined,
so only its state dict is stored."""

from __future__ import annotations

from pathlib import Path

import torch

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.models.base import DepthModel


def load_encoder(model: DepthModel, path: str) -> None:
    """Load the encoder state dict at ``path`` into ``model``; a missing or mismatching file is
    an :class:`InputError` (the node cannot start)."""
    if not Path(path).is_file():
        raise InputError(f"load_weights_path: file not found: {path}")
    try:
        state = torch.load(path, map_location=model.device, weights_only=True)
        model.encoder.load_state_dict(state)
    except Exception as exc:
        raise InputError(f"load_weights_path: cannot load encoder weights from {path}: "
                         f"{type(exc).__name__}: {exc}") from exc


def save_encoder(model: DepthModel, path: str, logger) -> None:
    """Save ``model``'s encoder state dict to ``path`` (parent folders created); a path that
    cannot be written (unwritable, full disk) is logged, never raised: the exit stays clean."""
    try:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        torch.save(model.encoder.state_dict(), path)
        logger.info(f"refined encoder saved to {path}")
    except Exception as exc:
        logger.error(f"cannot save the encoder to {path}: {type(exc).__name__}: {exc}")
