"""One SfM-TTR window end to end, as Fig. 2 of the paper: SfM → alignment → supervision →
refinement → prediction.

:meth:`SfmTTR.process_window` only calls the stages (private helpers here, each in front of the
module that holds its equations) and two collaborators: :class:`~sfm_ttr_ros.core.checks.window.
WindowJudge` (the window checks before, while and after refining, and rollback) and
:class:`~sfm_ttr_ros.core.refinement.weights.WeightPolicy` (where a window's refinement starts,
what an accepted window leaves to the next). The same :class:`SfmTTR` object serves the command line
(offline: one window = the whole sequence, as in the paper), the benchmark and the ROS node
(online: sliding windows, the encoder continued from the previous window or reset to the
original weights).
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from sfm_ttr_ros.core.alignment.affine import (
    AffineAlignmentResult,
    align_output,
    is_affine_output,
)
from sfm_ttr_ros.core.alignment.scale import AlignmentConfig, AlignmentResult
from sfm_ttr_ros.core.checks.measures import CheckConfig, CheckReport
from sfm_ttr_ros.core.checks.window import WindowJudge
from sfm_ttr_ros.core.errors import InputError, check_choice
from sfm_ttr_ros.core.frames import Frame, Intrinsics, check_window
from sfm_ttr_ros.core.metric.config import MetricConfig
from sfm_ttr_ros.core.metric.odometry import OdometryTrack
from sfm_ttr_ros.core.metric.scale import MetricScale, WindowMetric, estimate
from sfm_ttr_ros.core.models.base import DepthModel, warm_up_image
from sfm_ttr_ros.core.outcomes import Stop, Unrefined
from sfm_ttr_ros.core.prediction import Predictor
from sfm_ttr_ros.core.refinement.config import RefinementConfig, resolve_loss
from sfm_ttr_ros.core.refinement.encoder import (
    RefinementResult,
    frozen_stage_count,
    refine_encoder,
    warm_up_refinement,
)
from sfm_ttr_ros.core.refinement.photometric import PhotometricFrame, prepare_frames
from sfm_ttr_ros.core.refinement.supervision import (
    FrameSupervision,
    build_supervision,
    frame_loss,
    sample_at,
)
from sfm_ttr_ros.core.refinement.trainable import check_trainable
from sfm_ttr_ros.core.refinement.weights import WEIGHT_POLICIES, WeightPolicy
from sfm_ttr_ros.core.sfm.prefetch import SfmPrefetch
from sfm_ttr_ros.core.sfm.reconstruction import SfmConfig, SfmReconstructor, SfmResult


@dataclass
class TTRConfig:
    sfm: SfmConfig = field(default_factory=SfmConfig)
    alignment: AlignmentConfig = field(default_factory=AlignmentConfig)
    refinement: RefinementConfig = field(default_factory=RefinementConfig)
    check: CheckConfig = field(default_factory=CheckConfig)  # core/checks/measures.py
    metric: MetricConfig = field(default_factory=MetricConfig)  # core/metric/
    # Weights across windows (WEIGHT_POLICIES): "continue" every window starts from the last
    # ACCEPTED window's weights (a refused or rolled-back window leaves them as they were;
    # measured best on real video: docs/decisions.md); "reset" from the start-up weights (the
    # paper's per-sequence refinement).
    weight_policy: str = "continue"
    # Roll a window back to the weights before it when its loss after refinement exceeds this
    # many times its loss before (or anything is non-finite); 0 = only the non-finite check.
    max_loss_ratio: float = 2.0
    min_supervision_points: int = 50  # fewer selected points in the window: do not refine
    # Frames per forward pass of the window's predictions. 2 on CPU: a window's 15 KITTI-size
    # frames in 0.44 s (1 thread) / 0.25 s (2 threads) against 0.45-0.60 / 0.31-0.34 s with 8,
    # and +45 MiB of RSS at the peak against +220-237 MiB (scripts/studies/predict_batch.py,
    # BENCHMARKS.md "Memory").
    predict_batch: int = 2
    # Frames per forward pass when the model is on CUDA (0 = predict_batch): a window's
    # frames in one batched pass there (the GPU is launch-bound at small batches and has the
    # memory); the CPU keeps predict_batch.
    predict_batch_cuda: int = 16
    # Reuse a prediction made with the same weights for the same pixels instead of running the
    # network again (the overlap frames of consecutive windows: the previous window's refined
    # prediction is the next window's "before"). The same numbers as computing it again (up to
    # the last bits a different batch composition gives; bit for bit with predict_batch 1).
    # False: always recompute.
    reuse_predictions: bool = True

    def __post_init__(self) -> None:
        check_choice("weight_policy", self.weight_policy, WEIGHT_POLICIES)
        if self.predict_batch_cuda < 0:
            raise InputError(f"predict_batch_cuda must be >= 0, got {self.predict_batch_cuda}")
        v = float(self.max_loss_ratio)
        if not (math.isfinite(v) and v >= 0):
            raise InputError(f"max_loss_ratio must be a finite number >= 0, got {v}")


@dataclass
class WindowResult:
    """Outcome of one window. ``depths`` are the published depths (refined when ``refined``)."""

    names: list[str]
    depths: dict[str, np.ndarray]
    depths_before: dict[str, np.ndarray]
    refined: bool
    reason: str = ""  # why the window was not refined, for people ("" when it was)
    reason_key: Unrefined | None = None  # what is counted when it was not refined
    check: CheckReport | None = None  # what the window checks measured
    # the refined weights' depths of a window a check refused after refining (for evaluation)
    depths_candidate: dict[str, np.ndarray] = field(default_factory=dict)
    sfm: SfmResult | None = None
    alignment: AlignmentResult | None = None
    refinement: RefinementResult | None = None
    metric: WindowMetric | None = None  # the window's metric estimate (core/metric/)
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
            "step_mode": ([self.refinement.step_mode, self.refinement.step_mode_reason]
                          if self.refinement is not None else None),
            "check": self.check.summary() if self.check else None,
        }


@dataclass
class _Window:
    """One window on its way through Fig. 2: what each stage hands the next (the outcome so far
    in ``result``)."""

    frames: Sequence[Frame]
    intrinsics: Intrinsics
    result: WindowResult
    registered: list[str] = field(default_factory=list)  # the frames SfM registered, in order
    d_sfm: np.ndarray = field(default_factory=lambda: np.zeros(0))  # their D_sfm, concatenated
    d_nn: np.ndarray = field(default_factory=lambda: np.zeros(0))  # D_nn at the same pixels
    scaled: bool = False  # the alignment is the paper's scale fit (depth up to scale)
    metric: WindowMetric | None = None  # metres per SfM / network unit (core/metric/)
    supervision: list[FrameSupervision] = field(default_factory=list)  # Eq. (5) per frame

    def __post_init__(self) -> None:
        self.images = {f.name: f.image for f in self.frames}

    @property
    def names(self) -> list[str]:
        return self.result.names

    @property
    def before(self) -> dict[str, np.ndarray]:
        """The depths of the weights before the window."""
        return self.result.depths_before

    @property
    def timings(self) -> dict[str, float]:
        return self.result.timings


def _unrefined(res: WindowResult, stop: Stop,
               depths: dict[str, np.ndarray] | None = None) -> WindowResult:
    """``res`` as a window that is not refined, with why; ``depths`` (the depths before) are
    published instead of the refined weights' when given."""
    res.refined, res.reason, res.reason_key = False, stop.text, stop.key
    if depths is not None:
        res.depths = dict(depths)
    return res


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
        # a window runs and its own SfM has not ended yet (set by process_window, cleared once
        # its SfM ends; a window that stops before SfM runs none, so nothing waits on it)
        self._own_sfm_pending = False
        self._prefetch_lock = threading.Lock()
        # where each window starts and what an accepted one leaves to the next (weight policy)
        # D_nn = h(g(I)) with a cache of the latest predictions (core/prediction.py)
        self.predictor = Predictor(self.model, self.config.predict_batch,
                                   self.config.reuse_predictions, self.config.predict_batch_cuda)
        self.weights = WeightPolicy(self.model, on_reset=self.predictor.original_restored)
        self.checks = WindowJudge()  # the window checks and their references across windows
        self.metric = MetricScale()  # the steady metric factor of the accepted windows
        self.odometry = OdometryTrack()  # positions for metric.source odometry (the node's)
        self._stop = False
        # called with the step count after each refinement step of a window whose current
        # weights may be served before its end (the live server's interim weights,
        # core/stream/refiner.py): no check after refinement, or one that interim_refusal() re-runs
        self.on_refine_step: Callable[[int], None] | None = None

    # -- state ---------------------------------------------------------------------------
    def reset_model(self) -> None:
        """Back to the original encoder weights."""
        self.weights.reset()

    def _concrete(self, config: TTRConfig) -> TTRConfig:
        """``config`` with its objective resolved for this model (``refinement.loss`` "auto":
        :func:`~sfm_ttr_ros.core.refinement.encoder.resolve_loss`); the caller's object is not
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
        self.predictor.batch, self.predictor.reuse = config.predict_batch, config.reuse_predictions
        self.predictor.cuda_batch = config.predict_batch_cuda
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
        <sfm_ttr_ros.core.sfm.prefetch>`); :meth:`process_window` of exactly these frames then
        takes it instead of reconstructing. False when one is still running, or while the
        current window has not finished its own SfM: on a few cores two reconstructions at once
        slowed the current window's (a GPU machine held to 2 cores: first weights 6.8 s after
        the window's last frame instead of 4.2 s); the caller asks again at the next frame."""
        if self._own_sfm_pending:
            return False
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
        """Depth (H x W float32, network units) of each image with the current weights
        (:meth:`Predictor.predict <sfm_ttr_ros.core.prediction.Predictor.predict>`: answered
        from the cache when the same pixels were predicted with the same weights)."""
        return self.predictor.predict(images)

    def clear_prediction_cache(self) -> None:
        self.predictor.clear()

    @property
    def predictions_computed(self) -> int:
        """Images the network actually ran on."""
        return self.predictor.computed

    @property
    def predictions_reused(self) -> int:
        """Images answered from the cache."""
        return self.predictor.reused

    def warm_up(self) -> float:
        """Pay a window's one-time costs now, in the calling thread (the window worker's, before
        its first window; on CUDA kernels load at first use and each thread makes its own
        cuDNN / cuBLAS handles): the network's forward pass on a batch of grey frames
        (``predict_batch``, ``predict_batch_cuda`` on CUDA)
        (nothing cached) and two refinement steps on a copy of the model
        (:func:`~sfm_ttr_ros.core.refinement.encoder.warm_up_refinement`). Returns the seconds."""
        t0 = time.perf_counter()
        self.predictor.run([warm_up_image(self.model)] * self.predictor.effective_batch)
        warm_up_refinement(self.model, self.config.refinement)
        return time.perf_counter() - t0

    # -- one window ----------------------------------------------------------------------
    def process_window(self, frames: Sequence[Frame], intrinsics: Intrinsics,
                       refine: bool = True,
                       should_stop: Callable[[], bool] | None = None) -> WindowResult:
        """Run the whole method on one window; every frame gets a depth in the result.

        Fig. 2 of the paper, stage by stage; the window checks (:class:`WindowJudge`) judge
        the window before and after refining, the weight policy (:class:`WeightPolicy`) says
        where its refinement starts and what an accepted window leaves to the next."""
        check_window(frames, intrinsics)
        self._own_sfm_pending = True  # no SfM begun ahead until this window's own has ended
        self._stop = False
        cfg = self.config
        self.weights.begin_window(cfg.weight_policy)  # "reset": from the start-up weights
        self.checks.begin_window()  # the scale-jump reference: the window before, if accepted
        w = self._predict_before(frames, intrinsics)  # D_nn = h(g(I_j)) with the weights before
        res = w.result
        if not refine:
            return _unrefined(res, Stop(Unrefined.DISABLED, "refinement skipped"))
        if cfg.refinement.steps == 0:  # nothing to refine: do not spend time on SfM either
            return _unrefined(res, Stop(Unrefined.DISABLED,
                                        "refinement disabled: refinement.steps is 0"))
        if stop := self._reconstruct(w):  # SfM: D_sfm, p_lj, r_lj (Sec. 3.1)
            return _unrefined(res, stop)
        if stop := self._align(w):  # D_nn(p_lj) and one scale ŝ for the window (Sec. 3.2)
            return _unrefined(res, stop)
        res.check = self.checks.before_refining(cfg.check, res.sfm, w.registered, w.d_sfm,
                                                w.d_nn, res.alignment, w.scaled)
        if res.check.reason_key:
            return _unrefined(res, Stop(res.check.reason_key, f"check: {res.check.reason}"))
        if stop := self._measure_metric(w):  # metres per unit: ground plane or odometry
            return _unrefined(res, stop)
        self._supervise(w)  # Eq. (5) per frame and the window's loss before
        start = self.weights.begin(cfg.weight_policy)  # the weights before the window
        res.refinement = self._refine(w, should_stop)  # Adam on the encoder (Sec. 3.3)
        if res.refinement.cancelled:  # cancel() must return fast: no second prediction pass
            return _unrefined(res, Stop(Unrefined.CANCELLED, "refinement cancelled"))
        self._predict_after(w)  # the refined weights' depth of every frame
        if not res.refined:
            return _unrefined(res, Stop(Unrefined.TOO_FEW_POINTS, "no usable frame"))
        if why := self.checks.rollback_reason(cfg.max_loss_ratio, res.refinement.loss_history,
                                              res.loss_before, res.loss_after,
                                              self.model.encoder):
            self.weights.refuse(start)
            return _unrefined(res, Stop(Unrefined.ROLLED_BACK, f"rolled back: {why}"),
                              depths=w.before)
        c = self.checks.after_refining(cfg.check, res.check, w.before, res.depths, res.sfm,
                                       w.registered, w.scaled)
        res.timings["check"] = c.seconds
        if c.reason_key:
            self.weights.refuse(start)
            res.depths_candidate = res.depths
            return _unrefined(res, Stop(c.reason_key, f"rejected by check: {c.reason}"),
                              w.before)
        self.checks.accept(c, res.sfm, w.registered, res.scale, w.scaled)
        self.metric.accept(cfg.metric, w.metric, cfg.weight_policy)
        self._cloud(res, res.sfm, w.registered)
        return res

    def refinement_inputs(self, frames: Sequence[Frame], intrinsics: Intrinsics
                          ) -> tuple[list[FrameSupervision], list[PhotometricFrame]] | Stop:
        """A window's inputs to the refinement, as :meth:`process_window` makes them (Fig. 2 up
        to Sec. 3.3: the predictions before, SfM, the scale and its metres, Eq. (5)'s
        supervision per frame, the photometric frames), without the checks and without
        refining: what a profile of the refinement's steps runs on (tools/step_profile.py). The
        weights are not touched; a window that stops before refining gives its :class:`Stop`."""
        check_window(frames, intrinsics)
        self._stop = False
        w = self._predict_before(frames, intrinsics)
        if stop := self._reconstruct(w):
            return stop
        if stop := self._align(w):
            return stop
        if stop := self._measure_metric(w):  # the targets in metres, as the window trains on
            return stop
        self._supervise(w)
        res = w.result
        return w.supervision, self._photometric_frames(w.names, w.images, res.sfm, res.scale,
                                                       w.intrinsics)

    def interim_refusal(self) -> str:
        """Why the refining window's current weights may not be served yet ("" = they may).
        With ``check.max_unsupported_change`` on, its unsupported change
        measured on :func:`probe_frames` of the window with the weights as they are now, judged
        as the finished window's will be (core/checks/measures.py, 3.). For ``on_refine_step``
        (the worker thread, between steps)."""
        return self.checks.interim_refusal()

    @property
    def interim_unsupported(self) -> float:
        """U of the last interim weights checked (:meth:`interim_refusal`)."""
        return self.checks.interim_unsupported

    def metric_status(self) -> dict[str, object]:
        """What the outputs' units are now, for /diagnostics: ``source``, ``state``
        (``not_metric``: metric.source none; ``waiting``: no accepted estimate yet;
        ``metric``), ``metres_per_unit``, the relative ``spread`` of the accepted windows'
        estimates and how many there are."""
        cfg = self.config.metric
        k = self.metres_per_unit
        state = "not_metric" if cfg.source == "none" else ("waiting" if k is None else "metric")
        return {"source": cfg.source, "state": state,
                "metres_per_unit": float("nan") if k is None else k,
                "spread": self.metric.spread(), "windows": len(self.metric.history),
                "odometry_received": self.odometry.received,
                "odometry_rejected": self.odometry.rejected}

    @property
    def metres_per_unit(self) -> float | None:
        """The metric factor of the outputs now (core/metric/scale.py): metres per network
        depth unit of the current weights; None = not metric."""
        return self.metric.factor(self.config.metric)

    # -- the stages of one window (Fig. 2) -----------------------------------------------
    def _predict_before(self, frames: Sequence[Frame], intrinsics: Intrinsics) -> _Window:
        """The network's depth of every frame with the weights before the window: the
        published depth unless the window is refined, and D_nn of the alignment."""
        names = [f.name for f in frames]
        t: dict[str, float] = {}
        t0 = time.perf_counter()
        before = dict(zip(names, self.predict([f.image for f in frames]), strict=True))
        t["predict_before"] = time.perf_counter() - t0
        return _Window(frames, intrinsics,
                       WindowResult(names, dict(before), before, refined=False, timings=t))

    def _reconstruct(self, w: _Window) -> Stop | None:
        """SfM of the window (Sec. 3.1), or the reconstruction begun ahead of it
        (:meth:`prefetch_sfm`); why the window stops here (None = it goes on)."""
        t, res = w.timings, w.result
        t0 = time.perf_counter()
        try:
            sfm = (self._prefetch.take(w.frames, w.intrinsics) if self._prefetch is not None
                   else None)
            if sfm is not None:
                t["sfm_ahead"] = 1.0  # reconstructed while the previous window refined
            else:
                sfm = self.reconstructor.reconstruct(w.frames, w.intrinsics)
        finally:
            self._own_sfm_pending = False
        t["sfm"] = time.perf_counter() - t0
        t.update({f"sfm_{k}": v for k, v in sfm.timings.items()})
        res.sfm = sfm
        return None if sfm.ok else Stop(Unrefined.SFM_FAILED, f"SfM failed: {sfm.reason}")

    def _align(self, w: _Window) -> Stop | None:
        """Network depth at the SfM keypoints and one scale for the whole window (Sec. 3.2,
        Eq. (4): RANSAC, weighted least squares, the relaxed selection of the supervision
        points); why the window stops here (None = it goes on)."""
        cfg, res, sfm = self.config, w.result, w.result.sfm
        t0 = time.perf_counter()
        w.registered = reg = [n for n in w.names if n in sfm.frames]
        w.d_sfm = np.concatenate([sfm.frames[n].depths for n in reg])
        w.d_nn = np.concatenate([
            sample_at(w.before[n], sfm.frames[n].pixels, cfg.refinement.sampling) for n in reg])
        # The paper's scale fit; an affine fit in inverse depth for relative inverse-depth
        # networks (the targets are then in the network's own output space).
        align = align_output(w.d_sfm, w.d_nn, getattr(self.model, "output_kind", ""),
                             cfg.alignment, [len(sfm.frames[n].depths) for n in reg])
        res.alignment, res.scale = align, align.scale
        w.scaled = self._scaled(align)
        w.timings["align"] = time.perf_counter() - t0
        if not align.ok or int(align.selected.sum()) < cfg.min_supervision_points:
            return Stop(Unrefined.TOO_FEW_POINTS,
                        f"too few supervision points: {int(align.selected.sum())} selected of "
                        f"{w.d_sfm.size} (< {cfg.min_supervision_points})")
        return None

    def _measure_metric(self, w: _Window) -> Stop | None:
        """Metres per SfM unit of the window (``metric.source``: a ground plane under the
        camera, or odometry) and per network unit; refused when it jumps against the stream's
        steady factor (core/metric/scale.py). With ``metric.learn`` the supervision becomes
        metric (the targets m·D_sfm)."""
        cfg, res = self.config, w.result
        stamps = [f.stamp for f in w.frames if f.name in set(w.registered)]
        w.metric = res.metric = estimate(cfg.metric, res.sfm, w.registered, stamps,
                                         res.scale if w.scaled else float("nan"),
                                         self.odometry)
        if why := self.metric.refusal(cfg.metric, w.metric, cfg.weight_policy):
            return Stop(Unrefined.CHECK_SCALE_JUMP, f"check: {why}")
        if cfg.metric.learn and w.metric.ok:  # Eq. (5)'s targets m·D_sfm: metres are learnt
            res.alignment = dataclasses.replace(res.alignment, scale=w.metric.m)
            res.scale = w.metric.m
        return None

    def _supervise(self, w: _Window) -> None:
        """Eq. (5) per registered frame (targets ŝ·D_sfm at p_lj, weights exp(−r²)) and the
        window's loss before refining."""
        cfg, res = self.config, w.result
        w.supervision = build_supervision(res.sfm, w.registered, w.images, res.alignment,
                                          cfg.refinement.weighting)
        res.loss_before = float(np.mean([frame_loss(w.before[s.name], s)
                                         for s in w.supervision]))

    def _refine(self, w: _Window, should_stop: Callable[[], bool] | None) -> RefinementResult:
        """Test-time refinement (Sec. 3.3): Adam on the encoder over the supervision, as
        ``config.refinement`` says; between steps ``on_refine_step`` may serve the interim
        weights when the window checks allow it (their time counts in "refine" and in the
        check's)."""
        cfg, res = self.config, w.result

        def stop() -> bool:
            return self._stop or (should_stop is not None and should_stop())

        serve = self.checks.arm_interim(cfg.check, w.before, w.images, res.sfm, w.registered,
                                        self._predict_as_is, w.scaled)
        t0 = time.perf_counter()
        try:
            refinement = refine_encoder(
                self.model, w.supervision, cfg.refinement, should_stop=stop,
                photometric=self._photometric_frames(w.names, w.images, res.sfm, res.scale,
                                                     w.intrinsics),
                on_step=self.on_refine_step if serve else None)
        finally:
            interim = self.checks.disarm_interim()
        w.timings["refine"] = time.perf_counter() - t0
        if interim:  # part of the check's cost, spent between refinement steps
            w.timings["interim_check"] = interim
            res.check.seconds += interim
        return refinement

    def _predict_after(self, w: _Window) -> None:
        """The refined weights' depth of every frame and the window's loss after."""
        res = w.result
        t0 = time.perf_counter()
        res.depths = dict(zip(w.names, self.predict([f.image for f in w.frames]), strict=True))
        w.timings["predict_after"] = time.perf_counter() - t0
        res.loss_after = float(np.mean([frame_loss(res.depths[s.name], s)
                                        for s in w.supervision]))
        res.refined = res.refinement.steps_done > 0

    def _predict_as_is(self, images: list[np.ndarray]) -> list[np.ndarray]:
        """The network's depth of ``images`` mid-refinement (the interim gate): predict()
        switches to eval mode; every module is put back as it was (bn_mode "train" keeps the
        encoder's BatchNorm in training mode)."""
        modes = [(m, m.training) for m in self.model.modules()]
        try:
            return self.predictor.run(images)
        finally:
            for m, training in modes:
                m.training = training

    def _scaled(self, align: AlignmentResult) -> bool:
        """Whether ``align`` is the paper's scale fit (depth up to scale): the scale checks'
        precondition."""
        return not isinstance(align, AffineAlignmentResult) and not is_affine_output(self.model)

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
