"""A depth network turned into an affine-invariant inverse-depth network, for measurements.

:class:`AffineInverse` outputs p = a_j / D + b_j for the wrapped network's depth D, with a scale
a_j in [0.5, 5] and a shift b_j in [0, 0.3·a_j] drawn at random PER FRAME: what a MiDaS / Depth
Anything relative head promises and no more. It lets the affine path (per-frame
scale-and-shift alignment, :mod:`sfm_ttr_ros.core.alignment.affine`) be compared with the paper's
scale-only path on the same network and the same SfM (tests/test_affine_refinement.py,
docs/decisions.md, "Studies").

A frame keeps its pair between prediction and refinement: it is recognised by the nearest
per-channel mean of its network input among the images given at construction, not by an exact
key (an exact key, a pixel sum rounded at 1e-3, failed once when a frame lay 2.5e-5 from a
rounding edge: last-bit differences between a lone and a batched input are ~1e-7, frames' means
lie ~1e-3 apart). The wrapper runs the whole network at every call: use it with
``frozen_encoder_levels`` 0.
"""

from __future__ import annotations

import numpy as np
import torch

from sfm_ttr_ros.core.models.base import DepthModel


class AffineInverse(DepthModel):
    """``inner``'s depth D as p = a_j / D + b_j, (a_j, b_j) random per frame of ``images``."""

    output_kind = "relative_inverse_depth"

    def __init__(self, inner: DepthModel, images, seed: int = 7):
        super().__init__()
        self.inner = inner
        self.fingerprints = torch.cat([self.fingerprint(inner.preprocess(list(images[i:i + 32])))
                                       for i in range(0, len(images), 32)])
        rng = np.random.default_rng(seed)
        a = rng.uniform(0.5, 5.0, len(images))
        self.pairs = np.stack([a, a * rng.uniform(0.0, 0.3, len(images))], axis=1)

    encoder = property(lambda self: self.inner.encoder)
    decoder = property(lambda self: self.inner.decoder)
    input_size = property(lambda self: self.inner.input_size)

    def preprocess(self, images):
        return self.inner.preprocess(images)

    @staticmethod
    def fingerprint(x: torch.Tensor) -> torch.Tensor:
        return x.detach().double().mean(dim=(2, 3)).cpu()

    def frame_affine(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(a, b), N x 1 x 1 x 1 each, of the frames ``x`` shows."""
        dist = torch.cdist(self.fingerprint(x), self.fingerprints)
        nearest = dist.argmin(dim=1)
        if float(dist.min(dim=1).values.max()) >= 1e-5:
            raise ValueError("an input that is none of the wrapper's frames")
        ab = torch.as_tensor(self.pairs[nearest.numpy()], dtype=x.dtype, device=x.device)
        return ab[:, 0].view(-1, 1, 1, 1), ab[:, 1].view(-1, 1, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        a, b = self.frame_affine(x)
        return a / self.inner(x) + b
