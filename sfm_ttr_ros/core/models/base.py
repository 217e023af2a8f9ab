"""The one small interface every depth network implements: D_nn = h(g(I)).

SfM-TTR (Izquierdo & Civera, CVPR 2023, Sec. 3.3) refines the encoder ``g`` only and keeps the
decoder ``h`` frozen, so a model must expose the two as separate modules and say how its raw
output turns into metric-free depth.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from sfm_ttr_ros.core.errors import InputError

# Monodepth2's depth range: depth = 1 / (1/max + (1/min - 1/max) * sigmoid).
MIN_DEPTH = 0.1
MAX_DEPTH = 100.0


class ModelLoadError(InputError):
    """A model or its weights could not be built or loaded (missing file, wrong layout, shape
    mismatch, bad plug-in). An :class:`~sfm_ttr_ros.core.frames.InputError`, hence a
    ``ValueError``."""


def disp_to_depth(sigmoid: torch.Tensor, min_depth: float = MIN_DEPTH,
                  max_depth: float = MAX_DEPTH) -> torch.Tensor:
    """Monodepth2's sigmoid-disparity → depth: D = 1 / (1/max + (1/min − 1/max)·σ)."""
    min_disp, max_disp = 1.0 / max_depth, 1.0 / min_depth
    return 1.0 / (min_disp + (max_disp - min_disp) * sigmoid)


class DepthModel(nn.Module):
    """An encoder–decoder depth network.

    Subclasses (or :class:`EncoderDecoder` with any two modules) provide:

    * ``encoder``: ``nn.Module`` mapping a normalised-to-[0, 1] RGB batch N x 3 x H x W to
      whatever the decoder consumes (Monodepth2: a list of 5 feature maps). The only part that
      SfM-TTR trains.
    * ``decoder``: ``nn.Module`` mapping the encoder's output to the raw network output.
    * :meth:`output_to_depth`: raw output → depth N x 1 x H x W at the input resolution.
    * ``input_size``: (height, width) the network runs at (multiples of 32 for Monodepth2).
    """

    encoder: nn.Module
    decoder: nn.Module
    input_size: tuple[int, int]

    def output_to_depth(self, output) -> torch.Tensor:
        raise NotImplementedError

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Depth N x 1 x h x w for an input batch N x 3 x h x w with values in [0, 1]."""
        return self.depth_from_features(self.encoder(x))

    def depth_from_features(self, features) -> torch.Tensor:
        """D_nn = h(·) for the encoder's output g(I): decoder, then :meth:`output_to_depth`."""
        return self.output_to_depth(self.decoder(features))

    @property
    def staged_encoder(self):
        """What implements the staged-encoder protocol of :mod:`sfm_ttr_ros.core.refinement.encoder`
        (frozen leading stages computed once per frame) for this model: the encoder itself
        here; a model whose encoder is split elsewhere overrides it."""
        return self.encoder

    # -- helpers shared by every model -------------------------------------------------------
    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    def preprocess(self, images: np.ndarray | list[np.ndarray]) -> torch.Tensor:
        """uint8 RGB H x W x 3 image(s) → N x 3 x h x w float batch in [0, 1] at ``input_size``."""
        if isinstance(images, np.ndarray) and images.ndim == 3:
            images = [images]
        h, w = self.input_size
        if self.device.type == "cuda":
            x = _to_cuda_float(images, self.device)
        else:
            batch = []
            for im in images:
                t = torch.from_numpy(np.ascontiguousarray(im)).permute(2, 0, 1).float() / 255.0
                batch.append(t)
            x = torch.stack(batch).to(self.device)
        if x.shape[-2:] != (h, w):
            x = F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
        return x

    @torch.inference_mode()
    def predict(self, images: np.ndarray | list[np.ndarray],
                out_size: tuple[int, int] | None = None) -> np.ndarray:
        """Depth maps (N x H x W float32) for uint8 RGB images, resized to ``out_size`` (h, w)
        or to the images' own size. Runs in eval mode and restores the previous mode."""
        was_training = self.training
        self.eval()
        try:
            if isinstance(images, np.ndarray) and images.ndim == 3:
                images = [images]
            if out_size is None:
                out_size = images[0].shape[:2]
            depth = self(self.preprocess(images))
            if tuple(depth.shape[-2:]) != tuple(out_size):
                depth = F.interpolate(depth, size=tuple(out_size), mode="bilinear",
                                      align_corners=False)
            return depth[:, 0].float().cpu().numpy()
        finally:
            self.train(was_training)


def _to_cuda_float(images, device: torch.device) -> torch.Tensor:
    """uint8 RGB images → N x 3 x H x W float in [0, 1] on a CUDA ``device``: the uint8 pixels
    copied from pinned memory without blocking (a quarter of the bytes of float, no pageable
    staging copy), converted on the device (the same numbers as on the host)."""
    batch = torch.from_numpy(np.stack([np.ascontiguousarray(im) for im in images]))
    x = batch.pin_memory().to(device, non_blocking=True)
    return x.permute(0, 3, 1, 2).contiguous().float() / 255.0  # N x 3 x H x W, as on the host


#: (height, width) of :func:`warm_up_image` for a model that sizes its own input (``()``).
WARM_UP_FREE_SIZE = (256, 256)


def warm_up_image(model: DepthModel) -> np.ndarray:
    """A grey uint8 RGB frame at ``model``'s input size (:data:`WARM_UP_FREE_SIZE` for a model
    that sizes its own input): what the warm-ups (serving, window worker) run through it."""
    size = tuple(getattr(model, "input_size", ()) or ())
    h, w = (int(v) for v in size) if len(size) == 2 else WARM_UP_FREE_SIZE
    return np.full((h, w, 3), 128, np.uint8)


def finite_state(state: dict[str, torch.Tensor]) -> bool:
    """True when every floating-point tensor of a state dict is finite."""
    return all(bool(torch.isfinite(t).all()) for t in state.values()
               if torch.is_tensor(t) and t.is_floating_point())


class EncoderDecoder(DepthModel):
    """Any encoder and decoder whose decoder outputs Monodepth2-style sigmoid disparity.

    ``decoder(encoder(x))`` may return a tensor N x 1 x h x w or Monodepth2's dict with key
    ``("disp", 0)``.
    """

    def __init__(self, encoder: nn.Module, decoder: nn.Module, input_size: tuple[int, int],
                 min_depth: float = MIN_DEPTH, max_depth: float = MAX_DEPTH):
        super().__init__()
        self.encoder = encoder
        self.decoder = decoder
        self.input_size = (int(input_size[0]), int(input_size[1]))
        self.min_depth = float(min_depth)
        self.max_depth = float(max_depth)

    def output_to_depth(self, output) -> torch.Tensor:
        if isinstance(output, dict):
            output = output[("disp", 0)]
        return disp_to_depth(output, self.min_depth, self.max_depth)
