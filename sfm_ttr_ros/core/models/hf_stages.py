"""The staged-encoder protocol for Depth Anything's DINOv2 backbone (transformers).

SfM-TTR computes an encoder's frozen leading stages once per frame and runs only the rest at
every step (:mod:`sfm_ttr_ros.core.refinement.encoder`, ``frozen_encoder_levels``; with
``refinement.trainable_blocks = N`` every stage before the first trained block). For a ViT the
stages are the patch embedding (stage 0) and the transformer blocks (stage i = block i − 1): the
blocks before the first trained one are the most expensive part of a step's forward pass that
no trained parameter can change (8 of 12 blocks of a ViT-S with ``trainable_blocks: 4``).

:class:`Dinov2Stages` runs ``DepthAnythingForDepthEstimation`` as
``Dinov2Backbone.forward`` + ``neck`` + ``head`` do, split at any block: its features are the raw
hidden states of the tapped stages (``backbone.out_features``, before the backbone's final
LayerNorm, which :meth:`Dinov2Stages.decode` applies, so that LayerNorm stays trainable) after a
:class:`PatchGrid` that carries the input's size to the neck and head. Staged and whole forward
passes agree to float rounding (test ``test_staged_depth_anything_matches_its_forward``).
Other transformers models have no staged form here (:func:`dinov2_stages` gives None).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn

#: The modules a Depth Anything backbone needs for the staged forward (Dinov2Backbone).
BACKBONE_PARTS = ("embeddings", "encoder", "layernorm", "stage_names", "out_features")


class PatchGrid(NamedTuple):
    """The network input's size (pixels) and its patch grid, first entry of the features."""

    height: int
    width: int
    patch_height: int
    patch_width: int


class Dinov2Stages:
    """Staged forward of a Depth Anything network ``net`` (see the module docstring); the
    protocol of :mod:`sfm_ttr_ros.core.refinement.encoder`: ``num_stages``, ``level_stages``,
    ``stage_modules(i)``, ``forward_stages(x, start, stop, features)``; plus
    :meth:`stages_before_last_blocks` and :meth:`decode`. ``normalise`` maps the [0, 1] input
    batch to the network's pixel values (the model's processor rule)."""

    def __init__(self, net: nn.Module, normalise) -> None:
        self.net = net
        self.backbone = net.backbone
        self.normalise = normalise
        self.blocks = self.backbone.encoder.layer
        tapped = set(self.backbone.out_features)
        # stage_names: "stem", "stage1", ... one per hidden state
        self.taps = tuple(i for i, name in enumerate(self.backbone.stage_names) if name in tapped)
        self.patch = int(net.config.patch_size)

    @property
    def num_stages(self) -> int:
        return 1 + len(self.blocks)

    @property
    def level_stages(self) -> tuple[int, ...]:
        """Stages run to produce each feature map the neck reads (out_features)."""
        return tuple(t + 1 for t in self.taps)

    def stage_modules(self, index: int) -> list[nn.Module]:
        return [self.backbone.embeddings] if index == 0 else [self.blocks[index - 1]]

    def stages_before_last_blocks(self, count: int) -> int:
        """Leading stages that the last ``count`` blocks leave untrained (embedding included)."""
        return self.num_stages - int(count)

    def forward_stages(self, x: torch.Tensor, start: int, stop: int,
                       features: list) -> tuple[torch.Tensor, list]:
        """Run stages ``start`` … ``stop − 1`` on ``x`` (the [0, 1] batch when ``start`` is 0,
        else the hidden states after stage ``start − 1``), appending the tapped hidden states
        to a copy of ``features`` (which starts with the :class:`PatchGrid`)."""
        out = list(features)
        for i in range(start, stop):
            if i == 0:
                h, w = x.shape[-2:]
                out = [PatchGrid(int(h), int(w), int(h) // self.patch, int(w) // self.patch)]
                x = self.backbone.embeddings(self.normalise(x))
            else:
                x = self.blocks[i - 1](x, None)
            if i in self.taps:
                out.append(x)
        return x, out

    def decode(self, features: list) -> torch.Tensor:
        """Depth Anything's raw output N x 1 x h x w from the staged features: the backbone's
        final LayerNorm on each tapped hidden state, then neck and head (as its forward)."""
        grid, *hidden = features
        backbone = self.backbone
        if backbone.config.apply_layernorm:
            hidden = [backbone.layernorm(s) for s in hidden]
        if backbone.config.reshape_hidden_states:
            hidden = [s[:, 1:].reshape(s.shape[0], grid.patch_height, grid.patch_width, -1)
                      .permute(0, 3, 1, 2).contiguous() for s in hidden]
        hidden = self.net.neck(hidden, grid.patch_height, grid.patch_width)
        out = self.net.head(hidden, grid.patch_height, grid.patch_width)
        return out.unsqueeze(1) if out.dim() == 3 else out


def dinov2_stages(net: nn.Module, normalise) -> Dinov2Stages | None:
    """The staged form of ``net`` when it is a Depth Anything network on a DINOv2-style backbone
    (whose forward :class:`Dinov2Stages` reproduces), else None."""
    if getattr(net.config, "model_type", "") != "depth_anything":
        return None
    backbone = getattr(net, "backbone", None)
    if backbone is None or not all(hasattr(backbone, a) for a in BACKBONE_PARTS):
        return None
    if not isinstance(getattr(backbone.encoder, "layer", None), nn.ModuleList):
        return None
    return Dinov2Stages(net, normalise)
