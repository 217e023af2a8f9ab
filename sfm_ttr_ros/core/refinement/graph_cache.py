"""What a captured refinement step keeps between windows, and how its replays are paced.

The step of :mod:`~sfm_ttr_ros.core.refinement.graph_step` (Izquierdo & Civera, CVPR 2023,
Sec. 3.3: one frame's objective, its backward pass, Adam on the encoder) captured as one
``torch.cuda.CUDAGraph`` reads and writes fixed addresses: the static inputs, the encoder's
weights and BatchNorm buffers, the gradients (allocated from the graph's own memory pool at
the capture), Adam's state, the loss history. A window's refinement starts from the weights the
weight policy put back *in place* (``load_state_dict`` copies), so the same graph serves every
window of a stream whose inputs have the same layout (:class:`CapturedStep`):

* the layout: the network input's structure and shapes, the points per frame rounded up to a
  cap (:func:`point_cap`), the photometric sources per step up to the objective's offsets, the
  objective's settings; one graph per (model, CUDA stream, layout), at most
  :data:`LAYOUTS_PER_MODEL` per model (the oldest is dropped);
* a window's start resets Adam's state in place (step count, first and second moments to 0:
  the state a fresh Adam starts from) and the loss history, and puts the graph's gradient
  tensors back on the parameters (they are taken off at the window's end so that nothing else
  sees them); the graph and its memory pool stay alive, so later windows allocate nothing;
* a capture that fails is not tried again for that model and objective (:func:`refuse`): its
  reason is logged once and every later window carries it as its ``step_mode_reason``.

:class:`ReplayPacer`: replays are launched without a host sync, so a window could queue tens
of steps of kernels at once and a live frame launched behind them would wait for all of them.
The pacer records an event after each replay and, once more than ``in_flight`` replays are
queued, waits for the oldest: the device never holds more than ``in_flight`` steps of
refinement ahead of a live prediction. It is given its event factory (``torch.cuda.Event`` on
CUDA, None elsewhere: it does nothing), so its logic is tested on the CPU.
"""

from __future__ import annotations

import logging
import weakref
from collections import OrderedDict, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch

LOG = logging.getLogger(__name__)

#: Smallest cap on SfM points per frame; above it the window's most rounded up to a power of two
POINT_CAP_MIN = 256
#: Captured layouts kept per model (a stream's windows use one or two point caps)
LAYOUTS_PER_MODEL = 4
#: Replays queued on the device at most before the refinement waits for the oldest
REPLAYS_IN_FLIGHT = 3


def point_cap(points: int) -> int:
    """The layout's points per frame for a window whose largest frame has ``points``: a power
    of two, at least :data:`POINT_CAP_MIN` (few distinct layouts, so few captures)."""
    return max(POINT_CAP_MIN, 1 << max(0, int(points) - 1).bit_length())


@dataclass
class CapturedStep:
    """One captured step and everything its kernels address (module docstring)."""

    graph: object  # torch.cuda.CUDAGraph
    buffers: dict[str, torch.Tensor]
    optimizer: torch.optim.Optimizer
    history: torch.Tensor
    counter: torch.Tensor
    params: list[torch.nn.Parameter]
    grads: list[torch.Tensor | None] = field(default_factory=list)
    addresses: tuple[int, ...] = ()

    def fits(self, params: Sequence[torch.nn.Parameter]) -> bool:
        """Whether the graph still addresses ``params`` (the same tensors, not moved)."""
        return (len(params) == len(self.params)
                and all(p is q for p, q in zip(params, self.params, strict=True))
                and tuple(p.data_ptr() for p in params) == self.addresses)

    def start_window(self) -> None:
        """Adam's state and the loss history reset in place; the graph's gradients back on the
        parameters."""
        with torch.no_grad():
            for state in self.optimizer.state.values():
                for value in state.values():
                    if torch.is_tensor(value):
                        value.zero_()
            self.history.fill_(float("nan"))
            self.counter.zero_()
        for p, g in zip(self.params, self.grads, strict=True):
            p.grad = g

    def end_window(self) -> None:
        """The gradients off the parameters (kept here: the graph writes into them)."""
        self.grads = [p.grad for p in self.params]
        for p in self.params:
            p.grad = None


_CAPTURED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_REFUSED: dict[tuple, str] = {}


def cached_step(model: torch.nn.Module, key: tuple,
                params: Sequence[torch.nn.Parameter]) -> CapturedStep | None:
    """The step captured for ``model`` under ``key`` that still fits ``params`` (else None,
    and a stale one is dropped)."""
    steps = _CAPTURED.get(model)
    entry = steps.get(key) if steps else None
    if entry is None:
        return None
    if not entry.fits(params):
        del steps[key]
        return None
    steps.move_to_end(key)
    return entry


def keep_step(model: torch.nn.Module, key: tuple, entry: CapturedStep) -> None:
    """Keep ``entry`` for ``model``'s later windows (at most :data:`LAYOUTS_PER_MODEL`)."""
    steps = _CAPTURED.setdefault(model, OrderedDict())
    steps[key] = entry
    steps.move_to_end(key)
    while len(steps) > LAYOUTS_PER_MODEL:
        steps.popitem(last=False)


def refusal(key: tuple) -> str:
    """Why a capture under ``key`` failed before ("" = it did not)."""
    return _REFUSED.get(key, "")


def refuse(key: tuple, reason: str) -> None:
    """Remember that the capture under ``key`` failed; logged the first time only."""
    if key not in _REFUSED:
        LOG.warning(f"refinement step not captured as a CUDA graph ({reason}); this model "
                    f"and objective run their steps eagerly from now on")
    _REFUSED[key] = reason


def forget_captures() -> None:
    """Drop every kept graph and refusal (tests; freeing the device memory)."""
    _CAPTURED.clear()
    _REFUSED.clear()


class ReplayPacer:
    """At most ``in_flight`` replays queued on the device (module docstring). ``new_event``:
    a factory of events with ``record()`` (on the current stream) and ``synchronize()``;
    None: pacing off (CPU). ``waits`` counts the times the host waited."""

    def __init__(self, in_flight: int = REPLAYS_IN_FLIGHT,
                 new_event: Callable[[], object] | None = None):
        if in_flight < 1:
            raise ValueError(f"in_flight must be >= 1, got {in_flight}")
        self.in_flight = int(in_flight)
        self._new_event = new_event
        self._queued: deque = deque()
        self.waits = 0

    def launched(self) -> None:
        """Call after each replay: mark it, and wait for the oldest one beyond the bound."""
        if self._new_event is None:
            return
        event = self._new_event()
        event.record()
        self._queued.append(event)
        while len(self._queued) > self.in_flight:
            self._queued.popleft().synchronize()
            self.waits += 1

    @property
    def queued(self) -> int:
        """Replays marked and not yet waited for (an upper bound on those still running)."""
        return len(self._queued)
