"""One SfM-TTR window end to end: SfM → alignment → refinement → prediction.

The same :class:`SfmTTR` object serves the command line (offline: one window = the whole
sequence, as in the paper), the benchmark and the ROS node (online: sliding windows, the
encoder continued from the previous window or reset to the original weights).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from sfm_ttr_ros.core.alignment import AlignmentConfig, AlignmentResult
from sfm_ttr_ros.core.alignment_affine import (
    AffineAlignmentResult,
    align_output,
    is_affine_output,
)
from sfm_ttr_ros.core.frames import Frame, InputError, Intrinsics, check_window
from sfm_ttr_ros.core.models.base import DepthModel, warm_up_image
from sfm_ttr_ros.core.photometric import PhotometricFrame, prepare_frames
from sfm_ttr_ros.core.prefetch import SfmPrefetch
from sfm_ttr_ros.core.refinement import (
    RefinementConfig,
    RefinementResult,
    frozen_stage_count,
    refine_encoder,
    resolve_loss,
    restore_encoder,
    snapshot_encoder,
    warm_up_refinement,
)
from sfm_ttr_ros.core.serving import finite_state
from sfm_ttr_ros.core.sfm import SfmConfig, SfmReconstructor, SfmResult, image_digest
from sfm_ttr_ros.core.supervision import (
    FrameSupervision,
    at_network_size,
    build_supervision,
    frame_loss,
    sample_at,
)
from sfm_ttr_ros.core.trainable import check_trainable
from sfm_ttr_ros.core.verification import (
    UNSUPPORTED_HISTORY,
    CheckConfig,
    PathReference,
    WindowCheck,
    accept,
    check_error,
    frame_scale_spread,
    parallax,
    path_reference,
    probe_frames,
    sanity_check,
    scale_jump,
    split_supervision,
    track_length,
    unsupported_change,
    unsupported_refusal,
)

WEIGHT_POLICIES = ("reset", "continue", "continual")

#: Predictions kept for reuse (at least; a larger predict call keeps all of its frames).
PREDICTION_CACHE_FRAMES = 16


@dataclass
class TTRConfig:
    sfm: SfmConfig = field(default_factory=SfmConfig)
    alignment: AlignmentConfig = field(default_factory=AlignmentConfig)
    refinement: RefinementConfig = field(default_factory=RefinementConfig)
    check: CheckConfig = field(default_factory=CheckConfig)  # core/verification.py
    # Weights across windows (WEIGHT_POLICIES): "continue" every window starts from the last
    # ACCEPTED window's weights (a refused or rolled-back window leaves them as they were;
    # measured best on real video: BENCHMARKS.md); "reset" from the start-up weights (the
    # paper's per-sequence refinement); "continual" continues with a replay of earlier windows'
    # supervision and an L2 pull toward the start-up encoder (see refine_encoder).
    weight_policy: str = "continue"
    replay_windows: int = 3  # continual: earlier windows whose supervision is replayed
    replay_ratio: float = 0.5  # continual: share of the steps spent on a replayed frame
    anchor_weight: float = 0.01  # continual: λ of λ·Σ‖θ − θ₀‖² over the trainable encoder
    # Steps of a window whose refinement starts from carried weights (continue, continual:
    # after an accepted window): 0 = refinement.steps. What a window learnt carries
    # over, so later windows may need fewer steps than the first.
    carried_steps: int = 0
    # Roll a window back to the weights before it when its loss after refinement exceeds this
    # many times its loss before (or anything is non-finite); 0 = only the non-finite check.
    max_loss_ratio: float = 2.0
    min_supervision_points: int = 50  # fewer selected points in the window: do not refine
    # Frames per forward pass of the window's predictions. 2 on CPU: a window's 15 KITTI-size
    # frames in 0.44 s (1 thread) / 0.25 s (2 threads) against 0.45-0.60 / 0.31-0.34 s with 8,
    # and +45 MiB of RSS at the peak against +220-237 MiB (scripts/studies/predict_batch.py,
    # BENCHMARKS.md "Memory").
    predict_batch: int = 2
    # Reuse a prediction made with the same weights for the same pixels instead of running the
    # network again (the overlap frames of consecutive windows: the previous window's refined
    # prediction is the next window's "before"). The same numbers as computing it again (up to
    # the last bits a different batch composition gives; bit for bit with predict_batch 1).
    # False: always recompute.
    reuse_predictions: bool = True

    def __post_init__(self) -> None:
        if self.weight_policy not in WEIGHT_POLICIES:
            raise InputError(f"weight_policy must be one of {WEIGHT_POLICIES}, got "
                             f"{self.weight_policy!r}")
        if self.replay_windows < 0:
            raise InputError(f"replay_windows must be >= 0, got {self.replay_windows}")
        if self.carried_steps < 0:
            raise InputError(f"carried_steps must be >= 0, got {self.carried_steps}")
        for name in ("replay_ratio", "anchor_weight", "max_loss_ratio"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v >= 0):
                raise InputError(f"{name} must be a finite number >= 0, got {v}")
        if self.replay_ratio > 1:
            raise InputError(f"replay_ratio must lie in [0, 1], got {self.replay_ratio}")


@dataclass
class WindowResult:
    """Outcome of one window. ``depths`` are the published depths (refined when ``refined``)."""

    names: list[str]
    depths: dict[str, np.ndarray]
    depths_before: dict[str, np.ndarray]
    refined: bool
    reason: str = ""  # why the window was not refined ("" when it was)
    reason_key: str = ""  # a verification.CHECK_REASONS key when a check refused the window
    check: WindowCheck | None = None  # what the window checks measured
    # the refined weights' depths of a window a check refused after refining (for evaluation)
    depths_candidate: dict[str, np.ndarray] = field(default_factory=dict)
    sfm: SfmResult | None = None
    alignment: AlignmentResult | None = None
    refinement: RefinementResult | None = None
    scale: float = float("nan")
    loss_before: float = float("nan")
    loss_after: float = float("nan")
    cloud_frame: str = ""  # the registered frame whose optical frame the cloud is in
    cloud_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    cloud_error: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    timings: dict[str, float] = field(default_factory=dict)

    def summary(self) -> dict:
        """The window's outcome as plain numbers (for JSON reports)."""
        return {
            "frames": len(self.names),
            "refined": self.refined,
            "reason": self.reason,
            "registered": self.sfm.num_registered if self.sfm else 0,
            "points": self.sfm.num_points if self.sfm else 0,
            "scale": self.scale,
            "loss_before": self.loss_before,
            "loss_after": self.loss_after,
            "check": self.check.summary() if self.check else None,
        }


class SfmTTR:
    """SfM-TTR over windows of a stream for one depth network."""

    def __init__(self, model: DepthModel, config: TTRConfig | None = None,
                 workspace: str | None = None):
        self.model = model.eval()
        for p in self.model.parameters():
            p.requires_grad_(False)
        self.config = self._concrete(config or TTRConfig())
        self.check_config(self.config)
        self.reconstructor = SfmReconstructor(self.config.sfm, workspace)
        self._prefetch: SfmPrefetch | None = None  # the next window's SfM, see prefetch_sfm
        self.prefetch_nice = 0  # OS priority of that SfM's thread (the window worker's)
        self._prefetch_lock = threading.Lock()
        self._original = snapshot_encoder(model)
        self._carried = False  # the encoder holds an accepted window's weights, not start-up's
        # continual policy: the supervision of the last replay_windows refined windows
        self._replay: deque[list[FrameSupervision]] = deque()
        # the last accepted window's camera path in network units (the scale-jump check)
        self._path: PathReference | None = None
        # U of the last accepted windows: the reference of check.unsupported_change_ratio
        self._unsupported: deque[float] = deque(maxlen=UNSUPPORTED_HISTORY)
        self._stop = False
        # called with the step count after each refinement step of a window whose current
        # weights may be served before its end (the live server's interim weights,
        # core/online.py): no check after refinement, or one that interim_refusal() re-runs
        self.on_refine_step: Callable[[int], None] | None = None
        self._interim_check: Callable[[], str] | None = None  # see interim_refusal()
        self.interim_unsupported = float("nan")  # U of the last interim weights checked
        self._interim_seconds = 0.0  # the window's time in interim checks (in its "refine")
        # (weights key, pixel digest -> depth) of the latest predictions, see predict()
        self._pred_key: tuple | None = None
        self._pred_cache: OrderedDict[bytes, np.ndarray] = OrderedDict()
        # Predictions of the ORIGINAL weights survive refinement and the next reset: with
        # reset_each_window the overlap frames' "before" depths are those of the previous window.
        self._original_key: tuple | None = self._weights_key()
        self._original_cache: OrderedDict[bytes, np.ndarray] = OrderedDict()
        self.predictions_computed = 0  # images the network actually ran on
        self.predictions_reused = 0  # images answered from the cache

    # -- state ---------------------------------------------------------------------------
    def reset_model(self) -> None:
        """Back to the original encoder weights."""
        restore_encoder(self.model, self._original)
        self._original_key = self._weights_key()
        self._carried = False

    def _concrete(self, config: TTRConfig) -> TTRConfig:
        """``config`` with its objective resolved for this model (``refinement.loss`` "auto":
        :func:`~sfm_ttr_ros.core.refinement.resolve_loss`); the caller's object is not
        changed."""
        refinement = resolve_loss(config.refinement, self.model)
        if refinement is config.refinement:
            return config
        return dataclasses.replace(config, refinement=refinement)

    def check_config(self, config: TTRConfig) -> None:
        """InputError if ``config`` cannot run on this model (frozen encoder levels on an encoder
        without the staged-encoder protocol, or all of its levels)."""
        frozen_stage_count(self.model.staged_encoder, config.refinement.frozen_encoder_levels)
        r = config.refinement
        check_trainable(self.model, r.trainable, r.trainable_blocks)
        if r.uses_photometric and is_affine_output(self.model):
            raise InputError(f"refinement.loss {r.loss!r} needs depth up to scale; this model "
                             "predicts affine-invariant inverse depth: use 'sfm'")

    def set_config(self, config: TTRConfig) -> None:
        """New options, used from the next window on."""
        config = self._concrete(config)
        self.check_config(config)
        self.config = config
        self.reconstructor.config = config.sfm
        if self._prefetch is not None:
            self._prefetch.set_config(config.sfm)

    def cancel(self) -> None:
        """Stop the running window at the next step boundary (thread-safe)."""
        self._stop = True
        self.reconstructor.cancel()
        if self._prefetch is not None:
            self._prefetch.cancel()

    def close(self) -> None:
        self.reconstructor.close()
        if self._prefetch is not None:
            self._prefetch.close()

    def prefetch_sfm(self, frames: Sequence[Frame], intrinsics: Intrinsics) -> bool:
        """Begin the SfM of a coming window now, in the background (:mod:`core/prefetch
        <sfm_ttr_ros.core.prefetch>`); :meth:`process_window` of exactly these frames then
        takes it instead of reconstructing. False when one is still running."""
        with self._prefetch_lock:
            if self._prefetch is None:
                self._prefetch = SfmPrefetch(self.config.sfm, self.prefetch_nice)
        return self._prefetch.start(frames, intrinsics)

    @property
    def prefetch_counters(self) -> dict[str, int]:
        """SfM reconstructions begun ahead: started, used by their window, discarded."""
        return self._prefetch.counters() if self._prefetch is not None else \
            {"started": 0, "used": 0, "discarded": 0}

    # -- prediction ----------------------------------------------------------------------
    def predict(self, images: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Depth (H x W float32, network units) of each image with the current weights.

        With ``config.reuse_predictions`` an image whose pixels were predicted before with the
        same weights is not run through the network again (each call returns new arrays; at
        most max(PREDICTION_CACHE_FRAMES, len(images)) depth maps are kept). The weights are
        identified by every parameter and buffer of the model (storage and in-place version
        counter), so an optimizer step, ``load_state_dict``, a BatchNorm statistics update or
        a move to another device all invalidate the cache. The predictions of the original
        weights are kept apart and found again after :meth:`reset_model` (with
        ``reset_each_window`` the overlap frames' "before" depths are reused). Call
        :meth:`clear_prediction_cache` after changing anything else the network's output
        depends on."""
        key = self._weights_key() if self.config.reuse_predictions else None
        if key is None:
            self.clear_prediction_cache()
            self.predictions_computed += len(images)
            return self._run_network(images)
        if key == self._original_key:
            cache = self._original_cache
        else:
            if key != self._pred_key:
                self._pred_key = key
                self._pred_cache.clear()
            cache = self._pred_cache
        digests = [image_digest(np.asarray(im)) for im in images]
        todo: dict[bytes, int] = {}
        for i, d in enumerate(digests):
            if d not in cache and d not in todo:
                todo[d] = i
        fresh = dict(zip(todo, self._run_network([images[i] for i in todo.values()]),
                         strict=True))
        self.predictions_computed += len(fresh)
        self.predictions_reused += len(images) - len(fresh)
        out = []
        for d in digests:
            depth = fresh[d] if d in fresh else cache[d]
            cache[d] = depth
            cache.move_to_end(d)
            out.append(depth.copy())
        while len(cache) > max(PREDICTION_CACHE_FRAMES, len(images)):
            cache.popitem(last=False)
        return out

    def clear_prediction_cache(self) -> None:
        self._pred_key = None
        self._pred_cache.clear()
        self._original_cache.clear()
        self._original_key = None  # until the next reset_model(): nothing is known original

    def warm_up(self) -> float:
        """Pay a window's one-time costs now, in the calling thread (the window worker's, before
        its first window; on CUDA kernels load at first use and each thread makes its own
        cuDNN / cuBLAS handles): the network's forward pass on ``predict_batch`` grey frames
        (:meth:`_run_network`, nothing cached) and two refinement steps on a copy of the model
        (:func:`~sfm_ttr_ros.core.refinement.warm_up_refinement`). Returns the seconds."""
        t0 = time.perf_counter()
        self._run_network([warm_up_image(self.model)] * max(1, self.config.predict_batch))
        warm_up_refinement(self.model, self.config.refinement)
        return time.perf_counter() - t0

    def _run_network(self, images: Sequence[np.ndarray]) -> list[np.ndarray]:
        out: list[np.ndarray] = []
        b = max(1, self.config.predict_batch)
        for i in range(0, len(images), b):
            out.extend(self.model.predict(list(images[i:i + b])))
        return out

    def _weights_key(self) -> tuple | None:
        """Changes whenever a tensor of the model is replaced or modified in place."""
        m = self.model
        try:
            tensors = tuple((t.data_ptr(), t._version)
                            for t in itertools.chain(m.parameters(), m.buffers()))
        except (RuntimeError, AttributeError):  # e.g. inference tensors: no version counter
            return None
        return (id(m), tuple(getattr(m, "input_size", ())), str(m.device),
                getattr(m, "min_depth", None), getattr(m, "max_depth", None), tensors)

    # -- one window ----------------------------------------------------------------------
    def process_window(self, frames: Sequence[Frame], intrinsics: Intrinsics,
                       refine: bool = True,
                       should_stop: Callable[[], bool] | None = None) -> WindowResult:
        """Run the whole method on one window; every frame gets a depth in the result."""
        check_window(frames, intrinsics)
        self._stop = False
        cfg = self.config
        names = [f.name for f in frames]
        t: dict[str, float] = {}

        def stop() -> bool:
            return self._stop or (should_stop is not None and should_stop())

        if cfg.weight_policy == "reset":
            self.reset_model()
        # the scale-jump check compares with the window just before, when it was accepted
        previous_path, self._path = self._path, None
        t0 = time.perf_counter()
        before = dict(zip(names, self.predict([f.image for f in frames]), strict=True))
        t["predict_before"] = time.perf_counter() - t0
        res = WindowResult(names, dict(before), before, refined=False, timings=t)
        if not refine:
            res.reason = "refinement skipped"
            return res
        if cfg.refinement.steps == 0:  # nothing to refine: do not spend time on SfM either
            res.reason = "refinement disabled: refinement.steps is 0"
            return res

        t0 = time.perf_counter()
        sfm = self._prefetch.take(frames, intrinsics) if self._prefetch is not None else None
        if sfm is not None:
            t["sfm_ahead"] = 1.0  # reconstructed while the previous window refined
        else:
            sfm = self.reconstructor.reconstruct(frames, intrinsics)
        t["sfm"] = time.perf_counter() - t0
        t.update({f"sfm_{k}": v for k, v in sfm.timings.items()})
        res.sfm = sfm
        if not sfm.ok:
            res.reason = f"SfM failed: {sfm.reason}"
            return res

        # Stage 2-3: network depth at the SfM keypoints, one scale for the whole window.
        t0 = time.perf_counter()
        images = {f.name: f.image for f in frames}
        reg = [n for n in names if n in sfm.frames]
        d_sfm = np.concatenate([sfm.frames[n].depths for n in reg])
        d_nn = np.concatenate([
            sample_at(before[n], sfm.frames[n].pixels, cfg.refinement.sampling) for n in reg])
        # The paper's scale fit; an affine fit in inverse depth for relative inverse-depth
        # networks (the targets are then in the network's own output space).
        align = align_output(d_sfm, d_nn, getattr(self.model, "output_kind", ""),
                             cfg.alignment, [len(sfm.frames[n].depths) for n in reg])
        res.alignment, res.scale = align, align.scale
        t["align"] = time.perf_counter() - t0
        if not align.ok or int(align.selected.sum()) < cfg.min_supervision_points:
            res.reason = (f"too few supervision points: {int(align.selected.sum())} selected of "
                          f"{d_sfm.size} (< {cfg.min_supervision_points})")
            return res

        t0 = time.perf_counter()
        res.check = self._sanity(sfm, reg, d_sfm, d_nn, align, previous_path)
        res.check.seconds = time.perf_counter() - t0
        if res.check.reason_key:
            res.reason_key, res.reason = res.check.reason_key, f"check: {res.check.reason}"
            return res
        sup = build_supervision(sfm, reg, images, align, cfg.refinement.weighting)
        res.loss_before = float(np.mean([frame_loss(before[s.name], s) for s in sup]))
        t0 = time.perf_counter()
        train, held = (split_supervision(sup, cfg.check.holdout_fraction, cfg.check.seed)
                       if cfg.check.holdout else (sup, []))
        res.check.check_points = sum(len(s) for s in held)
        rescale = self._scaled(align)
        res.check.error_before = check_error(before, held, cfg.refinement.sampling, rescale)
        res.check.seconds += time.perf_counter() - t0
        continual = cfg.weight_policy == "continual"
        replay = [s for window in self._replay for s in window] if continual else []
        # the weights before the window (rollback); under "reset" they are the start-up weights
        start = self._original if cfg.weight_policy == "reset" else snapshot_encoder(self.model)
        anchor = self._original if continual and cfg.anchor_weight > 0 else None
        refinement = cfg.refinement
        if self._carried and cfg.carried_steps > 0:
            refinement = dataclasses.replace(refinement, steps=cfg.carried_steps)
        # interim weights: served unchecked without a check after refinement, else only when
        # the unsupported change can be re-measured on them (interim_refusal)
        self._interim_seconds = 0.0
        self._interim_check = (self._interim_gate(before, images, sfm, reg)
                               if cfg.check.interim_checkable and rescale else None)
        on_step = (self.on_refine_step if not cfg.check.after_refinement
                   or self._interim_check is not None else None)
        t0 = time.perf_counter()
        try:
            res.refinement = refine_encoder(
                self.model, train, refinement, should_stop=stop, replay=replay,
                replay_ratio=cfg.replay_ratio, anchor=anchor, anchor_weight=cfg.anchor_weight,
                photometric=self._photometric_frames(names, images, sfm, align.scale,
                                                     intrinsics), on_step=on_step)
        finally:
            self._interim_check = None
        t["refine"] = time.perf_counter() - t0
        if self._interim_seconds:  # part of the check's cost, spent between refinement steps
            t["interim_check"] = self._interim_seconds
            res.check.seconds += self._interim_seconds
        if res.refinement.cancelled:  # cancel() must return fast: no second prediction pass
            res.reason = "refinement cancelled"
            return res

        t0 = time.perf_counter()
        res.depths = dict(zip(names, self.predict([f.image for f in frames]), strict=True))
        t["predict_after"] = time.perf_counter() - t0
        res.loss_after = float(np.mean([frame_loss(res.depths[s.name], s) for s in sup]))
        res.refined = res.refinement.steps_done > 0
        if not res.refined:
            res.reason = "refinement cancelled" if res.refinement.cancelled else "no usable frame"
            return res
        why = self._rollback_reason(res)
        if why:
            restore_encoder(self.model, start)
            res.refined, res.reason, res.depths = False, f"rolled back: {why}", dict(before)
            return res
        t0 = time.perf_counter()
        c = res.check
        c.error_after = check_error(res.depths, held, cfg.refinement.sampling, rescale)
        if rescale:
            c.unsupported_change = unsupported_change(
                before, res.depths, {n: sfm.frames[n].pixels for n in reg})
        c.seconds += time.perf_counter() - t0
        t["check"] = c.seconds
        if not accept(cfg.check, c.error_before, c.error_after):
            c.reason_key = "rejected_by_check"
            c.reason = (f"held-out check error {c.error_before:.4g} -> {c.error_after:.4g} "
                        f"on {c.check_points} points did not fall by "
                        f"check.holdout_margin {cfg.check.holdout_margin:g}")
        elif unsupported_refusal(cfg.check, c.unsupported_change, self._unsupported):
            c.reason_key = "check_unsupported_change"
            c.reason = unsupported_refusal(cfg.check, c.unsupported_change, self._unsupported)
        if c.reason_key:
            restore_encoder(self.model, start)
            res.reason_key = c.reason_key
            res.refined, res.reason = False, f"rejected by check: {c.reason}"
            res.depths_candidate, res.depths = res.depths, dict(before)
            return res
        self._path = path_reference(sfm, reg, align.scale) if self._scaled(align) else None
        self._carried = cfg.weight_policy != "reset"
        if math.isfinite(c.unsupported_change):
            self._unsupported.append(c.unsupported_change)
        if continual and cfg.replay_windows > 0:
            self._replay.append(self._replay_frames(sup))
            while len(self._replay) > cfg.replay_windows:
                self._replay.popleft()
        self._cloud(res, sfm, reg)
        return res

    def interim_refusal(self) -> str:
        """Why the refining window's current weights may not be served yet ("" = they may).
        With ``check.max_unsupported_change`` on (and no held-out check), its unsupported change
        measured on :func:`probe_frames` of the window with the weights as they are now, judged
        as the finished window's will be (core/verification.py, 3.). For ``on_refine_step``
        (the worker thread, between steps)."""
        check = self._interim_check
        return check() if check is not None else ""

    def _interim_gate(self, before: dict[str, np.ndarray], images: dict[str, np.ndarray],
                      sfm: SfmResult, reg: list[str]) -> Callable[[], str]:
        probe = probe_frames(reg)
        pixels = {n: sfm.frames[n].pixels for n in probe}
        history = tuple(self._unsupported)

        def refusal() -> str:
            t0 = time.perf_counter()
            # mid-refinement: predict() switches to eval mode; put every module back as it was
            # (bn_mode "train" keeps the encoder's BatchNorm in training mode)
            modes = [(m, m.training) for m in self.model.modules()]
            try:
                depths = self._run_network([images[n] for n in probe])
            finally:
                for m, training in modes:
                    m.training = training
            self.interim_unsupported = unsupported_change(
                before, dict(zip(probe, depths, strict=True)), pixels)
            why = unsupported_refusal(self.config.check, self.interim_unsupported, history)
            self._interim_seconds += time.perf_counter() - t0
            return why

        return refusal

    def _scaled(self, align: AlignmentResult) -> bool:
        """Whether ``align`` is the paper's scale fit (depth up to scale): the scale checks'
        precondition."""
        return not isinstance(align, AffineAlignmentResult) and not is_affine_output(self.model)

    def _sanity(self, sfm: SfmResult, reg: list[str], d_sfm: np.ndarray, d_nn: np.ndarray,
                align: AlignmentResult, previous: PathReference | None) -> WindowCheck:
        """The window's statistics and the verdict of the cheap checks
        (:func:`~sfm_ttr_ros.core.verification.sanity_check`)."""
        c = WindowCheck(reprojection_error=sfm.reprojection_error,
                        track_length=track_length(sfm, reg), parallax=parallax(sfm, reg))
        if align.ransac_inliers.size:
            valid = np.isfinite(d_sfm) & np.isfinite(d_nn) & (d_sfm > 0) & (d_nn > 0)
            c.inlier_ratio = float(align.ransac_inliers.sum() / max(1, int(valid.sum())))
        if self._scaled(align):
            bounds = np.cumsum([0] + [len(sfm.frames[n].depths) for n in reg])
            parts = [slice(a, b) for a, b in itertools.pairwise(bounds)]
            c.scale_spread = frame_scale_spread([d_sfm[p] for p in parts],
                                                [d_nn[p] for p in parts])
            c.scale_jump = scale_jump(path_reference(sfm, reg, align.scale), previous)
        return sanity_check(self.config.check, c)

    def _rollback_reason(self, res: WindowResult) -> str:
        """Why a refined window must not be kept ("" when it may): a non-finite loss or
        encoder weight, or a loss after refinement above ``max_loss_ratio`` x the loss before
        (the refinement exploded)."""
        history = np.asarray(res.refinement.loss_history, np.float64)
        if not np.all(np.isfinite(history)) or not math.isfinite(res.loss_after):
            return "non-finite loss"
        if not finite_state(self.model.encoder.state_dict()):
            return "non-finite weights"
        ratio = self.config.max_loss_ratio
        if ratio > 0 and res.loss_after > ratio * res.loss_before:
            return (f"loss {res.loss_before:.4g} -> {res.loss_after:.4g} exceeds "
                    f"max_loss_ratio {ratio:g}")
        return ""

    def _photometric_frames(self, names: list[str], images: dict[str, np.ndarray],
                            sfm: SfmResult, scale: float,
                            intrinsics: Intrinsics) -> list[PhotometricFrame]:
        """The window's photometric terms, prepared once per window when the loss
        needs them: network-size images, the SfM poses of each registered frame's registered
        neighbours with their translations times the alignment scale ŝ (SfM units → network
        depth units: Ph-TTR needs the SfM scale too), K at the network's size and the
        auto-masking identity errors. [] for ``sfm`` (and ``hybrid`` with λ = 0)."""
        r = self.config.refinement
        if not r.uses_photometric:
            return []
        return prepare_frames(self.model, names, images, sfm.frames, scale, intrinsics,
                              r.photometric_config())

    def _replay_frames(self, sup: list[FrameSupervision]) -> list[FrameSupervision]:
        """A window's supervision as the replay keeps it: with a model whose input is the image
        resized to ``input_size`` (:meth:`DepthModel.preprocess`) each image at that size
        (:func:`~sfm_ttr_ros.core.supervision.at_network_size`; 3 windows of 15 KITTI frames:
        7 MB instead of 63 MB); other models' images (normalised, or sized by their own
        processor) as they are."""
        if (len(tuple(getattr(self.model, "input_size", ()))) != 2
                or type(self.model).preprocess is not DepthModel.preprocess):
            return list(sup)
        return [at_network_size(s, self.model) for s in sup]

    @staticmethod
    def _cloud(res: WindowResult, sfm: SfmResult, reg: list[str]) -> None:
        """The sparse cloud in the newest registered frame's optical frame, network units."""
        newest = reg[-1]
        # Depth outputs: network units (× ŝ). An affine fit has no depth unit of its own: the
        # cloud stays in SfM units, those of affine_to_depth(fit, prediction).
        scale = 1.0 if isinstance(res.alignment, AffineAlignmentResult) else res.scale
        xyz = sfm.points_in_frame(newest) * scale
        res.cloud_frame = newest
        res.cloud_xyz = xyz.astype(np.float32)
        res.cloud_error = sfm.points_error.astype(np.float32)
