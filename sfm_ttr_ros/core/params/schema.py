"""The ONE parameter schema of sfm_ttr_ros: pure data, ROS-free.

One row per public parameter (the refiner node's parameter names): where its value goes (one or
more ``section.field`` targets in the typed configs), its range, choices, whether it is live (may
change while the node runs) or start-up (read-only), and what it does. Its DEFAULT and TYPE are
read from the target dataclass field, so they are written once, in the config. Why a default is
what it is lives in docs/decisions.md, not here. Sections:

=========== ====================================================================
``sfm``       :class:`~sfm_ttr_ros.core.sfm.sfm_config.SfmConfig`
``alignment`` :class:`~sfm_ttr_ros.core.alignment.scale.AlignmentConfig`
``refinement``:class:`~sfm_ttr_ros.core.refinement.refinement_config.RefinementConfig`
``ttr``       :class:`~sfm_ttr_ros.core.pipeline.TTRConfig` (its own fields)
``check``     :class:`~sfm_ttr_ros.core.checks.measures.CheckConfig` (the window checks)
``metric``    :class:`~sfm_ttr_ros.core.metric.metric_config.MetricConfig` (metres)
``stream``    :class:`~sfm_ttr_ros.core.stream.window_runner.StreamSettings`
``model``     :class:`~sfm_ttr_ros.core.models.registry.ModelConfig`
``node``      :class:`~sfm_ttr_ros.core.params.node.NodeSettings`
=========== ====================================================================

Config fields that no row targets are not parameters: they keep their defaults, and
experiments set them as ``section.field`` (``--set refinement.photometric_alpha=0.8``).
Everything else comes from this table: the node's ROS descriptors (:mod:`sfm_ttr_ros.ros.params`),
the checks of values, parameter files and ``--set`` (:mod:`.values`), the old names that still
work for one release (:mod:`.legacy`) and the reference page (:mod:`.docs`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from sfm_ttr_ros.core.alignment.scale import AlignmentConfig
from sfm_ttr_ros.core.checks.measures import CheckConfig
from sfm_ttr_ros.core.metric.metric_config import METRIC_SOURCES, MetricConfig
from sfm_ttr_ros.core.models.hf import OUTPUT_KINDS
from sfm_ttr_ros.core.models.registry import ModelConfig
from sfm_ttr_ros.core.params.node import (
    IMAGE_TRANSPORTS,
    OUTPUTS,
    QOS_RELIABILITIES,
    RELATIVE_DEPTH_CHOICES,
    USE_PROJECTION_CHOICES,
    NodeSettings,
)
from sfm_ttr_ros.core.refinement.refinement_config import (
    LOSSES,
    WEIGHT_POLICIES,
    WEIGHTINGS,
    RefinementConfig,
)
from sfm_ttr_ros.core.refinement.trainable import TRAINABLE_MODES
from sfm_ttr_ros.core.sfm.sfm_config import FEATURE_BACKENDS, SFM_MODES, SfmConfig
from sfm_ttr_ros.core.stream.keyframes import KEYFRAME_POLICIES
from sfm_ttr_ros.core.stream.settings import StreamSettings
from sfm_ttr_ros.core.window_io import TTRConfig

INT_MAX = 2**31 - 1
#: section name → the config dataclass its fields live in
SECTIONS: dict[str, type] = {"sfm": SfmConfig, "alignment": AlignmentConfig,
                             "refinement": RefinementConfig, "ttr": TTRConfig,
                             "check": CheckConfig, "metric": MetricConfig,
                             "stream": StreamSettings,
                             "model": ModelConfig, "node": NodeSettings}
TYPE_NAMES = {bool: "bool", int: "integer", float: "double", str: "string"}


def config_field(path: str) -> dataclasses.Field:
    """The dataclass field of ``section.field`` (KeyError when there is none)."""
    section, _, name = path.partition(".")
    cls = SECTIONS.get(section)
    fields = {f.name: f for f in dataclasses.fields(cls)} if cls else {}
    if name not in fields:
        raise KeyError(path)
    return fields[name]


def settable(path: str) -> bool:
    """A ``section.field`` with a plain bool / int / float / str default."""
    try:
        f = config_field(path)
    except KeyError:
        return False
    return f.default is not dataclasses.MISSING and type(f.default) in TYPE_NAMES


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
        return config_field(self.targets[0]).default

    @property
    def type(self) -> type:
        return type(self.default)

    @property
    def type_name(self) -> str:
        name = TYPE_NAMES[self.type]
        return f"{name} or bool" if self.dynamic_typing else name


def _p(name: str, targets: str, description: str, lo=None, hi=None, **kw) -> Param:
    return Param(name, tuple(targets.split(",")), description,
                 None if lo is None else (lo, hi), **kw)


_START_UP = {"live": False}
PARAMS: tuple[Param, ...] = (
    # -- windows and keyframes (live) -------------------------------------------------------
    _p("window_size", "stream.window_size", "Keyframes per SfM-TTR window.", 2, 1000),
    _p("first_window_size", "stream.first_window_size", "Keyframes of the stream's first "
       "window, so that the first refined weights reach ~/depth sooner; 0 = window_size.",
       0, 1000, constraints="0 or 2..window_size"),
    _p("window_stride", "stream.window_stride", "New keyframes between consecutive windows "
       "(window_size - window_stride keyframes overlap); 0 = window_size (side by side).", 0,
       1000, constraints="0 or <= window_size"),
    _p("keyframe_policy", "stream.keyframe_policy", "Which frames the windows take: newest = "
       "windows of the newest consecutive frames, frames the next window has left behind "
       "skipped ('stale'); all = every frame (a camera faster than the windows overloads the "
       "queue). Frames passed on are served live and published unrefined.",
       choices=KEYFRAME_POLICIES),
    _p("min_keyframe_motion", "stream.min_keyframe_motion", "Minimum mean absolute grey-level "
       "difference (0-255, on 64-px-wide thumbnails) of a keyframe to the last one; 0 = off.",
       0.0, 255.0),
    _p("overload_pending", "stream.overload_pending", "When a window is due while more frames "
       "than this wait, it is skipped and its frames pass unrefined ('overload'), so the "
       "queue drains; 0 = never.", 0, 1_000_000),
    _p("republish_unrefined", "stream.republish_unrefined", "Frames no window refines that "
       "~/depth already carried are predicted again and published on ~/depth_refined too; "
       "false = not again (counted in frames_live_only), so the worker spends its time on "
       "windows."),
    _p("max_pending", "stream.max_pending", "Bound of the input queue's frames that hold an "
       "image (and of the frames held for intrinsics); when full the OLDEST pending frame is "
       "dropped and counted, except under keyframe_policy newest a frame ~/depth served: it "
       "gives its image up and is counted stale.",
       1, 1_000_000, **_START_UP),
    _p("idle_flush_s", "stream.idle_flush_s", "After this long without input (and at least 3 "
       "of the stream's median frame intervals), the frames of an incomplete window are "
       "processed as a final window; 0 = wait for more frames.", 0.0, 3600.0),
    _p("worker_threads", "stream.worker_threads", "OpenMP threads of the background window "
       "worker's torch operations (live serving keeps torch_num_threads); 0 = the OpenMP "
       "runtime's default.", 0, 256, **_START_UP),
    _p("serve_every_steps", "stream.serve_every_steps", "While a window refines, serve its "
       "weights on ~/depth after a quarter and half this many steps, then every this many (when "
       "the window checks pass them); a window "
       "that is then refused puts the weights before it back. 0 = at the window's end only.",
       0, 100_000),
    # -- SfM (live) ---------------------------------------------------------------------------
    _p("sfm.features", "sfm.features", "SfM features: colmap = pycolmap's SIFT and sequential "
       "matcher on the CPU; torch = SIFT and mutual nearest-neighbour matching in torch (on the "
       "GPU when there is one), verified and mapped by pycolmap.", choices=FEATURE_BACKENDS,
       **_START_UP),
    _p("sfm.mode", "sfm.mode", "Where a window's SfM comes from: batch = features, matching "
       "and a fresh mapping of the window after its last frame; streaming = each keyframe's "
       "features, matches and registration into one map carried across windows as the stream "
       "takes it (the window then maps what is left; a fresh mapping, with its reason, when "
       "the continuation fits badly). streaming needs sfm.features colmap.",
       choices=SFM_MODES, **_START_UP),
    _p("sfm.max_image_size", "sfm.max_image_size", "SIFT runs on images downscaled to this "
       "longest side; 0 = full resolution.", 0, 100_000,
       constraints="0 or >= 16 (1 crashes pycolmap)"),
    _p("sfm.max_num_features", "sfm.max_num_features", "Maximum SIFT features per image.", 16,
       1_000_000),
    _p("sfm.first_octave", "sfm.first_octave", "SIFT's first octave: -1 = COLMAP's default "
       "(upsampled image), 0 = start at full size (faster).", -1, 8),
    _p("sfm.overlap", "sfm.overlap", "Sequential matching: each frame is matched with the next "
       "N frames.", 1, 1000),
    _p("sfm.num_threads", "sfm.num_threads", "Threads of feature extraction, matching and "
       "mapping.", 1, 256),
    # -- alignment (live) ---------------------------------------------------------------------
    _p("alignment.tau", "alignment.tau", "RANSAC inlier threshold on (s*D_sfm - D_nn)^2 / "
       "(s*D_sfm).", 0.0, 1e6, constraints="> 0"),
    _p("min_supervision_points", "ttr.min_supervision_points", "A window whose alignment "
       "selects fewer points than this is not refined ('too_few_points').", 1, 1_000_000),
    # -- refinement (live) --------------------------------------------------------------------
    _p("refinement.steps", "refinement.steps", "Adam steps per window (one frame per step); "
       "0 = no refinement.", 0, 1_000_000),
    _p("refinement.lr", "refinement.lr", "Adam learning rate.", 0.0, 1.0, constraints="> 0"),
    _p("refinement.loss", "refinement.loss", "A step's objective: sfm = the paper's Eq. (5); "
       "photometric = Monodepth2's photometric + smoothness loss with the window's SfM poses "
       "(Ph-TTR); hybrid = Eq. (5)'s term + lambda x that loss (the field "
       "refinement.photometric_weight); auto = "
       "hybrid, or sfm for a network whose output is affine-invariant.", choices=LOSSES),
    _p("refinement.weighting", "refinement.weighting", "Per-point weight of the SfM term: "
       "exp(-r^2) with the reprojection error r per observation or per track, or none.",
       choices=WEIGHTINGS),
    _p("refinement.frozen_encoder_levels", "refinement.frozen_encoder_levels", "Keep the "
       "encoder fixed up to its L-th feature map (1 = 1/2 ... 4 = 1/16 of the input), computed "
       "once per frame instead of once per step (faster); 0 = the whole encoder trains.",
       0, 4),
    _p("refinement.trainable", "refinement.trainable", "What a step trains: encoder = every "
       "encoder parameter (the paper); norm = the encoder's normalisation weights; lora = "
       "low-rank adapters on a transformer encoder's attention (needs peft), merged after each "
       "window.", choices=TRAINABLE_MODES),
    _p("refinement.trainable_blocks", "refinement.trainable_blocks", "Transformer encoders: "
       "train only inside the last N blocks (the blocks before run once per frame); 0 = all.",
       0, 1000),
    _p("weight_policy", "ttr.weight_policy", "Where each window's refinement starts: continue "
       "= the last accepted window's weights (a refused or failed window leaves them as they "
       "were); reset = the start-up weights (the paper).", choices=WEIGHT_POLICIES),
    _p("max_loss_ratio", "ttr.max_loss_ratio", "Roll a window back to the weights before it "
       "when its loss after refinement exceeds this many times the loss before ('rolled_back'; "
       "non-finite losses always roll back); 0 = only the non-finite check.", 0.0, 1e6),
    # -- window checks (live) -----------------------------------------------------------------
    _p("check.max_reprojection_ratio", "check.max_reprojection_ratio", "Refuse a window whose "
       "mean reprojection error exceeds this factor x the median of the stream's last 10 "
       "accepted windows ('check_reprojection'; from the third window on); 0 = off.", 0.0,
       1e3, constraints="0 or >= 1"),
    _p("check.min_parallax", "check.min_parallax", "Refuse a window whose camera centres span "
       "less than this fraction of the median SfM depth ('check_parallax': creeping or turning "
       "on the spot); 0 = off.", 0.0, 1e3),
    _p("check.max_unsupported_change", "check.max_unsupported_change", "Refuse the refined "
       "weights of a window when more than this share of the pixels far from every SfM point "
       "changed depth by more than 1.5x against the change at the points (a region SfM says "
       "nothing about, e.g. a vehicle moving with the camera: 'check_unsupported_change'); "
       "0 = off.", 0.0, 1.0),
    _p("check.unsupported_change_ratio", "check.unsupported_change_ratio", "With "
       "check.max_unsupported_change: refuse only when the share is also above this factor x "
       "its median over the stream's last 10 accepted windows (none refused before 3); 0 = "
       "the absolute threshold alone.", 0.0, 1000.0, constraints="0 or >= 1"),
    # -- metric scale (live) ------------------------------------------------------------------
    _p("metric.source", "metric.source", "Where the outputs' metres come from: none = the "
       "network's units (diagnostics say not metric); camera_height = the camera's height above "
       "a ground plane of each window's SfM points (metric.camera_height); odometry = the "
       "distance nav_msgs/Odometry on 'odom' says the camera travelled; fixed = "
       "metric.factor.", choices=METRIC_SOURCES),
    _p("metric.camera_height", "metric.camera_height", "camera_height: the camera's height "
       "above the ground, metres.", 0.0, 1e3, constraints="> 0"),
    _p("metric.factor", "metric.factor", "fixed: metres per network depth unit.", 0.0, 1e9,
       constraints="> 0"),
    _p("seed", "sfm.seed,alignment.seed,refinement.seed", "Random seed of SfM, RANSAC and "
       "refinement.", 0, INT_MAX),
    # -- model (start-up) ---------------------------------------------------------------------
    _p("model_type", "model.type", "Depth network: default (embedded weights), monodepth2, "
       "mobilenet, hf (a transformers depth model, model_path) or a plug-in "
       "python:<module>:<factory>.",
       constraints="default, monodepth2, mobilenet, hf or python:<module>:<factory>",
       **_START_UP),
    _p("model_path", "model.model_path", "model_type hf: a save_pretrained directory or a hub "
       "id (from the local Hugging Face cache).", **_START_UP),
    _p("output_kind", "model.output_kind", "model_type hf: what the network predicts; empty = "
       "from its config. relative_inverse_depth is aligned in scale and shift, the others in "
       "scale.", choices=("", *OUTPUT_KINDS), **_START_UP),
    _p("encoder_path", "model.encoder_path", "Encoder weights (monodepth2 encoder.pth, "
       "mobilenet); empty = none.", **_START_UP),
    _p("decoder_path", "model.decoder_path", "Decoder weights (monodepth2 depth.pth, "
       "mobilenet); empty = none.", **_START_UP),
    _p("device", "model.device", "Torch device.", constraints="cpu, cuda, cuda:N or auto",
       **_START_UP),
    _p("channels_last", "model.channels_last", "Run the network's convolutions in channels-last "
       "memory format (faster on CPU; outputs equal to ~1e-5).", **_START_UP),
    _p("torch_num_threads", "node.torch_num_threads", "torch.set_num_threads at start-up; 0 = "
       "torch's default.", 0, 1024, **_START_UP),
    _p("load_weights_path", "node.load_weights_path", "Encoder state dict loaded at start-up "
       "(e.g. saved by an earlier run); empty = none.", **_START_UP),
    _p("save_weights_path", "node.save_weights_path", "Where the refined encoder's state dict "
       "is saved on shutdown; empty = not saved."),
    # -- camera (live) ------------------------------------------------------------------------
    _p("fallback_intrinsics", "node.fallback_intrinsics", "Intrinsics 'fx fy cx cy' (px) used "
       "until a CameraInfo arrives (cx, cy 0 = image centre); empty = frames wait for one.",
       constraints="empty or four numbers, fx and fy > 0"),
    _p("assumed_hfov_deg", "node.assumed_hfov_deg", "Horizontal field of view (deg) that "
       "intrinsics are assumed from when the CameraInfo's K is all zero (uncalibrated), the "
       "focal length then refined by SfM window after window; 0 = frames wait.", 0.0, 179.0),
    _p("camera_info_use_projection", "node.camera_info_use_projection", "Intrinsics from "
       "CameraInfo P (rectified images: true) or K (false); auto: P when it is set and D is "
       "zero.", choices=USE_PROJECTION_CHOICES, dynamic_typing=True),
    # -- transport and outputs ----------------------------------------------------------------
    _p("image_transport", "node.image_transport", "Input: raw = sensor_msgs/Image on image; "
       "compressed = sensor_msgs/CompressedImage (JPEG / PNG) on <image>/compressed.",
       choices=IMAGE_TRANSPORTS, **_START_UP),
    _p("qos_reliability", "node.qos_reliability", "Reliability of the image, camera_info and "
       "odom subscriptions (reliable: a reliable publisher repairs what the transport loses, "
       "a best-effort one is refused with an ERROR naming the fix; best_effort takes both, "
       "losing what the transport drops).",
       choices=QOS_RELIABILITIES, **_START_UP),
    _p("qos_depth", "node.qos_depth", "History depth (KEEP_LAST) of the subscriptions and "
       "publishers.", 1, 10_000, **_START_UP),
    _p("outputs", "node.outputs", "The outputs published, comma-separated (cloud, the live "
       "depth back-projected on ~/cloud, and compressed_depth, each depth image also on "
       "<image>/compressedDepth, are off unless listed).",
       constraints=f"any of {', '.join(OUTPUTS)}"),
    _p("cloud.stride", "node.cloud_stride", "~/cloud: every this-many-th pixel of the live "
       "depth, in both directions.", 1, 1000),
    _p("cloud.max_range", "node.cloud_max_range", "~/cloud: points farther than this from the "
       "camera are left out, in the depth's units; 0 = no limit.", 0.0, 1e9),
    _p("diagnostics_period_s", "node.diagnostics_period_s", "Period of the /diagnostics timer, "
       "seconds.", 0.05, 3600.0, **_START_UP),
    _p("diagnostics.stale_after_s", "node.diagnostics_stale_after_s", "The stream status on "
       "/diagnostics warns after this long without an input image (counted from start-up "
       "before the first), seconds; 0 = never.", 0.0, 3600.0),
    _p("relative_depth", "node.relative_depth", "Depth, ~/cloud and ~/points not (yet) in "
       "metres (metric state not_metric or waiting): publish = on their relative twins "
       "(~/depth_relative, ~/depth_refined_relative, ~/cloud_relative, ~/points_relative); "
       "drop = not published. The metric topics carry metres only (REP 118).",
       choices=RELATIVE_DEPTH_CHOICES),
    _p("compressed_depth.depth_max", "node.compressed_depth_max", "compressedDepth outputs: "
       "depths at or beyond this (metres, or the network's units on the relative topics) are "
       "sent as none (image_transport's depth_max).", 1e-3, 1e6),
    _p("odom.frame_id", "node.odom_frame_id", "~/odom (outputs: odom): the frame the base's "
       "path is in (REP 105's odom, gravity-aligned with metric.source camera_height; not "
       "'odom': that is wheel odometry's).", **_START_UP),
    _p("odom.child_frame_id", "node.odom_child_frame_id", "~/odom: the robot's base frame "
       "whose pose and twist are published (REP 105's base_link).", **_START_UP),
    _p("odom.camera_mount", "node.odom_camera_mount", "~/odom: the camera optical frame in the "
       "base frame, 'x y z roll pitch yaw' (metres, degrees; the default: at the base's "
       "origin looking along its x, REP 103).", **_START_UP),
    _p("odom.publish_tf", "node.odom_publish_tf", "Also publish the base's path as the "
       "transform odom.frame_id -> odom.child_frame_id on /tf (needs tf2_msgs).", **_START_UP),
)
SCHEMA: dict[str, Param] = {p.name: p for p in PARAMS}
#: ``section.field`` → the parameter that sets it
TARGETS: dict[str, str] = {t: p.name for p in PARAMS for t in p.targets}
