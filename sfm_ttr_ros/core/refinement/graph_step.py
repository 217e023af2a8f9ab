"""A refinement step without host overhead on CUDA: the step of
:func:`~sfm_ttr_ros.core.refinement.encoder.refine_encoder` (Izquierdo & Civera, CVPR 2023,
Sec. 3.3: one frame's objective, Eq. (5) / Ph-TTR / the hybrid, its backward pass and Adam on
the encoder) on static input buffers, captured once per model, CUDA stream and layout as one
``torch.cuda.CUDAGraph`` and replayed in every window of that layout
(:mod:`~sfm_ttr_ros.core.refinement.graph_cache`).

Why: on a GPU a window's refinement is host-bound (about a thousand kernel launches a step);
captured as one graph with ``Adam(capturable=True)`` the step is launched once
(docs/decisions.md, "The refinement step on CUDA").

How:

* every frame of a window gets the same input shapes (:func:`window_inputs`): its SfM points
  padded to the layout's cap (the window's largest frame rounded up to a power of two,
  :func:`~sfm_ttr_ros.core.refinement.graph_cache.point_cap`) with weight 0 (Eq. (5)
  divides by the frame's own count:
  :func:`~sfm_ttr_ros.core.refinement.supervision.padded_weighted_l1`); its photometric sources
  padded to the objective's source offsets (or the window's most) with a source no pixel can
  use (a pose that puts every point behind its camera, and an identity error of +inf: the
  per-pixel minimum is unchanged); in the hybrid, a frame without a photometric term has
  that term multiplied by 0. The frames' padded inputs stay on the device; a step copies the
  chosen frame's into the static buffers (device to device) and replays.
* one step body (:meth:`StaticStepRunner._body`: the objective read from the static buffers,
  the backward pass, Adam, the loss written into a preallocated history at a device counter)
  runs eagerly ("static", any device) and is what the graph captures ("graph", CUDA); on the
  CPU the tests hold its losses to the eager loop's.
* on CUDA, for a layout not captured yet, the first :data:`GRAPH_WARM_UP_STEPS` steps run
  eagerly on a side stream (lazy set-up: Adam's state, cuDNN), then the step is captured on that
  stream (``Adam(capturable=True, foreach=True)``; the
  gradients set to None first so that the backward pass allocates them from the graph's pool;
  ``capture_error_mode="thread_local"`` so that the live server's thread goes on) and replayed.
  A later window of the layout re-arms that graph (Adam's state reset in place) and replays
  from its first step. No host sync inside the loop but the pacer's: at most
  :data:`~sfm_ttr_ros.core.refinement.graph_cache.REPLAYS_IN_FLIGHT` replays queued, so a live
  frame never waits behind more; the losses are read once at the end; ``on_step`` runs between
  replays (a preview, when one is due, copies the weights).
* a capture that raises leaves the remaining steps to the same body run eagerly (mode
  "static", the reason kept, and not tried again for that model and objective); LoRA
  adapters, frames of different shapes, too few steps or a model off CUDA run the eager loop
  (:func:`plan_step_mode`).

"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Callable, Iterator, Sequence

import numpy as np
import torch

from sfm_ttr_ros.core.geometry import sample_depth
from sfm_ttr_ros.core.models.base import DepthModel
from sfm_ttr_ros.core.refinement.graph_cache import (
    REPLAYS_IN_FLIGHT,
    CapturedStep,
    ReplayPacer,
    cached_step,
    keep_step,
    point_cap,
    refusal,
    refuse,
)
from sfm_ttr_ros.core.refinement.objective import FrameTerms, objective
from sfm_ttr_ros.core.refinement.photometric import (
    PhotometricConfig,
    PhotometricFrame,
    SsimTarget,
    identity_errors,
    photometric_objective,
    ssim_target,
)
from sfm_ttr_ros.core.refinement.refinement_config import RefinementConfig
from sfm_ttr_ros.core.refinement.supervision import padded_weighted_l1

#: Eager steps on a side stream before the capture (PyTorch's whole-network capture recipe).
GRAPH_WARM_UP_STEPS = 3
#: T_{s<-t} of a padded photometric source: a half turn about x puts every point behind the
#: camera (z -> -z), so its warped error is +inf everywhere and never the minimum.
BEHIND_CAMERA = np.diag([1.0, -1.0, -1.0, 1.0])
SSIM_KEYS = ("ssim_padded", "ssim_mu", "ssim_sigma")


def _leaves(x) -> list[torch.Tensor]:
    """The tensors of a step input (a tensor, or the cached (output, features) of frozen
    leading stages: nested tuples and lists; anything else in them is a constant), in order."""
    if torch.is_tensor(x):
        return [x]
    if isinstance(x, list | tuple):
        return [t for item in x for t in _leaves(item)]
    return []


def _rebuild(like, leaves: Iterator[torch.Tensor]):
    """``like``'s structure with its tensors taken from ``leaves`` in order (its constants
    kept)."""
    if torch.is_tensor(like):
        return next(leaves)
    if isinstance(like, list | tuple):
        items = [_rebuild(item, leaves) for item in like]
        return type(like)(*items) if hasattr(like, "_fields") else type(like)(items)
    return like


def _signature(x):
    """What must match for two step inputs to share buffers: tensors' shapes and dtypes,
    the structure, the constants."""
    if torch.is_tensor(x):
        return tuple(x.shape), str(x.dtype)
    if isinstance(x, list | tuple):
        return type(x).__name__, tuple(_signature(item) for item in x)
    return repr(x)


def _shapes(t: FrameTerms) -> tuple:
    ph = t.photometric
    return _signature(t.x), None if ph is None else tuple(ph.target.shape)


def shape_mismatch(frames: Sequence[FrameTerms]) -> str:
    """Why the frames cannot share one set of static buffers ("" = they can): their network
    inputs, or their photometric images, differ in shape."""
    inputs = {_shapes(t)[0] for t in frames}
    images = {_shapes(t)[1] for t in frames} - {None}
    if len(inputs) > 1 or len(images) > 1:
        return f"frames differ in shape: inputs {sorted(inputs)}, images {sorted(images)}"
    return ""


def plan_step_mode(model: DepthModel, frames: Sequence[FrameTerms],
                   cfg: RefinementConfig) -> tuple[str, str]:
    """(mode, reason) of a window's steps: "graph" (reason ""), "static" or "eager" with the
    reason the window does not run as a CUDA graph (``cfg.step_mode``, module docstring)."""
    if cfg.step_mode == "eager":
        return "eager", "step_mode eager"
    if cfg.step_mode == "auto":
        if cfg.trainable == "lora":
            return "eager", "LoRA adapters are not captured"
        if model.device.type != "cuda":
            return "eager", f"not on CUDA ({model.device.type})"
        if cfg.steps <= GRAPH_WARM_UP_STEPS:
            return "eager", (f"{cfg.steps} steps: no more than the {GRAPH_WARM_UP_STEPS} "
                             "warm-up steps before a capture")
    if why := shape_mismatch(frames):
        return "eager", why
    if cfg.step_mode == "static":
        return "static", "step_mode static (not captured)"
    return "graph", ""


# -- the window's inputs, padded to one shape -----------------------------------------------

def _as_device(a, device) -> torch.Tensor:
    """A numpy (float64) or torch matrix as float32 on ``device``."""
    m = torch.as_tensor(np.asarray(a) if not torch.is_tensor(a) else a)
    return m.to(device=device, dtype=torch.float32)


def _sfm_inputs(t: FrameTerms, n_max: int) -> dict[str, torch.Tensor]:
    """The SfM term's grid, targets and weights padded to ``n_max`` points (weight 0) and the
    frame's own count |S_j|."""
    n = int(t.target.shape[0])
    pad = n_max - n
    grid = torch.cat([t.grid, t.grid.new_zeros(1, 1, pad, 2)], 2)
    return {"grid": grid, "target": torch.cat([t.target, t.target.new_zeros(pad)]),
            "weight": torch.cat([t.weight, t.weight.new_zeros(pad)]),
            "count": torch.tensor(float(n), dtype=torch.float32, device=t.target.device)}


def _photometric_inputs(ph: PhotometricFrame | None, like: PhotometricFrame, s_max: int,
                        pcfg: PhotometricConfig) -> dict[str, torch.Tensor]:
    """One frame's photometric term with its sources padded to ``s_max`` (module docstring);
    ``ph`` None: a stand-in of ``like``'s shapes whose term counts 0 (``has_photometric``)."""
    image = ph.target if ph is not None else torch.zeros_like(like.target)
    device = image.device
    sources = list(ph.sources) if ph is not None else []
    poses = list(ph.poses_device) if ph is not None else []
    n_real = len(sources)
    sources += [torch.zeros_like(image)] * (s_max - n_real)
    poses += [_as_device(BEHIND_CAMERA, device)] * (s_max - n_real)
    geometry = ph or like
    out = {"image": image, "sources": torch.stack(sources), "poses": torch.stack(poses),
           "K": geometry.K_device, "K_inv": geometry.K_inv.reshape(1, 3, 3),
           "has_photometric": torch.tensor(float(ph is not None), device=device)}
    if pcfg.automask:
        real = (ph.identity if ph is not None and ph.identity is not None else
                identity_errors(image, sources[:n_real], pcfg.alpha, pcfg.seed)
                if n_real else image.new_zeros(1, 0, *image.shape[-2:]))
        inf = torch.full((1, s_max - n_real, *image.shape[-2:]), float("inf"), device=device)
        out["identity"] = torch.cat([real, inf], 1)
    if pcfg.alpha != 0:
        with torch.no_grad():
            stats = ph.ssim_target if ph is not None and ph.ssim_target is not None else \
                ssim_target(image)
        out.update(zip(SSIM_KEYS, (stats.padded, stats.mu, stats.sigma), strict=True))
    return out


class StepLayout:
    """What the step reads from its buffers: the network input's structure and whether the
    window has a photometric term (else Eq. (5) alone)."""

    def __init__(self, frames: Sequence[FrameTerms], cfg: RefinementConfig):
        self.like_x = frames[0].x
        self.n_x = len(_leaves(self.like_x))
        with_ph = [t.photometric for t in frames if t.photometric is not None]
        self.photometric = cfg.loss in ("photometric", "hybrid") and bool(with_ph)
        self.sfm = cfg.loss != "photometric"
        self.like_ph = with_ph[0] if with_ph else None
        # the caps (graph_cache): sources up to the objective's offsets, points rounded up
        self.s_max = max((len(p.sources) for p in with_ph), default=0)
        if self.photometric:
            self.s_max = max(self.s_max, len(cfg.photometric_config().source_offsets))
        self.n_max = point_cap(max(int(t.target.shape[0]) for t in frames))

    def inputs(self, t: FrameTerms, pcfg: PhotometricConfig) -> dict[str, torch.Tensor]:
        """Frame ``t``'s step inputs in this layout (every frame's: the same keys and shapes)."""
        out = {f"x{i}": v.detach() for i, v in enumerate(_leaves(t.x))}
        if self.sfm:
            out.update(_sfm_inputs(t, self.n_max))
        if self.photometric:
            out.update(_photometric_inputs(t.photometric, self.like_ph, self.s_max, pcfg))
        return out


def window_inputs(frames: Sequence[FrameTerms], cfg: RefinementConfig
                  ) -> tuple[StepLayout, list[dict[str, torch.Tensor]]]:
    """The window's layout and every frame's padded step inputs (module docstring)."""
    layout = StepLayout(frames, cfg)
    pcfg = cfg.photometric_config()
    with torch.no_grad():
        return layout, [layout.inputs(t, pcfg) for t in frames]


def static_step_loss(model: DepthModel, inputs: dict[str, torch.Tensor], layout: StepLayout,
                     frozen_stages: int, cfg: RefinementConfig,
                     pcfg: PhotometricConfig) -> torch.Tensor:
    """One step's objective (:func:`~sfm_ttr_ros.core.refinement.objective.step_loss`: Eq. (5),
    Ph-TTR or Eq. (5) + λ·Ph-TTR) read from padded static inputs: the same numbers up to the
    order of Eq. (5)'s sum, no host value read (fit for a CUDA graph)."""
    x = _rebuild(layout.like_x, iter([inputs[f"x{i}"] for i in range(layout.n_x)]))

    def sfm_term(depth: torch.Tensor) -> torch.Tensor:
        return padded_weighted_l1(sample_depth(depth, inputs["grid"], cfg.sampling),
                                  inputs["target"], inputs["weight"], inputs["count"])

    def photometric_term(outputs) -> torch.Tensor:
        stats = SsimTarget(*(inputs[k] for k in SSIM_KEYS)) if SSIM_KEYS[0] in inputs else None
        return photometric_objective(outputs, inputs["image"],
                                     list(inputs["sources"].unbind(0)), inputs["K"],
                                     list(inputs["poses"].unbind(0)), pcfg,
                                     inputs.get("identity"), stats, K_inv=inputs["K_inv"]).total

    return objective(model, x, frozen_stages, cfg, pcfg, sfm_term if layout.sfm else None,
                     photometric_term if layout.photometric else None,
                     inputs["has_photometric"] if layout.sfm and layout.photometric else None)


# -- the runner -------------------------------------------------------------------------------

def capture_step(body: Callable[[], None], device: torch.device, stream=None):
    """``body`` captured as one CUDA graph (not run: a capture records the kernels only), on
    ``stream`` (the warm-up's side stream; None: torch's own)."""
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph, stream=stream, capture_error_mode="thread_local"):
        body()
    return graph


def bump_versions(tensors: Sequence[torch.Tensor]) -> None:
    """Mark ``tensors`` as modified in place (their autograd version counters + 1).
    ``torch.autograd.graph.increment_version`` is newer than the torch floor
    (sfm_ttr_ros/requirements.py): older releases bump one tensor at a time."""
    from torch.autograd import graph as autograd_graph

    if hasattr(autograd_graph, "increment_version"):
        autograd_graph.increment_version(list(tensors))
        return
    for t in tensors:
        torch._C._increment_version(t)


class StaticStepRunner:
    """A window's steps on static buffers (module docstring): ``step(frame)`` per step, then
    ``losses(steps)`` once. ``capture``: replay the step captured for this model, stream and
    layout by an earlier window (:mod:`~sfm_ttr_ros.core.refinement.graph_cache`), else capture
    it after the warm-up steps (CUDA); ``mode`` / ``reason`` say what ran ("graph", or "static"
    with the reason); ``capture_s`` the host seconds spent capturing (or re-arming a kept
    graph) this window; ``reused`` whether the graph was an earlier window's."""

    def __init__(self, model: DepthModel, frames: Sequence[FrameTerms],
                 params: Sequence[torch.nn.Parameter], cfg: RefinementConfig,
                 frozen_stages: int, capture: bool):
        self.model, self.cfg, self.frozen = model, cfg, frozen_stages
        self.params = list(params)
        self.pcfg = cfg.photometric_config()
        self.device = model.device
        self.layout, self.frames = window_inputs(frames, cfg)
        cuda = self.device.type == "cuda"
        self.refusal_key, self.key = self._keys(cuda)
        self.graph, self.entry = None, None
        self.steps_run = self.replays = 0
        self.capture_s, self.reused = 0.0, False
        self.capture = capture
        # what ran when it is not what was planned ("" = as planned)
        self.mode, self.reason = ("graph" if capture else "static"), ""
        self.pacer = ReplayPacer(REPLAYS_IN_FLIGHT, torch.cuda.Event if capture and cuda
                                 else None)
        self._side = torch.cuda.Stream(self.device) if capture and cuda else None
        if capture and (why := refusal(self.refusal_key)):
            self.capture, self.mode = False, "static"
            self.reason = f"capture failed earlier for this model and objective: {why}"
        if self.capture and self._adopt():
            return
        self.buffers = {k: v.clone() for k, v in self.frames[0].items()}
        self.loaded = 0
        # capturable: Adam's step count and bias corrections stay on the device
        self.optimizer = torch.optim.Adam(self.params, lr=cfg.lr, capturable=cuda,
                                          foreach=True if cuda else None)
        self.history = torch.full((max(1, cfg.steps),), float("nan"), device=self.device)
        self.counter = torch.zeros(1, dtype=torch.long, device=self.device)

    def _keys(self, cuda: bool) -> tuple[tuple, tuple]:
        """(what a refused capture is remembered by: the model's class, the objective and the
        inputs' structure without their sizes; the kept graph's key: the CUDA stream, the
        history's length and the inputs' shapes too)."""
        first = self.frames[0]
        objective_cfg = dataclasses.replace(self.cfg, steps=0, seed=0)
        refusal_key = (type(self.model).__qualname__, str(self.device), repr(objective_cfg),
                       self.frozen, tuple(sorted((k, str(v.dtype)) for k, v in first.items())))
        stream = torch.cuda.current_stream(self.device).cuda_stream if cuda else 0
        shapes = tuple(sorted((k, tuple(v.shape)) for k, v in first.items()))
        return refusal_key, (*refusal_key, stream, self.cfg.steps, shapes)

    def _adopt(self) -> bool:
        """Take the graph an earlier window captured under this key, re-armed (Adam's state
        and the history reset in place); False when there is none."""
        t0 = time.perf_counter()
        entry = cached_step(self.model, self.key, self.params)
        if entry is None:
            return False
        entry.start_window()
        self.entry, self.graph, self.reused = entry, entry.graph, True
        self.buffers, self.optimizer = entry.buffers, entry.optimizer
        self.history, self.counter = entry.history, entry.counter
        self.loaded = -1  # the buffers hold the last window's frame: load the first one
        self.capture_s = time.perf_counter() - t0
        return True

    def _body(self) -> None:
        """Objective, backward pass, Adam, the loss into the history: what the graph holds."""
        loss = static_step_loss(self.model, self.buffers, self.layout, self.frozen, self.cfg,
                                self.pcfg)
        loss.backward()
        self.optimizer.step()
        with torch.no_grad():
            self.history.index_copy_(0, self.counter, loss.detach().reshape(1))
            self.counter.add_(1)

    def _load(self, frame: int) -> None:
        """The chosen frame's inputs into the static buffers (device to device)."""
        if frame != self.loaded:
            for k, buf in self.buffers.items():
                buf.copy_(self.frames[frame][k], non_blocking=True)
            self.loaded = frame

    @contextlib.contextmanager
    def _warm_up_stream(self):
        """The side stream of the steps before a capture (CUDA), else the current stream."""
        if self._side is None or not self.capture:
            yield
            return
        current = torch.cuda.current_stream(self.device)
        self._side.wait_stream(current)
        with torch.cuda.stream(self._side):
            yield
        current.wait_stream(self._side)

    def _capture(self) -> None:
        """Capture the step on the warm-up's stream and keep it for later windows; on any
        refusal the remaining steps run the body eagerly and the refusal is remembered."""
        t0 = time.perf_counter()
        self.optimizer.zero_grad(set_to_none=True)
        try:
            with self._warm_up_stream():
                self.graph = capture_step(self._body, self.device, self._side)
        except Exception as exc:  # noqa: BLE001 - any refusal of the capture: run it eagerly
            self.graph, self.capture = None, False
            self.mode, self.reason = "static", f"capture failed: {type(exc).__name__}: {exc}"
            self.optimizer.zero_grad(set_to_none=True)
            refuse(self.refusal_key, self.reason[len("capture failed: "):])
        else:
            self.entry = CapturedStep(self.graph, self.buffers, self.optimizer, self.history,
                                      self.counter, self.params,
                                      addresses=tuple(p.data_ptr() for p in self.params))
            keep_step(self.model, self.key, self.entry)
        self.capture_s += time.perf_counter() - t0

    def step(self, frame: int) -> None:
        """One refinement step on frame ``frame`` of the window (no host sync but the
        pacer's bounded wait)."""
        if self.capture and self.graph is None and self.steps_run >= GRAPH_WARM_UP_STEPS:
            self._capture()
        if self.graph is not None:
            self._load(frame)
            self.graph.replay()
            self.pacer.launched()
            self.replays += 1
        else:
            with self._warm_up_stream():
                self._load(frame)
                self.optimizer.zero_grad(set_to_none=True)
                self._body()
        self.steps_run += 1

    def losses(self, steps: int) -> list[float]:
        """The first ``steps`` steps' objectives (one read from the device)."""
        return self.history[:steps].tolist() if steps else []

    def close(self) -> None:
        """End the window: the kept graph's gradients off the parameters (the graph keeps
        them), the window's inputs released. Replays change the weights and BatchNorm
        statistics in place without bumping their version counters, which the predictions'
        cache keys on (core/prediction.py): bumped here once."""
        if self.replays:
            bump_versions([*self.model.parameters(), *self.model.buffers()])
        if self.entry is not None:  # the kept graph's buffers live on with it
            self.entry.end_window()
        else:
            self.optimizer.zero_grad(set_to_none=True)
            self.buffers = {}
        self.graph = self.entry = None
        self.frames = []
