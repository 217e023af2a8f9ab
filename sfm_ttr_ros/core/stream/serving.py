"""The serving copy of the network: every frame's live depth, with the newest accepted weights.

SfM-TTR refines the encoder of one network over a window of frames (Sec. 3.3); while that
runs (seconds to tens of seconds on a CPU) the robot still needs depth for every frame. A
:class:`ServingModel` holds a second copy of the network that answers at once. When a window's
refinement is accepted its encoder weights are swapped in with :meth:`ServingModel.update`:
the swap holds the same lock as :meth:`ServingModel.predict`, so a prediction runs entirely on
the old or entirely on the new weights, never on half a state dict. ``version`` names the
window that produced the weights being served (0 = the start-up weights) and ``age_s`` says how
long ago they were swapped in.

Interim weights (``serve_every_steps`` N): while a window refines, :meth:`preview` serves its
weights on a schedule that starts early and settles to the period (:func:`interim_due`: after
N/4 and N/2 steps, then every N); the first preview of a window keeps a copy of the weights it
replaces, :meth:`update` (the window was accepted) drops that copy and :meth:`revert` (it was
not: cancelled, rolled back, refused) puts them back, so a window that fails leaves the served
weights as they were before it. ``interim_step`` is the refinement step of the previewed weights
(0: a finished window's, or the start-up weights). ``generation`` counts every swap (update,
preview, revert): two predictions with one generation ran on the same weights, which is what the
hand-over of live depths to the windows checks (core/prediction.py,
:class:`~sfm_ttr_ros.core.prediction.LiveDepths`).

On CUDA the serving copy predicts on a stream of its own with a higher priority than the
refinement's (:data:`LIVE_STREAM_PRIORITY`): its kernels are not queued behind a window's
replays (which :class:`~sfm_ttr_ros.core.refinement.graph_cache.ReplayPacer` bounds), and the
device schedules them first. New weights are copied in on the caller's stream; the live stream
waits for that copy (an event) before its next prediction. On the CPU none of this exists.
"""

from __future__ import annotations

import contextlib
import copy
import threading
import time
from dataclasses import dataclass

import numpy as np
import torch

from sfm_ttr_ros.core.metric.scale import in_metres
from sfm_ttr_ros.core.models.base import DepthModel, finite_state, warm_up_image

#: The live stream's priority (CUDA: lower is more urgent; the default stream's is 0)
LIVE_STREAM_PRIORITY = -1


def interim_due(step: int, every: int) -> bool:
    """Whether a window's weights after refinement step ``step`` (1-based) are served as
    interim weights under ``serve_every_steps`` = ``every`` (0: never): after ``every`` // 4
    and ``every`` // 2 steps (the first gain reaches the live output a quarter of a period
    in, which matters most for the stream's first window, when the start-up weights are all
    there is), then every ``every`` steps."""
    if every <= 0 or step <= 0:
        return False
    return step % every == 0 or step in (every // 4, every // 2)


@dataclass(frozen=True)
class Served:
    """One live prediction: ``depth`` in the outputs' units (metres when the served weights
    have a factor), ``raw`` the network's depth (network units; the same array when there is no
    factor), the weights' ``version`` (the window that made them), ``generation`` (the
    swap) and ``metres_per_unit`` (the factor ``depth`` was multiplied by; None: network
    units)."""

    depth: np.ndarray
    raw: np.ndarray
    version: int
    generation: int
    metres_per_unit: float | None = None


def live_stream(device: torch.device):
    """A CUDA stream for live predictions, more urgent than the default one; None off CUDA."""
    if device.type != "cuda":
        return None
    return torch.cuda.Stream(device, priority=LIVE_STREAM_PRIORITY)


class ServingModel:
    """A thread-safe copy of ``model`` for live prediction, updated atomically."""

    def __init__(self, model: DepthModel) -> None:
        self._model = copy.deepcopy(model).eval()
        for p in self._model.parameters():
            p.requires_grad_(False)
        self._lock = threading.Lock()
        self._version = 0
        self._generation = 0  # + 1 at every swap of the served weights
        self._updated = time.monotonic()
        self._interim_step = 0
        # metres per network unit of the served weights (core/metric/); None: network units
        self._metres_per_unit: float | None = None
        # (encoder state, version, swapped-in time, metric factor) a window's first preview
        # replaced
        self._before_preview: tuple[dict[str, torch.Tensor], int, float, float | None] | None \
            = None
        self.predictions = 0
        self.stream = live_stream(self._model.device)
        self._weights_copied = None  # CUDA: an event after the last weights' copy

    def _weights_changed(self) -> None:
        """A new generation of served weights; mark the end of their copy on the caller's
        stream (CUDA; under the lock)."""
        self._generation += 1
        if self.stream is not None:
            self._weights_copied = torch.cuda.Event()
            self._weights_copied.record()

    def _on_live_stream(self):
        """Run on the live stream after the last weights' copy (CUDA; under the lock)."""
        if self.stream is None:
            return contextlib.nullcontext()
        if self._weights_copied is not None:
            self.stream.wait_event(self._weights_copied)
        return torch.cuda.stream(self.stream)

    @property
    def model(self) -> DepthModel:
        return self._model

    @property
    def version(self) -> int:
        """The window whose refined weights are served (0: the start-up weights)."""
        return self._version

    @property
    def generation(self) -> int:
        """Changes with every swap of the served weights (update, preview, revert)."""
        return self._generation

    @property
    def age_s(self) -> float:
        """Seconds since the served weights were swapped in (or since start-up)."""
        return time.monotonic() - self._updated

    @property
    def interim_step(self) -> int:
        """The refinement step of previewed weights; 0 for a finished window's weights."""
        return self._interim_step

    @property
    def metres_per_unit(self) -> float | None:
        """The metric factor the served depth is multiplied by (None: network units)."""
        return self._metres_per_unit

    def set_metres_per_unit(self, factor: float | None) -> None:
        with self._lock:
            self._metres_per_unit = factor

    def update(self, encoder_state: dict[str, torch.Tensor], version: int,
               metres_per_unit: float | None = None) -> int:
        """Serve these encoder weights (and their metric factor) from the next prediction on;
        returns their :attr:`generation`. ``load_state_dict`` copies them into the serving
        copy's own tensors, so the caller may go on changing its own."""
        if not finite_state(encoder_state):
            raise ValueError("refusing to serve non-finite encoder weights")
        with self._lock:
            self._model.encoder.load_state_dict(encoder_state)
            self._weights_changed()
            self._metres_per_unit = metres_per_unit
            self._version = int(version)
            self._updated = time.monotonic()
            self._interim_step = 0
            self._before_preview = None
            return self._generation

    def preview(self, encoder_state: dict[str, torch.Tensor], version: int, step: int) -> None:
        """Serve a refining window's weights after its ``step``-th step, until :meth:`update`
        or :meth:`revert` ends the window (non-finite weights: ValueError, nothing changes)."""
        if not finite_state(encoder_state):
            raise ValueError("refusing to serve non-finite encoder weights")
        with self._lock:
            if self._before_preview is None:
                self._before_preview = (copy.deepcopy(self._model.encoder.state_dict()),
                                        self._version, self._updated, self._metres_per_unit)
            self._model.encoder.load_state_dict(encoder_state)
            self._weights_changed()
            self._version, self._interim_step = int(version), int(step)
            self._updated = time.monotonic()

    def revert(self) -> bool:
        """Serve again the weights from before this window's first :meth:`preview`; False when
        nothing was previewed."""
        with self._lock:
            if self._before_preview is None:
                return False
            state, self._version, self._updated, self._metres_per_unit = self._before_preview
            self._model.encoder.load_state_dict(state)
            self._weights_changed()
            self._interim_step = 0
            self._before_preview = None
            return True

    def warm_up(self) -> None:
        """One prediction on a grey image at the network's input size, not counted: the first
        forward pass pays for allocations and kernel set-up, a frame should not."""
        with self._lock, torch.inference_mode(), self._on_live_stream():
            self._model.predict([warm_up_image(self._model)])

    def predict(self, image: np.ndarray) -> tuple[np.ndarray, int]:
        """(depth H x W float32 at the image's size, version of the weights that made it);
        in metres when the served weights have a metric factor."""
        served = self.serve(image)
        return served.depth, served.version

    def serve(self, image: np.ndarray) -> Served:
        """The image's depth at its size (:class:`Served`: in the outputs' units and raw), with
        the version and generation of the weights that made it."""
        with self._lock, torch.inference_mode(), self._on_live_stream():
            raw = self._model.predict([image])[0]
            self.predictions += 1
            return Served(in_metres(raw, self._metres_per_unit), raw, self._version,
                          self._generation, self._metres_per_unit)
