"""The ONE parameter schema of sfm_ttr_ros: pure data, ROS-free.

One row per public parameter (the refiner node's parameter names): where its value goes (one or
more ``section.field`` targets in the typed configs), its range, choices, whether it is live (may
change while the node runs) or start-up (read-only), and its description. Its DEFAULT and TYPE
are read from the target dataclass field, so they are written once, in the config. Sections:

=========== ====================================================================
``sfm``       :class:`~sfm_ttr_ros.core.sfm.reconstruction.SfmConfig`
``alignment`` :class:`~sfm_ttr_ros.core.alignment.scale.AlignmentConfig`
``refinement``:class:`~sfm_ttr_ros.core.refinement.encoder.RefinementConfig`
``ttr``       :class:`~sfm_ttr_ros.core.pipeline.TTRConfig` (its own fields)
``check``     :class:`~sfm_ttr_ros.core.checks.measures.CheckConfig` (the window checks)
``stream``    :class:`~sfm_ttr_ros.core.stream.windows.StreamSettings`
``model``     :class:`~sfm_ttr_ros.core.models.registry.ModelConfig`
``node``      :class:`~sfm_ttr_ros.core.params.node.NodeSettings`
=========== ====================================================================

Everything else comes from this table: the node's ROS descriptors (:mod:`sfm_ttr_ros.ros.params`),
the check of parameter files (:func:`read_params_file`), the command line's ``--set name=value``
(:func:`parse_overrides`) and flags, and the documentation (:func:`markdown_table`,
``sfm-ttr params``, docs/parameters.md). A *values* mapping holds parameter names and, for
experiments, ``section.field`` paths of config fields that no parameter targets (e.g.
``ttr.predict_batch``); :func:`build` turns it into :class:`Settings`.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sfm_ttr_ros.core.alignment.scale import AlignmentConfig
from sfm_ttr_ros.core.checks.measures import (
    UNSUPPORTED_HISTORY,
    UNSUPPORTED_MIN_HISTORY,
    CheckConfig,
)
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.models.hf import OUTPUT_KINDS
from sfm_ttr_ros.core.models.registry import ModelConfig
from sfm_ttr_ros.core.params.node import (
    IMAGE_TRANSPORTS,
    QOS_RELIABILITIES,
    USE_PROJECTION_CHOICES,
    NodeSettings,
)
from sfm_ttr_ros.core.pipeline import WEIGHT_POLICIES, TTRConfig
from sfm_ttr_ros.core.refinement.encoder import (
    BN_MODES,
    LOSSES,
    SFM_RESIDUALS,
    WEIGHTINGS,
    RefinementConfig,
)
from sfm_ttr_ros.core.refinement.trainable import TRAINABLE_MODES
from sfm_ttr_ros.core.sfm.reconstruction import FEATURE_BACKENDS, RETRY_HISTORY, SfmConfig
from sfm_ttr_ros.core.stream.windows import StreamSettings

INT_MAX = 2**31 - 1
#: section name → the config dataclass its fields live in
SECTIONS: dict[str, type] = {"sfm": SfmConfig, "alignment": AlignmentConfig,
                             "refinement": RefinementConfig, "ttr": TTRConfig,
                             "check": CheckConfig,
                             "stream": StreamSettings, "model": ModelConfig, "node": NodeSettings}
BUILTIN_MODELS = ("default", "monodepth2", "mobilenet", "hf")
_TYPE_NAMES = {bool: "bool", int: "integer", float: "double", str: "string"}
_ARTICLES = {bool: "a bool", int: "an integer", float: "a double", str: "a string"}


def _field(path: str) -> dataclasses.Field:
    section, _, name = path.partition(".")
    cls = SECTIONS.get(section)
    fields = {f.name: f for f in dataclasses.fields(cls)} if cls else {}
    if name not in fields:
        raise KeyError(path)
    return fields[name]


def _settable(path: str) -> bool:
    """A ``section.field`` with a plain bool / int / float / str default."""
    try:
        f = _field(path)
    except KeyError:
        return False
    return f.default is not dataclasses.MISSING and type(f.default) in _TYPE_NAMES


@dataclass(frozen=True)
class Param:
    """One parameter: ``targets`` are ``section.field`` paths (the first one gives the default
    and the type); ``range`` (lo, hi) inclusive; ``live`` False = start-up only (read-only in
    ROS); ``constraints``: free text besides range and choices; ``dynamic_typing``: a bool or a
    string is accepted (``camera_info_use_projection``)."""

    name: str
    targets: tuple[str, ...]
    description: str
    range: tuple[float, float] | None = None
    choices: tuple = ()
    live: bool = True
    constraints: str = ""
    dynamic_typing: bool = False

    @property
    def default(self) -> bool | int | float | str:
        return _field(self.targets[0]).default

    @property
    def type(self) -> type:
        return type(self.default)

    @property
    def type_name(self) -> str:
        name = _TYPE_NAMES[self.type]
        return f"{name} or bool" if self.dynamic_typing else name


def _p(name: str, targets: str, description: str, lo=None, hi=None, **kw) -> Param:
    return Param(name, tuple(targets.split(",")), description,
                 None if lo is None else (lo, hi), **kw)


_START_UP = {"live": False}
PARAMS: tuple[Param, ...] = (
    # -- windows and keyframes (live) -----------------------------------------------------------
    _p("window_size", "stream.window_size", "Keyframes per SfM-TTR window.", 2, 1000),
    _p("first_window_size", "stream.first_window_size", "The stream's first window closes "
       "after this many keyframes instead of window_size, so that the first refined weights "
       "reach ~/depth sooner; 0 = window_size.", 0, 1000,
       constraints="0 or 2..window_size"),
    _p("window_stride", "stream.window_stride", "New keyframes between consecutive windows "
       "(window_size - stride frames overlap).", 1, 1000, constraints="<= window_size"),
    _p("min_keyframe_interval_s", "stream.min_keyframe_interval_s", "Minimum time between "
       "keyframes (stamps), seconds; frames in between are published unrefined ('not a "
       "keyframe').", 0.0, 3600.0),
    _p("min_keyframe_motion", "stream.min_keyframe_motion", "Minimum mean absolute grey-level "
       "difference (0-255, 64-px-wide thumbnails) to the last keyframe; 0 = off.", 0.0, 255.0),
    _p("overload_pending", "stream.overload_pending", "When a window is due while more frames "
       "than this are queued, refinement is skipped for it and its frames pass through "
       "unrefined; 0 = never.", 0, 1_000_000),
    _p("republish_unrefined", "stream.republish_unrefined", "Frames no window refines (overload, "
       "not a keyframe, ...) that ~/depth already carried are predicted again and published "
       "on ~/depth_refined too; false = not again (counted in frames_live_only): under "
       "overload the worker then spends its time on windows instead."),
    _p("max_pending", "stream.max_pending", "Bound of the input queue (and of the frames held "
       "while no intrinsics are known); when full the OLDEST pending frame is dropped and "
       "counted.", 1, 1_000_000, **_START_UP),
    _p("idle_flush_s", "stream.idle_flush_s", "After this long without input, and at least 3 "
       "of the stream's median frame intervals (a slow camera is not a stopped one), frames "
       "waiting in an incomplete window are processed as a final partial window; 0 = wait for "
       "more frames.", 0.0, 3600.0),
    _p("live_max_queue", "stream.live_max_queue", "Bound of the live-serving queue: when a "
       "frame arrives while this many wait for their live depth, the OLDEST is skipped and "
       "counted.", 1, 10_000, **_START_UP),
    _p("worker_nice", "stream.worker_nice", "Nice value added to the background window "
       "worker (SfM + refinement) so live serving gets the cores first (Linux, per thread); "
       "0 = same priority.", 0, 19, **_START_UP),
    _p("worker_threads", "stream.worker_threads", "OpenMP threads of the window worker's torch "
       "ops (its own team; live serving keeps torch_num_threads). 1 refines a window ~35 % "
       "faster than 2 on 2 cores (a second OpenMP team makes libgomp stop spin-waiting); "
       "0 = the OpenMP runtime's default.", 0, 256, **_START_UP),
    _p("serve_every_steps", "stream.serve_every_steps", "While a window refines, swap its "
       "weights into the live serving copy (~/depth) every this many steps, not only when it "
       "ends; a window that is then cancelled, rolled back or refused puts the weights from "
       "before it back. With check.max_unsupported_change > 0 each interim state is served only "
       "if its unsupported change on 2 of the window's frames passes that check; with "
       "check.holdout_fraction > 0 none is served (only verified weights are). 0 = at the "
       "window's end only.", 0, 100_000),
    # -- SfM (live) -------------------------------------------------------------------------
    _p("sfm.prefetch", "stream.prefetch_sfm", "While a window refines, reconstruct the next "
       "window's frames in the background as soon as they are all queued, so that it starts "
       "with its SfM done (every frame must be a keyframe: min_keyframe_interval_s and "
       "min_keyframe_motion 0). Off: each window reconstructs when it starts."),
    _p("sfm.max_image_size", "sfm.max_image_size", "SIFT runs on images downscaled to this "
       "longest side; 0 = full resolution.", 0, 100_000,
       constraints="0 or >= 16 (1 crashes pycolmap)"),
    _p("sfm.max_num_features", "sfm.max_num_features", "Maximum SIFT features per image.", 16,
       1_000_000),
    _p("sfm.num_threads", "sfm.num_threads", "Threads of feature extraction, matching and "
       "mapping.", 1, 256),
    _p("sfm.first_octave", "sfm.first_octave", "SIFT first octave: -1 = COLMAP default "
       "(upsampled), 0 = ~3x faster.", -1, 8),
    _p("sfm.features", "sfm.features", "SfM features: colmap = pycolmap's SIFT and sequential "
       "matcher on the CPU (the reference); torch = a weight-free SIFT (difference-of-Gaussians "
       "detector, SIFT descriptor) and mutual nearest-neighbour + ratio matching in torch, on "
       "the GPU when torch sees one, the matches verified and mapped by pycolmap as before.",
       choices=FEATURE_BACKENDS, **_START_UP),
    _p("sfm.overlap", "sfm.overlap", "Sequential matching: each frame is matched with the next "
       "N frames.", 1, 1000),
    _p("sfm.init_min_tri_angle", "sfm.init_min_tri_angle", "Minimum triangulation angle "
       "(degrees) of the initial pair (COLMAP's 16 rejects forward driving).", 0.0, 90.0,
       constraints="> 0"),
    _p("sfm.refine_intrinsics", "sfm.refine_intrinsics", "Refine the focal length in bundle "
       "adjustment (the paper holds the known intrinsics fixed)."),
    _p("sfm.mapping_attempts", "sfm.mapping_attempts", "Runs of the incremental mapper per "
       "window, each with the next random seed, while the best reconstruction so far has a mean "
       "reprojection error above sfm.retry_above_error; the one with the most registered "
       "frames, then the lowest error, is kept. From the same matches the mapper now and then "
       "settles on a wrong reconstruction with ~2x the error that another seed gets right "
       "(BENCHMARKS.md, 'Window checks'). A run takes 0.1-0.6 s (3-10 % of a window); 1 = "
       "the mapper once.", 1, 100),
    _p("sfm.retry_above_error", "sfm.retry_above_error", "Mean reprojection error (px) above "
       "which the mapper runs again (sfm.mapping_attempts); a retry that is not needed costs "
       "only its time. 0 = every attempt runs.", 0.0, 1000.0),
    _p("sfm.retry_above_ratio", "sfm.retry_above_ratio", "The mapper also runs again when the "
       f"error is above this many times the median of the stream's last {RETRY_HISTORY} "
       "reconstructions (a camera whose reconstructions fit far better than "
       "sfm.retry_above_error): wrong reconstructions measured 1.43-1.55x, right ones of "
       "driving <= 1.19x. 0 = off.",
       0.0, 1000.0),
    _p("sfm.min_points", "sfm.min_points", "Fewer 3D points than this: the window's SfM "
       "failed.", 1, 1_000_000),
    # -- alignment (live) -------------------------------------------------------------------
    _p("alignment.ransac_iterations", "alignment.ransac_iterations", "RANSAC iterations of the "
       "one-point scale model.", 1, 1_000_000),
    _p("alignment.affine_ransac_iterations", "alignment.affine_ransac_iterations", "RANSAC "
       "iterations of the per-frame two-point (scale, shift) model of relative inverse-depth "
       "networks (output_kind relative_inverse_depth): a two-point sample is all-inlier far "
       "less often than the paper's one-point one (20 iterations); ~ms per window "
       "(BENCHMARKS.md, 'ViT and affine paths').",
       1, 1_000_000),
    _p("alignment.tau", "alignment.tau", "RANSAC inlier threshold on (s*D_sfm - D_nn)^2 / "
       "(s*D_sfm).", 0.0, 1e6, constraints="> 0"),
    _p("alignment.relaxed_tau", "alignment.relaxed_tau", "Threshold of the relaxed second pass "
       "that selects the supervision points.", 0.0, 1e6, constraints="> 0"),
    _p("min_supervision_points", "ttr.min_supervision_points", "Fewer selected points in a "
       "window: do not refine.", 1, 1_000_000),
    # -- refinement (live) ------------------------------------------------------------------
    _p("refinement.steps", "refinement.steps", "Adam steps per window (one frame per step); "
       "0 = no refinement.", 0, 1_000_000),
    _p("refinement.lr", "refinement.lr", "Adam learning rate of the encoder.", 0.0, 1.0,
       constraints="> 0"),
    _p("refinement.bn_mode", "refinement.bn_mode", "BatchNorm mode during refinement.",
       choices=tuple(BN_MODES)),
    _p("refinement.weighting", "refinement.weighting", "Per-point weight: exp(-r^2) with r per "
       "observation or per track, or none (w = 1).", choices=tuple(WEIGHTINGS)),
    _p("refinement.early_stop_patience", "refinement.early_stop_patience", "Stop a window's "
       "refinement when the running loss has not improved for N steps; 0 = off.", 0,
       1_000_000),
    _p("refinement.frozen_encoder_levels", "refinement.frozen_encoder_levels", "Speed option: "
       "keep the encoder fixed up to its L-th feature map too (1 = 1/2, 2 = 1/4, 3 = 1/8, "
       "4 = 1/16 of the input), computed once per frame instead of once per step; 0 = the "
       "paper's whole-encoder refinement.", 0, 4),
    _p("refinement.trainable", "refinement.trainable", "What a step trains: encoder = every "
       "encoder parameter (the paper); norm = only the encoder's normalisation (LayerNorm / "
       "BatchNorm) affine weights; lora = low-rank adapters on a transformer encoder's "
       "attention projections (needs peft), merged into the encoder after each window.",
       choices=TRAINABLE_MODES),
    _p("refinement.lora_rank", "refinement.lora_rank", "Rank of the LoRA adapters "
       "(refinement.trainable = lora); new adapters are made for every window.", 1, 1024),
    _p("refinement.trainable_blocks", "refinement.trainable_blocks", "Train only inside the "
       "last N transformer blocks of the encoder (any refinement.trainable mode); on Depth "
       "Anything the blocks before them run once per frame, not per step (ViT-S at 518 px: "
       "steps ~2.8x cheaper than the whole encoder with N = 4, ~3.8x with N = 2); 0 = all. "
       "Transformer encoders only.", 0, 1000),
    _p("refinement.loss", "refinement.loss", "A step's objective: hybrid = Eq. (5)'s SfM term "
       "(refinement.sfm_residual) + refinement.photometric_weight x (Monodepth2's photometric "
       "+ smoothness loss with the window's SfM poses, scaled by the alignment scale); "
       "photometric = that photometric loss alone (Ph-TTR); sfm = the paper's Eq. (5) on the "
       "aligned SfM points; auto = hybrid (measured best on real video, BENCHMARKS.md), or sfm "
       "for a network whose output is affine-invariant (relative inverse depth: no depth to "
       "warp with).", choices=LOSSES),
    _p("refinement.photometric_weight", "refinement.photometric_weight", "lambda of the hybrid "
       "loss (weight of photometric + smoothness against Eq. (5)); 0 = Eq. (5) alone.", 0.0,
       1e6),
    _p("refinement.photometric_alpha", "refinement.photometric_alpha", "Weight of the SSIM term "
       "in the photometric error alpha*(1-SSIM)/2 + (1-alpha)*L1(I_t, I_s->t) (Monodepth2: "
       "0.85).", 0.0, 1.0),
    _p("refinement.smoothness_weight", "refinement.smoothness_weight", "Weight of the "
       "edge-aware disparity smoothness in the photometric loss (Monodepth2: 1e-3).", 0.0, 1e3),
    _p("refinement.photometric_sources", "refinement.photometric_sources", "Source frames of "
       "the photometric loss: window offsets of the target, comma-separated (\"-1,1\" = the "
       "previous and the next frame); unregistered sources give no term.",
       constraints="distinct non-zero integers, e.g. -1,1 or -2,-1,1,2"),
    _p("refinement.hybrid_min_parallax", "refinement.hybrid_min_parallax", "hybrid loss only: "
       "parallax gate of its photometric term, a source counts at a pixel only where moving the "
       "pixel's point from its predicted depth to infinity moves its projection by at least this "
       "many pixels (at the network's input size); far pixels are left to the SfM term; 0 = "
       "every pixel (Monodepth2's loss; 'photometric' is never gated).", 0.0, 1e3),
    _p("refinement.sfm_residual", "refinement.sfm_residual", "hybrid loss only: its SfM "
       "term's residual. relative = |s*D_sfm - D_nn| / (s*D_sfm), the same weight near and far, "
       "so that photometric_weight balances the two terms at every depth; absolute = the "
       "paper's |s*D_sfm - D_nn| (in depth units: far points dominate). Loss sfm is always the "
       "paper's.", choices=SFM_RESIDUALS),
    _p("weight_policy", "ttr.weight_policy", "Weights across windows: 'reset' (every window "
       "refines from the start-up weights), 'continue' (from the previous window's result), "
       "'continual' (continue, replaying earlier windows' supervision, pulled toward the "
       "start-up weights). Under continue and continual a window starts from the last ACCEPTED "
       "weights: a window that is refused, rolled back or fails leaves them as they were.",
       choices=WEIGHT_POLICIES),
    _p("carried_steps", "ttr.carried_steps", "Adam steps of a window that starts from carried "
       "weights (continue, continual: after an accepted window); 0 = refinement.steps.",
       0, 1_000_000),
    _p("continual.replay_windows", "ttr.replay_windows", "continual: how many earlier refined "
       "windows' supervision is kept and replayed.", 0, 1000),
    _p("continual.replay_ratio", "ttr.replay_ratio", "continual: share of the refinement steps "
       "spent on a replayed frame.", 0.0, 1.0),
    _p("continual.anchor_weight", "ttr.anchor_weight", "continual: weight of the L2 pull "
       "sum((theta - theta0)^2) toward the start-up encoder; 0 = off.", 0.0, 1e6),
    _p("max_loss_ratio", "ttr.max_loss_ratio", "Roll a window back to the weights before it "
       "when its loss after refinement exceeds this many times the loss before (non-finite "
       "losses or weights always roll back); 0 = only the non-finite check.", 0.0, 1e6),
    # -- window checks (core/checks/measures.py; live) -----------------------------------
    _p("check.holdout_fraction", "check.holdout_fraction", "Share of a window's supervision "
       "tracks held out of refinement to check it: the refined weights are served and kept only "
       "if the held-out error fell (check.holdout_margin); else the window is published "
       "unrefined ('rejected_by_check'); 0 = no held-out check.", 0.0, 0.9),
    _p("check.holdout_margin", "check.holdout_margin", "Relative fall of the held-out check "
       "error a window must show: accepted when after <= (1 - margin) * before.", 0.0, 0.9),
    _p("check.max_reprojection_error", "check.max_reprojection_error", "Refuse a window "
       "whose mean SfM reprojection error exceeds this (px) before refining "
       "('check_reprojection'); 0 = off.", 0.0, 1e3),
    _p("check.max_reprojection_ratio", "check.max_reprojection_ratio", "Refuse a window whose "
       "mean SfM reprojection error exceeds this factor x the median of the stream's last 10 "
       "accepted windows' (from the third window on; a reconstruction still wrong after the "
       "mapper's retries: 'check_reprojection'); its frames keep the weights before it; 0 = "
       "off.", 0.0, 1e3, constraints="0 or >= 1"),
    _p("check.min_track_length", "check.min_track_length", "Refuse a window whose 3D points "
       "are seen by fewer registered frames than this on average ('check_track_length'); 0 = "
       "off.", 0.0, 1e3),
    _p("check.min_parallax", "check.min_parallax", "Refuse a window whose camera centres span "
       "less than this fraction of the median SfM depth (low parallax: creeping or turning "
       "on the spot; 'check_parallax'); 0 = off.", 0.0, 1e3),
    _p("check.min_inlier_ratio", "check.min_inlier_ratio", "Refuse a window whose scale "
       "RANSAC keeps fewer inliers than this share of its points ('check_inlier_ratio'); 0 = "
       "off.", 0.0, 1.0),
    _p("check.max_scale_spread", "check.max_scale_spread", "Refuse a window in which a "
       "frame's own scale differs from the window's by more than this factor "
       "('check_scale_spread'); 0 = off.", 0.0, 1e3, constraints="0 or >= 1"),
    _p("check.max_scale_jump", "check.max_scale_jump", "Refuse a window whose camera path on "
       "the frames it shares with the previous accepted window differs by more than this "
       "factor in network units ('check_scale_jump'; windows that share no frame are not "
       "compared); 0 = off.", 0.0, 1e3, constraints="0 or >= 1"),
    _p("check.max_unsupported_change", "check.max_unsupported_change", "Refuse the refined "
       "weights of a window when, on average over its frames, more than this share of the "
       "pixels lying far (> 5 % of the width) from every SfM point changed depth by more than "
       "1.5x against the change at the points: a region SfM says nothing about, e.g. a "
       "vehicle moving with the camera ('check_unsupported_change'); 0 = off.", 0.0, 1.0),
    _p("check.unsupported_change_ratio", "check.unsupported_change_ratio", "With "
       "check.max_unsupported_change > 0: refuse only when the unsupported change is also above "
       f"this factor times its median over the stream's last {UNSUPPORTED_HISTORY} accepted "
       "windows (how far depth may move without SfM points depends on the scene: indoors, with "
       "the network far off, whole walls rightly move); a window with fewer than "
       f"{UNSUPPORTED_MIN_HISTORY} accepted ones before it is not refused by it. 0 = the "
       "absolute threshold alone.", 0.0, 1000.0, constraints="0 or >= 1"),
    _p("seed", "sfm.seed,alignment.seed,refinement.seed,check.seed", "Random seed of SfM, "
       "RANSAC, refinement and the held-out split.", 0, INT_MAX),
    # -- model (start-up) -------------------------------------------------------------------
    _p("model_type", "model.type", "Depth network: 'default' (embedded weights), 'monodepth2', "
       "'mobilenet', 'hf' (a transformers depth-estimation model, model_path) or a plug-in "
       "'python:<module>:<factory>'.",
       constraints="default, monodepth2, mobilenet, hf or python:<module>:<factory>",
       **_START_UP),
    _p("model_path", "model.model_path", "model_type hf: a directory written by "
       "save_pretrained or a hub id (e.g. depth-anything/Depth-Anything-V2-Small-hf; from the "
       "Hugging Face cache, downloaded there on first use when online).", **_START_UP),
    _p("output_kind", "model.output_kind", "model_type hf: what the network predicts; empty = "
       "detected from its config. relative_inverse_depth (MiDaS / DPT / Depth Anything "
       "relative) is aligned in scale AND shift; the others by the paper's scale.",
       choices=("", *OUTPUT_KINDS), **_START_UP),
    _p("encoder_path", "model.encoder_path", "Encoder weights file (monodepth2 / mobilenet); "
       "empty = none.", **_START_UP),
    _p("decoder_path", "model.decoder_path", "Decoder weights file (monodepth2 / mobilenet); "
       "empty = none.", **_START_UP),
    _p("num_layers", "model.num_layers", "ResNet depth of a randomly initialised monodepth2 "
       "model.", 18, 152, choices=(18, 34, 50, 101, 152), **_START_UP),
    _p("device", "model.device", "Torch device.", constraints="cpu, cuda, cuda:N or auto",
       **_START_UP),
    _p("channels_last", "model.channels_last", "Run the network's convolutions in channels-last "
       "memory format (faster on CPU: ~13 % per refinement step; outputs equal to ~1e-5, not "
       "bit for bit).", **_START_UP),
    _p("torch_num_threads", "node.torch_num_threads", "torch.set_num_threads at start-up; 0 = "
       "torch's default.", 0, 1024, **_START_UP),
    _p("load_weights_path", "node.load_weights_path", "Encoder state dict (torch.save of "
       "model.encoder.state_dict()) loaded at start-up, e.g. saved by a previous run; empty = "
       "none.", **_START_UP),
    _p("save_weights_path", "node.save_weights_path", "Where the refined encoder's state dict "
       "is saved on shutdown; empty = not saved."),
    # -- camera (live) ----------------------------------------------------------------------
    _p("fx", "node.fx", "Fallback focal length x (px) used until a CameraInfo arrives; 0 = "
       "unset.", 0.0, 1e7),
    _p("fy", "node.fy", "Fallback focal length y (px); 0 = unset.", 0.0, 1e7),
    _p("cx", "node.cx", "Fallback principal point x (px); 0 = image centre.", 0.0, 1e7),
    _p("cy", "node.cy", "Fallback principal point y (px); 0 = image centre.", 0.0, 1e7),
    _p("camera_info_use_projection", "node.camera_info_use_projection", "Intrinsics from "
       "CameraInfo P (rectified images: true) or K (false); auto: P when it is set and D is "
       "zero.", choices=USE_PROJECTION_CHOICES, dynamic_typing=True),
    # -- transport (start-up) -------------------------------------------------------------
    _p("image_transport", "node.image_transport", "Input images: 'raw' = sensor_msgs/Image on "
       "image; 'compressed' = sensor_msgs/CompressedImage (JPEG / PNG) on <image>/compressed, "
       "the image_transport convention of recorded robot bags.", choices=IMAGE_TRANSPORTS,
       **_START_UP),
    _p("qos_reliability", "node.qos_reliability", "Reliability of the image and camera_info "
       "subscriptions (best_effort for sensor-data publishers).", choices=QOS_RELIABILITIES,
       **_START_UP),
    _p("qos_depth", "node.qos_depth", "History depth (KEEP_LAST) of the subscriptions and "
       "publishers.", 1, 10_000, **_START_UP),
    _p("publish_live", "node.publish_live", "Publish ~/depth: every frame at once, predicted by "
       "the serving copy of the network (the newest refined weights)."),
    _p("publish_refined", "node.publish_refined", "Publish ~/depth_refined: every frame again "
       "once its window is done (refined, or unrefined with a reason)."),
    _p("publish_colored", "node.publish_colored", "Publish ~/depth_colored (bgr8, of the live "
       "depth)."),
    _p("publish_points", "node.publish_points", "Publish ~/points (the window's sparse SfM "
       "cloud)."),
    _p("publish_diagnostics", "node.publish_diagnostics", "Publish /diagnostics after each "
       "window and periodically."),
    _p("diagnostics_period_s", "node.diagnostics_period_s", "Period of the /diagnostics timer, "
       "seconds.", 0.05, 3600.0, **_START_UP),
)
SCHEMA: dict[str, Param] = {p.name: p for p in PARAMS}
#: ``section.field`` → the parameter that sets it
TARGETS: dict[str, str] = {t: p.name for p in PARAMS for t in p.targets}


@dataclass
class Settings:
    """Everything a set of parameter values configures."""

    ttr: TTRConfig
    stream: StreamSettings
    model: ModelConfig
    node: NodeSettings


def defaults() -> dict[str, Any]:
    """Every parameter at its default (the dataclass fields' defaults)."""
    return {p.name: p.default for p in PARAMS}


def _close(name: str, fields: bool = True) -> str:
    """" (did you mean a, b?)" for the parameters (and settable fields) close to ``name``."""
    paths = (f"{s}.{f.name}" for s, c in SECTIONS.items() for f in dataclasses.fields(c))
    candidates = [*SCHEMA, *(p for p in paths if fields and p not in TARGETS and _settable(p))]
    close = difflib.get_close_matches(name, candidates, n=3, cutoff=0.6)
    return f" (did you mean {', '.join(close)}?)" if close else ""


#: parameters that were replaced, and what replaces them
RENAMED = {"reset_each_window": "weight_policy (true = reset, false = continue)"}


def _unknown(name: str) -> str:
    if name in RENAMED:
        return f"parameter {name!r} was replaced by {RENAMED[name]}"
    return f"unknown parameter {name!r}{_close(name)}; `sfm-ttr params` lists them"


def _value_type(name: str) -> type:
    return SCHEMA[name].type if name in SCHEMA else type(_field(name).default)


def check_value(name: str, value: Any) -> str:
    """Why ``value`` is not acceptable for parameter (or settable config field) ``name``: its
    type (a double given as an integer is an error, as for rclpy), range and choices; "" when
    it is acceptable."""
    param = SCHEMA.get(name)
    if param is None and not (name not in TARGETS and _settable(name)):
        return _unknown(name)
    want = _value_type(name)
    if param is not None and param.dynamic_typing:
        ok = isinstance(value, bool | str)
    else:
        ok = isinstance(value, want) and (want is bool or not isinstance(value, bool))
    if not ok:
        hint = " (write doubles as 1.0, not 1)" if want is float and isinstance(value, int) \
            else ""
        return f"{name} must be {_ARTICLES[want]}, got {value!r}{hint}"
    if param is None:
        return ""
    if param.range is not None and not isinstance(value, bool | str):
        lo, hi = param.range
        if not (math.isfinite(value) and lo <= value <= hi):
            side = f">= {_number(lo)}" if not value >= lo else f"<= {_number(hi)}"
            return f"{name} must be {side} (range {_number(lo)} … {_number(hi)}), got {value!r}"
    if param.choices and not param.dynamic_typing and value not in param.choices:
        return f"{name} must be one of {', '.join(map(str, param.choices))}; got {value!r}"
    return ""


def _check_model(values: Mapping[str, Any]) -> None:
    kind = str(values["model_type"]).strip()
    if kind.lower() not in BUILTIN_MODELS and ":" not in kind:
        raise InputError(f"model_type must be default, monodepth2, mobilenet, hf or "
                         f"python:<module>:<factory>; got {kind!r}")
    if kind.lower() == "hf" and not str(values["model_path"]).strip():
        raise InputError("model_type hf needs model_path: a save_pretrained directory or a hub "
                         "id, e.g. depth-anything/Depth-Anything-V2-Small-hf")
    if bool(str(values["encoder_path"]).strip()) != bool(str(values["decoder_path"]).strip()):
        raise InputError("give both encoder_path and decoder_path, or neither")


def build(values: Mapping[str, Any]) -> Settings:
    """The configs of ``values`` (parameters not given keep their defaults; ``section.field``
    entries set config fields no parameter targets). :class:`InputError` says what is wrong."""
    for name, value in values.items():
        reason = check_value(name, value)
        if reason:
            raise InputError(reason)
    full = {**defaults(), **values}
    _check_model(full)
    sections: dict[str, dict[str, Any]] = {s: {} for s in SECTIONS}
    for name, value in full.items():
        for target in SCHEMA[name].targets if name in SCHEMA else (name,):
            section, _, attr = target.partition(".")
            sections[section][attr] = value
    try:
        ttr_top = sections.pop("ttr")
        return Settings(
            stream=StreamSettings(**sections["stream"]),
            ttr=TTRConfig(sfm=SfmConfig(**sections["sfm"]),
                          alignment=AlignmentConfig(**sections["alignment"]),
                          check=CheckConfig(**sections["check"]),
                          refinement=RefinementConfig(**sections["refinement"]), **ttr_top),
            model=ModelConfig(**sections["model"]),
            node=NodeSettings(**sections["node"]))
    except InputError:
        raise
    except (TypeError, ValueError) as exc:
        raise InputError(f"bad parameters: {exc}") from exc


def validate(values: Mapping[str, Any]) -> str:
    """Why this set of values is not acceptable ("" when it is): every value's type, range and
    choices, the rules between parameters and every config's own checks."""
    try:
        build(values)
    except InputError as exc:
        return str(exc)
    return ""


# ---------------------------------------------------------------------------------------------
# Parameter files and the command line
# ---------------------------------------------------------------------------------------------


def _flatten(d: Mapping, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def read_params_file(path: str | Path, node_name: str) -> dict[str, Any]:
    """The ``ros__parameters`` a ROS 2 parameter file gives node ``node_name`` (wildcard
    sections ``/**`` first, then the node's own), checked as the node checks them: every key a
    parameter, of its type (a double written as ``1`` is an error, as for rclpy) and within its
    range and choices. Nested mappings are flattened with dots."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise InputError(f"parameter file not found: {path}")
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise InputError(f"cannot read parameter file {path}: {exc}") from exc
    if not isinstance(doc, Mapping):
        raise InputError(f"{path}: expected a mapping of node names to ros__parameters")
    wild, own = {}, {}
    for section, body in doc.items():
        s = str(section).strip()
        if not isinstance(body, Mapping) or "ros__parameters" not in body:
            continue
        params = body["ros__parameters"]
        if not isinstance(params, Mapping):
            raise InputError(f"{path}: ros__parameters of {s!r} is not a mapping")
        if s in ("/**", "**"):
            wild.update(_flatten(params))
        elif s.lstrip("/").split("/")[-1] == node_name:
            own.update(_flatten(params))
    values = {**wild, **own}
    if not values:
        raise InputError(f"{path}: no ros__parameters for node {node_name!r}")
    for key, value in values.items():
        if key not in SCHEMA:
            if key in RENAMED:
                raise InputError(f"{path}: {_unknown(key)}")
            raise InputError(f"{path}: {key!r} is not a parameter of the {node_name} node"
                             f"{_close(key, fields=False)}")
        reason = check_value(key, value)
        if reason:
            raise InputError(f"{path}: {reason}")
    return values


def _typed(kind: type, dynamic: bool, text: str) -> Any:
    """``text`` read as a YAML scalar, then made the parameter's type where that is lossless:
    integers (and YAML 1.1's ``3e-5``, a string to it) become doubles, anything becomes the
    text itself for a string parameter."""
    import yaml

    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        value = text
    if dynamic:
        return value if isinstance(value, bool) else text
    if kind is str:
        return value if isinstance(value, str) else text
    if kind is float and not isinstance(value, bool | float):
        try:
            return float(text)
        except ValueError:
            return value  # the type check names what was expected
    return value


def parse_overrides(items: Iterable[str]) -> dict[str, Any]:
    """``["name=value", ...]`` (the command line's repeated ``--set``) → values. ``name`` is a
    parameter, or a ``section.field`` path: one that a parameter targets means that parameter
    (``model.channels_last`` = ``channels_last``), any other plain config field is set as it is
    (``ttr.predict_batch=4``, experiments). Values are typed by the schema; later items win."""
    out: dict[str, Any] = {}
    for item in items:
        name, sep, text = str(item).partition("=")
        name, text = name.strip(), text.strip()
        if not sep or not name:
            raise InputError(f"--set {item!r}: expected NAME=VALUE")
        name = TARGETS.get(name, name)
        if name not in SCHEMA and not _settable(name):
            raise InputError(f"--set {item!r}: {_unknown(name)}")
        param = SCHEMA.get(name)
        value = _typed(_value_type(name), bool(param and param.dynamic_typing), text)
        reason = check_value(name, value)
        if reason:
            raise InputError(f"--set {item!r}: {reason}")
        out[name] = value
    return out


# ---------------------------------------------------------------------------------------------
# Documentation
# ---------------------------------------------------------------------------------------------


def ros_literal(v: Any) -> str:
    """A parameter value as ROS 2 reads it back with its type (YAML): ``-p NAME:=`` this, or a
    parameter file's value. A float always has a dot (``1.0``, ``1.0e-05``: ROS reads ``1`` as
    an integer, and YAML 1.1 reads ``1e-05`` as a string)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, float):
        text = repr(v)
        mantissa, e, exponent = text.partition("e")
        if "." not in mantissa and mantissa.lstrip("-").isdigit():
            mantissa += ".0"
        return mantissa + e + exponent
    return repr(v)


def _number(v: int | float) -> str:
    """A range bound, short: 0, 3600, 0.05, 1e6, 2147483647."""
    text = f"{v:g}"
    if isinstance(v, int) and float(text) != v:
        return str(v)
    return text.replace("e+0", "e").replace("e+", "e")


def _limits(p: Param) -> str:
    parts = []
    if p.range is not None and not p.choices:
        parts.append(f"{_number(p.range[0])} … {_number(p.range[1])}")
    if p.choices:
        parts.append(", ".join(f"`{c}`" for c in p.choices))
    if p.constraints:
        parts.append(p.constraints.replace("<=", "≤"))
    return "; ".join(parts) or "—"


def markdown_table() -> str:
    """The parameter table (name, type, default, range / choices, live or start-up,
    description) as Markdown: ``sfm-ttr params`` prints it, docs/parameters.md holds it."""
    lines = ["| parameter | type | default | range / values | set | description |",
             "| --- | --- | --- | --- | --- | --- |"]
    for p in PARAMS:
        lines.append(f"| `{p.name}` | {p.type_name} | `{ros_literal(p.default)}` | {_limits(p)} | "
                     f"{'live' if p.live else 'start-up'} | {p.description} |")
    return "\n".join(lines) + "\n"
