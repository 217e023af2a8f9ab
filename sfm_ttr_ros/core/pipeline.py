"""One SfM-TTR window end to end, as Fig. 2 of the paper: SfM → alignment → supervision →
refinement → prediction.

:meth:`SfmTTR.process_window` only calls the stages, each the owner of its work: the SfM source
(:class:`~sfm_ttr_ros.core.sfm.source.SfmSource`: the window's reconstruction or the one begun
ahead), the alignment
(:func:`~sfm_ttr_ros.core.alignment.window_alignment.align_window`), the window checks
(:class:`~sfm_ttr_ros.core.checks.judge.WindowJudge`: before, while and after
refining, and rollback), the metres (:class:`~sfm_ttr_ros.core.metric.scale.MetricScale`), the
supervision and the refinement (:mod:`core/refinement <sfm_ttr_ros.core.refinement>`), the
weights across windows (:class:`~sfm_ttr_ros.core.refinement.weights.WeightPolicy`) and the
network's depth with its cache (:class:`~sfm_ttr_ros.core.prediction.Predictor`). The same
:class:`SfmTTR` object serves the command line (offline: one window = the whole sequence, as
in the paper), the benchmark and the ROS node (online: sliding windows, the encoder continued
from the previous window or reset to the original weights).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence

import numpy as np

from sfm_ttr_ros.core.alignment.affine import is_affine_output
from sfm_ttr_ros.core.alignment.cloud import window_cloud
from sfm_ttr_ros.core.alignment.window_alignment import align_window
from sfm_ttr_ros.core.checks.judge import WindowJudge
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Frame, Intrinsics, check_window
from sfm_ttr_ros.core.metric.metric_config import check_source_for_output
from sfm_ttr_ros.core.metric.odometry_track import OdometryTrack
from sfm_ttr_ros.core.metric.scale import MetricScale, MetricStatus, estimate
from sfm_ttr_ros.core.models.base import DepthModel, warm_up_image
from sfm_ttr_ros.core.outcomes import Stop, Unrefined
from sfm_ttr_ros.core.prediction import Predictor
from sfm_ttr_ros.core.refinement.encoder import (
    RefinementResult,
    frozen_stage_count,
    refine_encoder,
    warm_up_refinement,
)
from sfm_ttr_ros.core.refinement.photometric import PhotometricFrame, prepare_frames
from sfm_ttr_ros.core.refinement.refinement_config import resolve_loss
from sfm_ttr_ros.core.refinement.supervision import (
    FrameSupervision,
    build_supervision,
    frame_loss,
)
from sfm_ttr_ros.core.refinement.trainable import check_trainable
from sfm_ttr_ros.core.refinement.weights import WeightPolicy
from sfm_ttr_ros.core.sfm.self_calibration import SelfCalibration
from sfm_ttr_ros.core.sfm.source import make_sfm_source, reconfigure_sfm_source
from sfm_ttr_ros.core.window_io import TTRConfig, WindowResult, WindowState, unrefined


class SfmTTR:
    """SfM-TTR over windows of a stream for one depth network."""

    def __init__(self, model: DepthModel, config: TTRConfig | None = None,
                 workspace: str | None = None):
        self.model = model.eval()
        for p in self.model.parameters():
            p.requires_grad_(False)
        self.config = self._concrete(config or TTRConfig())
        self.check_config(self.config)
        self.sfm = make_sfm_source(self.config.sfm, workspace)  # stage 1, of the configured kind
        # D_nn = h(g(I)) with a cache of the latest predictions (core/prediction.py)
        self.predictor = Predictor(self.model, self.config.predict_batch,
                                   self.config.reuse_predictions, self.config.predict_batch_cuda,
                                   self.config.reuse_live_predictions)
        # where each window starts and what an accepted one leaves to the next (weight policy)
        self.weights = WeightPolicy(self.model, on_reset=self.predictor.original_restored)
        self.checks = WindowJudge()  # the window checks and their references across windows
        self.metric = MetricScale()  # the steady metric factor of the accepted windows
        self.odometry = OdometryTrack()  # positions for metric.source odometry (the node's)
        self.focal = SelfCalibration()  # the focal length of assumed intrinsics, per window
        self._stop = False
        # called with the step count after each refinement step whose weights may be served
        # before the window ends (core/stream/refiner.py; checks.interim_refusal() says)
        self.on_refine_step: Callable[[int], None] | None = None

    # -- one window (Fig. 2) -------------------------------------------------------------
    def process_window(self, frames: Sequence[Frame], intrinsics: Intrinsics,
                       refine: bool = True,
                       should_stop: Callable[[], bool] | None = None) -> WindowResult:
        """Run the whole method on one window; every frame gets a depth in the result.

        Fig. 2 of the paper, stage by stage; the window checks (:class:`WindowJudge`) judge
        the window before and after refining, the weight policy (:class:`WeightPolicy`) says
        where its refinement starts and what an accepted window leaves to the next."""
        w = self._begin(frames, intrinsics)  # D_nn = h(g(I_j)) with the weights before
        res = w.result
        if stop := self._not_refining(refine):
            return unrefined(res, stop)
        if stop := self._prepare(w):  # SfM, alignment, the checks before refining, Eq. (5)
            return unrefined(res, stop)
        start = self.weights.rollback_point(self.config.weight_policy)
        with self.weights.restored_on_error(start):
            res.refinement = self._refine(w, should_stop)  # Adam on the encoder (Sec. 3.3)
            if res.refinement.cancelled:  # cancel() must return fast: no second prediction
                return unrefined(res, Stop(Unrefined.CANCELLED, "refinement cancelled"))
            self._predict_after(w)  # the refined weights' depth of every frame
            if not res.refined:
                return unrefined(res, Stop(Unrefined.TOO_FEW_POINTS, "no usable frame"))
            if stop := self._keep_or_refuse(w, start):  # rollback, the checks after refining
                return unrefined(res, stop, w.before)
        return res

    def refinement_inputs(self, frames: Sequence[Frame], intrinsics: Intrinsics
                          ) -> tuple[list[FrameSupervision], list[PhotometricFrame]] | Stop:
        """A window's inputs to the refinement, made by the same preparation as
        :meth:`process_window`'s (Fig. 2 up to Sec. 3.3: the predictions before, SfM, the
        scale, the checks before refining, the metres, Eq. (5)'s supervision per frame, the
        photometric frames), without refining: what a profile of the refinement's steps runs
        on (tools/step_profile.py). The weights are not touched; a window that stops before
        refining gives its :class:`Stop`."""
        check_window(frames, intrinsics)
        self._stop = False
        w = self._predict_before(frames, intrinsics)
        if stop := self._prepare(w):
            return stop
        return w.supervision, photometric_frames(self.model, self.config, w)

    def _begin(self, frames: Sequence[Frame], intrinsics: Intrinsics) -> WindowState:
        """A window begins: its input checked, no SfM begun ahead until its own has ended,
        the weights it starts from (``reset``: the start-up weights), the scale-jump reference
        (the window before, if accepted), and the depths of the weights before it."""
        check_window(frames, intrinsics)
        self.sfm.begin_window()
        self._stop = False
        self.weights.load_start(self.config.weight_policy)
        self.checks.begin_window()
        return self._predict_before(frames, intrinsics)

    def _not_refining(self, refine: bool) -> Stop | None:
        """Why the window is not refined at all (no SfM spent either); None = it is."""
        if not refine:
            return Stop(Unrefined.DISABLED, "refinement skipped")
        if self.config.refinement.steps == 0:
            return Stop(Unrefined.DISABLED, "refinement disabled: refinement.steps is 0")
        return None

    def _prepare(self, w: WindowState) -> Stop | None:
        """Fig. 2 up to the refinement: SfM (Sec. 3.1), D_nn(p_lj) and one scale ŝ (Sec. 3.2),
        the checks before refining, the metres, Eq. (5) per frame; why the window stops
        (None = it goes on to refine)."""
        for stage in (self._reconstruct, self._align, self._check_before, self._measure_metric):
            if stop := stage(w):
                return stop
        self._supervise(w)
        return None

    # -- the stages of one window ---------------------------------------------------------
    def _predict_before(self, frames: Sequence[Frame], intrinsics: Intrinsics) -> WindowState:
        """The network's depth of every frame with the weights before the window: the
        published depth unless the window is refined, and D_nn of the alignment."""
        names, t0, counts = [f.name for f in frames], time.perf_counter(), {}
        depths = self.predictor.predict([f.image for f in frames], counts)  # computed or reused
        before = dict(zip(names, depths, strict=True))
        t = {"predict_before": time.perf_counter() - t0}
        return WindowState(frames, intrinsics, WindowResult(
            names, dict(before), before, refined=False, timings=t, predictions=counts))

    def _reconstruct(self, w: WindowState) -> Stop | None:
        """SfM of the window (Sec. 3.1: D_sfm, p_lj, r_lj) from the SfM source: its own, begun
        ahead, or the streaming SfM's carried map, how it was mapped in the result (assumed
        intrinsics: the carried focal length, refined till it settles); why it stops here."""
        t, t0 = w.timings, time.perf_counter()
        w.intrinsics = self.focal.prepare_window(w.frames, w.intrinsics, self.sfm,
                                                 self.config.sfm)
        sfm, ahead = self.sfm.reconstruct(w.frames, w.intrinsics)
        w.intrinsics = self.focal.window_done(sfm) or w.intrinsics
        if ahead:
            t["sfm_ahead"] = 1.0  # reconstructed while the previous window refined
        t["sfm"] = time.perf_counter() - t0
        t.update({f"sfm_{k}": v for k, v in sfm.timings.items()})
        w.result.sfm = sfm
        return None if sfm.ok else Stop(Unrefined.SFM_FAILED, f"SfM failed: {sfm.reason}")

    def _align(self, w: WindowState) -> Stop | None:
        """Network depth at the SfM keypoints and one scale for the whole window (Sec. 3.2,
        Eq. (4): RANSAC, weighted least squares, the relaxed selection of the supervision
        points); why the window stops here (None = it goes on)."""
        cfg, res = self.config, w.result
        t0 = time.perf_counter()
        w.alignment = a = align_window(res.sfm, w.names, w.before, self.model, cfg.alignment,
                                       cfg.refinement.sampling)
        res.alignment, res.scale = a.fit, a.fit.scale
        w.timings["align"] = time.perf_counter() - t0
        selected = int(a.fit.selected.sum())
        if not a.fit.ok or selected < cfg.min_supervision_points:
            return Stop(Unrefined.TOO_FEW_POINTS,
                        f"too few supervision points: {selected} selected of "
                        f"{a.d_sfm.size} (< {cfg.min_supervision_points})")
        return None

    def _check_before(self, w: WindowState) -> Stop | None:
        """The window checks before refining (core/checks/measures.py, 1.)."""
        res, a = w.result, w.alignment
        res.check = self.checks.before_refining(self.config.check, res.sfm, a.registered,
                                                a.d_sfm, a.d_nn, res.alignment, a.scaled)
        if res.check.reason_key:
            return Stop(res.check.reason_key, f"check: {res.check.reason}")
        return None

    def _measure_metric(self, w: WindowState) -> Stop | None:
        """Metres per SfM unit of the window (``metric.source``: a ground plane under the
        camera, or odometry) and per network unit, judged against the stream's anchor
        (core/metric/anchor.py): refused when it jumps. With ``metric.learn`` the supervision
        becomes metric (the targets m·D_sfm; the anchor's metres when the window disagrees)."""
        cfg, res = self.config, w.result
        stamps = [f.stamp for f in w.frames if f.name in set(w.registered)]
        self.metric.note_images([f.stamp for f in w.frames])
        w.metric = res.metric = estimate(cfg.metric, res.sfm, w.registered, stamps,
                                         res.scale if w.scaled else float("nan"),
                                         self.odometry)
        if why := self.metric.judge(cfg.metric, w.metric, cfg.weight_policy):
            return Stop(Unrefined.CHECK_SCALE_JUMP, f"check: {why}")
        if cfg.metric.learn and w.metric.ok:  # Eq. (5)'s targets m·D_sfm: metres are learnt
            metres = w.metric.supervision_metres_per_sfm_unit
            res.alignment = dataclasses.replace(res.alignment, scale=metres)
            res.scale = metres
        return None

    def _supervise(self, w: WindowState) -> None:
        """Eq. (5) per registered frame (targets ŝ·D_sfm at p_lj, weights exp(−r²)) and the
        window's loss before refining."""
        cfg, res = self.config, w.result
        w.supervision = build_supervision(res.sfm, w.registered, w.images, res.alignment,
                                          cfg.refinement.weighting)
        res.loss_before = float(np.mean([frame_loss(w.before[s.name], s)
                                         for s in w.supervision]))

    def _refine(self, w: WindowState, should_stop: Callable[[], bool] | None) -> RefinementResult:
        """Test-time refinement (Sec. 3.3): Adam on the encoder over the supervision, as
        ``config.refinement`` says; between steps ``on_refine_step`` may serve the interim
        weights when the window checks allow it (their time counts in "refine" and in the
        check's)."""
        cfg, res = self.config, w.result

        def stop() -> bool:
            return self._stop or (should_stop is not None and should_stop())

        serve = self.checks.arm_interim(cfg.check, w.before, w.images, res.sfm, w.registered,
                                        self.predictor.run_as_is, w.scaled)
        t0 = time.perf_counter()
        try:
            refinement = refine_encoder(
                self.model, w.supervision, cfg.refinement, should_stop=stop,
                photometric=photometric_frames(self.model, self.config, w),
                on_step=self.on_refine_step if serve else None)
        finally:
            interim = self.checks.disarm_interim()
        w.timings["refine"] = time.perf_counter() - t0
        if interim:  # part of the check's cost, spent between refinement steps
            w.timings["interim_check"] = interim
            res.check.seconds += interim
        return refinement

    def _predict_after(self, w: WindowState) -> None:
        """The refined weights' depth of every frame and the window's loss after."""
        res = w.result
        t0 = time.perf_counter()
        res.depths = dict(zip(w.names, self.predictor.predict([f.image for f in w.frames]),
                              strict=True))
        w.timings["predict_after"] = time.perf_counter() - t0
        res.loss_after = float(np.mean([frame_loss(res.depths[s.name], s)
                                        for s in w.supervision]))
        res.refined = res.refinement.steps_done > 0

    def _keep_or_refuse(self, w: WindowState, start: dict) -> Stop | None:
        """After refining: rolled back (non-finite, ``max_loss_ratio``) or refused by the
        checks after refining, the weights before it restored; or accepted: the reference of
        the next window's checks and metres, and the window's cloud."""
        cfg, res = self.config, w.result
        if why := self.checks.rollback_reason(cfg.max_loss_ratio, res.refinement.loss_history,
                                              res.loss_before, res.loss_after,
                                              self.model.encoder):
            self.weights.refuse(start)
            return Stop(Unrefined.ROLLED_BACK, f"rolled back: {why}")
        c = self.checks.after_refining(cfg.check, res.check, w.before, res.depths, res.sfm,
                                       w.registered, w.scaled)
        res.timings["check"] = c.seconds
        if c.reason_key:
            self.weights.refuse(start)
            res.depths_candidate = res.depths
            return Stop(c.reason_key, f"rejected by check: {c.reason}")
        self.checks.accept(c, res.sfm, w.registered, res.scale, w.scaled)
        self.metric.accept(cfg.metric, w.metric, cfg.weight_policy)
        res.cloud_frame, res.cloud_xyz, res.cloud_error = window_cloud(
            res.sfm, w.registered, res.alignment, self.metres_per_unit)
        return None

    # -- options, warm-up, status, lifecycle ----------------------------------------------
    def _concrete(self, config: TTRConfig) -> TTRConfig:
        """``config`` with ``refinement.loss`` "auto" resolved for this model (a copy)."""
        r = resolve_loss(config.refinement, self.model)
        return config if r is config.refinement else dataclasses.replace(config, refinement=r)

    def check_config(self, config: TTRConfig) -> None:
        """InputError if ``config`` cannot run on this model (frozen encoder levels out of range
        for its staged encoder, or all of its levels; an encoder without stages trains whole; a
        photometric loss or a metric source on affine-invariant inverse depth)."""
        frozen_stage_count(self.model.staged_encoder, config.refinement.frozen_encoder_levels)
        r = config.refinement
        check_trainable(self.model, r.trainable, r.trainable_blocks)
        if r.uses_photometric and is_affine_output(self.model):
            raise InputError(f"refinement.loss {r.loss!r} needs depth up to scale; this model "
                             "predicts affine-invariant inverse depth: use 'sfm'")
        check_source_for_output(config.metric.source, getattr(self.model, "output_kind", ""))

    def set_config(self, config: TTRConfig) -> None:
        """New options, used from the next window on."""
        config = self._concrete(config)
        self.check_config(config)
        self.config = config
        self.sfm = reconfigure_sfm_source(self.sfm, config.sfm)
        self.predictor.batch, self.predictor.reuse = config.predict_batch, config.reuse_predictions
        self.predictor.cuda_batch, self.predictor.reuse_live = (config.predict_batch_cuda,
                                                                config.reuse_live_predictions)

    def warm_up(self) -> float:
        """Pay a window's one-time costs now, in the calling thread (on CUDA kernels load at
        first use and each thread makes its own cuDNN / cuBLAS handles): a forward pass on a
        batch of grey frames (nothing cached) and two refinement steps on a copy of the model
        (:func:`~sfm_ttr_ros.core.refinement.encoder.warm_up_refinement`), and the SfM
        source's (:meth:`~sfm_ttr_ros.core.sfm.source.SfmSource.warm_up`: the streaming SfM's
        process started). Returns the seconds."""
        t0 = time.perf_counter()
        self.sfm.warm_up()
        self.predictor.run([warm_up_image(self.model)] * self.predictor.effective_batch)
        warm_up_refinement(self.model, self.config.refinement)
        return time.perf_counter() - t0

    @property
    def metres_per_unit(self) -> float | None:
        """The outputs' metres per network unit now (None: not metric); what every published
        frame needs, without the status's statistics."""
        return self.metric.factor(self.config.metric)

    def metric_status(self) -> MetricStatus:
        """The outputs' units now under the current ``metric`` options, with the odometry's
        counts (core/metric/scale.py)."""
        return self.metric.status(self.config.metric, self.odometry)

    def cancel(self) -> None:
        """Stop the running window at the next step boundary (thread-safe)."""
        self._stop = True
        self.sfm.cancel()

    def close(self) -> None:
        self.sfm.close()


def photometric_frames(model: DepthModel, config: TTRConfig,
                       w: WindowState) -> list[PhotometricFrame]:
    """The window's photometric terms once per window (Ph-TTR, the hybrid): the SfM poses'
    translations times ŝ (SfM units → network depth units); [] for ``sfm``."""
    r, res = config.refinement, w.result
    if not r.uses_photometric:
        return []
    return prepare_frames(model, w.names, w.images, res.sfm.frames, res.scale, w.intrinsics,
                          r.photometric_config())
