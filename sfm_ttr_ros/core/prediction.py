"""Stage 2 of SfM-TTR: the network's depth D_nn = h(g(I_j)) of a window's frames, with a cache.

A window predicts its frames twice (with the weights before it: the published depth unless the
window is refined, and D_nn of the alignment; and with the refined weights), and consecutive
windows overlap: the previous window's refined prediction is the next window's "before".
:class:`Predictor` answers an image predicted before with the same weights from a cache
instead of running the network again: the same numbers (up to the last bits a different batch
composition gives; bit for bit with a batch of 1).
"""

from __future__ import annotations

import itertools
from collections import OrderedDict
from collections.abc import Sequence

import numpy as np

from sfm_ttr_ros.core.models.base import DepthModel
from sfm_ttr_ros.core.sfm.reconstruction import image_digest

#: Predictions kept for reuse (at least; a larger predict call keeps all of its frames).
PREDICTION_CACHE_FRAMES = 16


class Predictor:
    """The network's depth of images, ``batch`` frames per forward pass (``cuda_batch`` when
    the model is on CUDA and it is > 0), with a cache (``reuse`` off: always computed).
    ``computed`` / ``reused`` count the images the network ran on and those the cache
    answered."""

    def __init__(self, model: DepthModel, batch: int = 2, reuse: bool = True,
                 cuda_batch: int = 0):
        self.model = model
        self.batch = batch
        self.cuda_batch = cuda_batch
        self.reuse = reuse
        self._key: tuple | None = None  # the weights of _cache
        self._cache: OrderedDict[bytes, np.ndarray] = OrderedDict()
        # Predictions of the ORIGINAL weights survive refinement and the next reset: under the
        # reset policy the overlap frames' "before" depths are those of the previous window.
        self._original_key: tuple | None = self.weights_key()
        self._original_cache: OrderedDict[bytes, np.ndarray] = OrderedDict()
        self.computed = 0
        self.reused = 0

    def original_restored(self) -> None:
        """The start-up weights are back: their predictions count as the original's again."""
        self._original_key = self.weights_key()

    def predict(self, images: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Depth (H x W float32, network units) of each image with the current weights.

        An image whose pixels were predicted before with the same weights is not run through
        the network again (each call returns new arrays; at most
        max(PREDICTION_CACHE_FRAMES, len(images)) depth maps are kept). The weights are
        identified by every parameter and buffer of the model (storage and in-place version
        counter), so an optimizer step, ``load_state_dict``, a BatchNorm statistics update or a
        move to another device all invalidate the cache. The predictions of the original weights
        are kept apart and found again after a reset to them. Call :meth:`clear` after changing
        anything else the network's output depends on."""
        key = self.weights_key() if self.reuse else None
        if key is None:
            self.clear()
            self.computed += len(images)
            return self.run(images)
        cache = self._cache_for(key)
        digests = [image_digest(np.asarray(im)) for im in images]
        todo: dict[bytes, int] = {}
        for i, d in enumerate(digests):
            if d not in cache and d not in todo:
                todo[d] = i
        fresh = dict(zip(todo, self.run([images[i] for i in todo.values()]), strict=True))
        self.computed += len(fresh)
        self.reused += len(images) - len(fresh)
        out = []
        for d in digests:
            depth = fresh[d] if d in fresh else cache[d]
            cache[d] = depth
            cache.move_to_end(d)
            out.append(depth.copy())
        while len(cache) > max(PREDICTION_CACHE_FRAMES, len(images)):
            cache.popitem(last=False)
        return out

    def _cache_for(self, key: tuple) -> OrderedDict[bytes, np.ndarray]:
        if key == self._original_key:
            return self._original_cache
        if key != self._key:
            self._key = key
            self._cache.clear()
        return self._cache

    def clear(self) -> None:
        self._key = None
        self._cache.clear()
        self._original_cache.clear()
        self._original_key = None  # until the next reset: nothing is known original

    @property
    def effective_batch(self) -> int:
        """Frames per forward pass on the model's device now: ``cuda_batch`` on CUDA (when
        > 0: a window in one pass, the GPU being launch-bound at small batches), else
        ``batch``."""
        m = self.model
        on_cuda = getattr(m, "device", None) is not None and m.device.type == "cuda"
        return max(1, self.cuda_batch if on_cuda and self.cuda_batch > 0 else self.batch)

    def run(self, images: Sequence[np.ndarray]) -> list[np.ndarray]:
        """The network on ``images``, :attr:`effective_batch` at a time, no cache."""
        out: list[np.ndarray] = []
        b = self.effective_batch
        for i in range(0, len(images), b):
            out.extend(self.model.predict(list(images[i:i + b])))
        return out

    def weights_key(self) -> tuple | None:
        """Changes whenever a tensor of the model is replaced or modified in place."""
        m = self.model
        try:
            tensors = tuple((t.data_ptr(), t._version)
                            for t in itertools.chain(m.parameters(), m.buffers()))
        except (RuntimeError, AttributeError):  # e.g. inference tensors: no version counter
            return None
        return (id(m), tuple(getattr(m, "input_size", ())), str(m.device),
                getattr(m, "min_depth", None), getattr(m, "max_depth", None), tensors)
