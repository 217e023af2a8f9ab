"""Stage 2 of SfM-TTR: the network's depth D_nn = h(g(I_j)) of a window's frames, with a cache.

A window predicts its frames twice (with the weights before it: the published depth unless the
window is refined, and D_nn of the alignment; and with the refined weights), and consecutive
windows overlap: the previous window's refined prediction is the next window's "before".
:class:`Predictor` answers an image predicted before with the same weights from a cache
instead of running the network again: the same numbers (up to the last bits a different batch
composition gives; bit for bit with a batch of 1).

The live server predicts every frame as it arrives with a serving copy of the network; under
the ``continue`` weight policy the weights it serves once a window is accepted are the ones the
next window starts from. :class:`LiveDepths` hands those depths over, so a window's frames
served live with the same weights are not predicted again (``ttr.reuse_live_predictions``).
They agree with the window's own prediction bit for bit when both threads have OpenMP teams of
one size; with the default teams (the live thread torch's, the window worker one thread:
core/threads.py) convolutions sum in another order and the depths differ by ~1e-6 relative.
"""

from __future__ import annotations

import itertools
import threading
import weakref
from collections import Counter, OrderedDict
from collections.abc import Sequence

import numpy as np
import torch

from sfm_ttr_ros.core.frames import image_digest
from sfm_ttr_ros.core.models.base import DepthModel

#: Predictions kept for reuse (at least; a larger predict call keeps all of its frames).
PREDICTION_CACHE_FRAMES = 16
#: What :meth:`LiveDepths.figures` counts.
HANDOVER_COUNTS = ("recorded", "handed", "replaced", "dropped_stale_weights",
                   "dropped_released", "dropped_overflow", "binds", "binds_refused")


class Predictor:
    """The network's depth of images, ``batch`` frames per forward pass (``cuda_batch`` when
    the model is on CUDA and it is > 0), with a cache (``reuse`` off: always computed) and
    the live server's depths of the same weights (``live_depths``, when ``reuse_live``).
    ``computed`` / ``reused`` / ``reused_live`` count the images the network ran on, those the
    cache answered and those the live server's depths answered."""

    def __init__(self, model: DepthModel, batch: int = 2, reuse: bool = True,
                 cuda_batch: int = 0, reuse_live: bool = True):
        self.model = model
        self.batch = batch
        self.cuda_batch = cuda_batch
        self.reuse = reuse
        self.reuse_live = reuse_live
        self.live_depths: LiveDepths | None = None  # set by the stream's live serving
        self._key: tuple | None = None  # the weights of _cache
        self._cache: OrderedDict[bytes, np.ndarray] = OrderedDict()
        # Predictions of the ORIGINAL weights survive refinement and the next reset: under the
        # reset policy the overlap frames' "before" depths are those of the previous window.
        self._original_key: tuple | None = self.weights_key()
        self._original_cache: OrderedDict[bytes, np.ndarray] = OrderedDict()
        self.computed = 0
        self.reused = 0
        self.reused_live = 0

    def original_restored(self) -> None:
        """The start-up weights are back: their predictions count as the original's again."""
        self._original_key = self.weights_key()

    def predict(self, images: Sequence[np.ndarray],
                tally: dict[str, int] | None = None) -> list[np.ndarray]:
        """Depth (H x W float32, network units) of each image with the current weights.

        An image whose pixels were predicted before with the same weights is not run through
        the network again (each call returns new arrays; at most
        max(PREDICTION_CACHE_FRAMES, len(images)) depth maps are kept). The weights are
        identified by every parameter and buffer of the model (storage and in-place version
        counter), so an optimizer step, ``load_state_dict``, a BatchNorm statistics update or a
        move to another device all invalidate the cache. The predictions of the original weights
        are kept apart and found again after a reset to them. An image the cache does not hold
        may come from :attr:`live_depths` (:meth:`LiveDepths.take`: served live with these very
        weights). Call :meth:`clear` after changing anything else the network's output depends
        on. ``tally`` (optional) gets this call's ``computed`` / ``reused`` / ``reused_live``."""
        key = self.weights_key() if self.reuse else None
        if key is None:
            self.clear()
            self._count(tally, computed=len(images))
            return self.run(images)
        cache = self._cache_for(key)
        digests = [image_digest(np.asarray(im)) for im in images]
        live = self._from_live(digests, cache, key)
        todo: dict[bytes, int] = {}
        for i, d in enumerate(digests):
            if d not in cache and d not in todo and d not in live:
                todo[d] = i
        fresh = dict(zip(todo, self.run([images[i] for i in todo.values()]), strict=True))
        self._count(tally, computed=len(fresh), reused_live=len(live),
                    reused=len(images) - len(fresh) - len(live))
        fresh.update(live)
        out = []
        for d in digests:
            depth = fresh[d] if d in fresh else cache[d]
            cache[d] = depth
            cache.move_to_end(d)
            out.append(depth.copy())
        while len(cache) > max(PREDICTION_CACHE_FRAMES, len(images)):
            cache.popitem(last=False)
        return out

    def _from_live(self, digests: list[bytes], cache: OrderedDict[bytes, np.ndarray],
                   key: tuple) -> dict[bytes, np.ndarray]:
        """The live server's depths of the images the cache does not hold, made with the
        weights ``key`` names."""
        handover = self.live_depths
        if handover is None or not self.reuse_live:
            return {}
        found = {}
        for d in dict.fromkeys(digests):
            if d not in cache and (depth := handover.take(d, key)) is not None:
                found[d] = depth
        return found

    def _count(self, tally: dict[str, int] | None, **counts: int) -> None:
        for name, n in counts.items():
            setattr(self, name, getattr(self, name) + n)
            if tally is not None:
                tally[name] = tally.get(name, 0) + n

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

    def run_as_is(self, images: Sequence[np.ndarray]) -> list[np.ndarray]:
        """:meth:`run` mid-refinement (the interim gate): every module's train/eval mode put
        back after (bn_mode "train" keeps the encoder's BatchNorm training)."""
        modes = [(m, m.training) for m in self.model.modules()]
        try:
            return self.run(images)
        finally:
            for m, training in modes:
                m.training = training

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


def same_weights(model: DepthModel, other: DepthModel) -> bool:
    """Whether two networks compute the same function bit for bit on one thread team: the same
    class and output settings, every parameter and buffer equal in value, dtype, device and
    memory layout (channels-last convolutions round differently)."""
    settings = ("input_size", "min_depth", "max_depth")
    if type(model) is not type(other) or any(
            getattr(model, k, None) != getattr(other, k, None) for k in settings):
        return False
    a, b = model.state_dict(), other.state_dict()
    if a.keys() != b.keys():
        return False
    return all(x.dtype == b[k].dtype and x.device == b[k].device and x.stride() == b[k].stride()
               and torch.equal(x, b[k]) for k, x in a.items())


class LiveDepths:
    """The live server's network depths of its newest frames, handed to the window that takes
    them (Sec. 3's D_nn computed once): a thread-safe, bounded hand-over.

    The live server :meth:`record`\\ s each frame it served with the *generation* of the served
    weights (:attr:`~sfm_ttr_ros.core.stream.serving.ServingModel.generation`: it changes with
    every swap, interim previews and reverts included) and the raw depth (network units, before
    any metres factor, at the image's size: what :meth:`Predictor.predict` gives). When a window
    is accepted and its weights are swapped into serving, :meth:`bind` ties that generation to
    the window model's :meth:`Predictor.weights_key`, after checking that the two copies hold the
    same weights. :meth:`take` hands a depth over only when its generation is the bound one and
    the Predictor's weights key is still the bound one (not refined, reset or rolled back since):
    frames served with interim, reverted or older weights are predicted again.

    Memory: at most ``capacity`` depths (the next window's frames), the oldest dropped first;
    entries of older weights drop as soon as newer weights are served, and an entry drops when
    its image is freed (a released image, a stale frame the stream let go)."""

    def __init__(self, capacity: int = PREDICTION_CACHE_FRAMES) -> None:
        self.capacity = max(1, int(capacity))
        self._lock = threading.RLock()  # a freed image's callback may run inside a call here
        # digest -> (generation, raw depth, weak reference to the image it was predicted from)
        self._entries: OrderedDict[bytes, tuple[int, np.ndarray, weakref.ref]] = OrderedDict()
        self._bound: tuple[int, tuple] | None = None  # (generation, the window model's key)
        self.counts: Counter[str] = Counter()  # recorded, handed, dropped_*, binds*

    def record(self, image: np.ndarray, generation: int, depth: np.ndarray) -> None:
        """The live server served ``image`` with the weights of ``generation``; ``depth``: the
        network's depth (a copy is kept when ``generation`` is the bound one: nothing else
        could be handed over)."""
        bound = self._bound
        if bound is None or generation != bound[0]:  # nothing could take it
            with self._lock:
                self._drop_older(generation)
            return
        digest = image_digest(np.asarray(image))
        with self._lock:
            self._drop_older(generation)
            if self._bound is None or generation != self._bound[0]:
                return
            if self._entries.pop(digest, None) is not None:  # the same pixels again
                self.counts["replaced"] += 1
            self._entries[digest] = (generation, np.array(depth, np.float32, copy=True),
                                     weakref.ref(image, self._freed(digest)))
            self.counts["recorded"] += 1
            self._trim()

    def bind(self, generation: int, predictor: Predictor, served: DepthModel,
             capacity: int | None = None) -> bool:
        """Serving swapped in the window model's weights as ``generation``: its depths may go to
        ``predictor`` while its weights stay as they are now (``capacity``: the next window's
        frames, when given). Refused (nothing recorded nor handed over until the next bind)
        when the predictor takes no live depths or the serving copy computes something
        else."""
        ok = predictor.reuse_live and predictor.reuse and same_weights(predictor.model, served)
        with self._lock:
            self._bound = (generation, predictor.weights_key()) if ok else None
            self.counts["binds" if ok else "binds_refused"] += 1
            if capacity is not None:
                self.capacity = max(1, int(capacity))
            self._drop_older(generation if ok else float("inf"))
            self._trim()
        return ok

    def unbind(self) -> None:
        """Nothing is handed over (nor recorded) until the next :meth:`bind`."""
        with self._lock:
            self._bound = None
            self._drop_older(float("inf"))

    def take(self, digest: bytes, key: tuple | None) -> np.ndarray | None:
        """The recorded depth of the image with ``digest`` if it was made with the weights that
        ``key`` (the caller's :meth:`Predictor.weights_key`) names; it leaves the hand-over."""
        with self._lock:
            entry = self._entries.get(digest)
            if entry is None or key is None or self._bound is None \
                    or (entry[0], key) != self._bound or entry[2]() is None:
                return None
            del self._entries[digest]
            self.counts["handed"] += 1
            return entry[1]

    def figures(self) -> dict[str, int]:
        """Depths held now and the counts: recorded, handed, replaced (the same pixels again),
        dropped (stale weights, released images, overflow), binds (refused)."""
        with self._lock:
            return {"held": len(self._entries), **{k: self.counts[k] for k in HANDOVER_COUNTS}}

    def __len__(self) -> int:
        with self._lock:
            return len(self._entries)

    def _drop_older(self, generation: int) -> None:
        """Entries of weights served before ``generation`` can never be handed over."""
        for d in [d for d, e in self._entries.items() if e[0] < generation]:
            del self._entries[d]
            self.counts["dropped_stale_weights"] += 1

    def _trim(self) -> None:
        while len(self._entries) > self.capacity:
            self._entries.popitem(last=False)
            self.counts["dropped_overflow"] += 1

    def _freed(self, digest: bytes):
        """A callback for the image's weak reference: its entry goes with the image."""
        def drop(ref: weakref.ref) -> None:
            with self._lock:
                entry = self._entries.get(digest)
                if entry is not None and entry[2] is ref:
                    del self._entries[digest]
                    self.counts["dropped_released"] += 1
        return drop
