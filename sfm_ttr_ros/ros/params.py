"""The refiner node's parameters: one table (name, default, range, read-only, where it goes),
declared with full descriptors, validated as a whole, and turned into the core's configs.

Live parameters (not read-only) take effect at the next window: the node builds a new
:class:`~sfm_ttr_ros.core.pipeline.TTRConfig` and
:class:`~sfm_ttr_ros.core.stream.StreamSettings` from
the current values at the start of every window (``SfmTTR.set_config``). rclpy itself enforces
types, ranges and read-only; :func:`validate` adds what descriptors cannot say (enum values,
``window_stride <= window_size``, ``lr > 0``, both model files or neither, ...).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
)

from sfm_ttr_ros.core.alignment import AlignmentConfig
from sfm_ttr_ros.core.frames import InputError
from sfm_ttr_ros.core.models.registry import ModelConfig
from sfm_ttr_ros.core.pipeline import TTRConfig
from sfm_ttr_ros.core.refinement import BN_MODES, WEIGHTINGS, RefinementConfig
from sfm_ttr_ros.core.sfm import SfmConfig
from sfm_ttr_ros.core.stream import StreamSettings

INT_MAX = 2**31 - 1


@dataclass(frozen=True)
class ParamSpec:
    """One parameter. ``target`` is where the value goes: ``"<section>.<field>"`` with section
    ``sfm``, ``alignment``, ``refinement``, ``ttr`` (TTRConfig itself), ``stream``
    (StreamSettings), ``model`` (ModelConfig), or ``node`` (read by the node directly); several
    targets separated by ``,``."""

    name: str
    default: bool | int | float | str
    description: str
    target: str
    lo: int | float | None = None
    hi: int | float | None = None
    read_only: bool = False
    choices: tuple = ()
    constraints: str = ""  # free text for additional_constraints (besides choices)
    dynamic_typing: bool = False

    @property
    def type(self) -> int:
        if self.dynamic_typing:
            return ParameterType.PARAMETER_NOT_SET
        return {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
                float: ParameterType.PARAMETER_DOUBLE,
                str: ParameterType.PARAMETER_STRING}[type(self.default)]

    def descriptor(self) -> ParameterDescriptor:
        d = ParameterDescriptor(name=self.name, type=self.type, description=self.description,
                                read_only=self.read_only, dynamic_typing=self.dynamic_typing)
        text = self.constraints
        if self.choices:
            text = (f"one of: {', '.join(map(str, self.choices))}"
                    + (f"; {text}" if text else ""))
        d.additional_constraints = text
        if self.lo is not None and isinstance(self.default, int) \
                and not isinstance(self.default, bool):
            d.integer_range = [IntegerRange(from_value=int(self.lo), to_value=int(self.hi),
                                            step=1)]
        elif self.lo is not None and isinstance(self.default, float):
            d.floating_point_range = [FloatingPointRange(from_value=float(self.lo),
                                                         to_value=float(self.hi), step=0.0)]
        return d


_P = ParamSpec
_RO = {"read_only": True}
PARAMS: tuple[ParamSpec, ...] = (
    # -- windows and keyframes (live) -----------------------------------------------------------
    _P("window_size", 10, "Keyframes per SfM-TTR window.", "stream.window_size", 2, 1000),
    _P("window_stride", 5, "New keyframes between consecutive windows (window_size - stride "
       "frames overlap).", "stream.window_stride", 1, 1000, constraints="<= window_size"),
    _P("min_keyframe_interval_s", 0.0, "Minimum time between keyframes (stamps), seconds; "
       "frames in between are published unrefined ('not a keyframe').",
       "stream.min_keyframe_interval_s", 0.0, 3600.0),
    _P("min_keyframe_motion", 0.0, "Minimum mean absolute grey-level difference (0-255, "
       "64-px-wide thumbnails) to the last keyframe; 0 = off.", "stream.min_keyframe_motion",
       0.0, 255.0),
    _P("overload_pending", 30, "When a window is due while more frames than this are queued, "
       "refinement is skipped for it and its frames pass through unrefined; 0 = never.",
       "stream.overload_pending", 0, 1_000_000),
    _P("max_pending", 100, "Bound of the input queue (and of the frames held while no "
       "intrinsics are known); when full the OLDEST pending frame is dropped and counted.",
       "stream.max_pending", 1, 1_000_000, **_RO),
    _P("idle_flush_s", 2.0, "After this long without input, frames waiting in an incomplete "
       "window are processed as a final partial window; 0 = wait for more frames.",
       "stream.idle_flush_s", 0.0, 3600.0),
    # -- SfM (live) -------------------------------------------------------------------------
    _P("sfm.max_image_size", 640, "SIFT runs on images downscaled to this longest side; "
       "0 = full resolution.", "sfm.max_image_size", 0, 100_000),
    _P("sfm.max_num_features", 8192, "Maximum SIFT features per image.", "sfm.max_num_features",
       16, 1_000_000),
    _P("sfm.num_threads", 2, "Threads of feature extraction, matching and mapping.",
       "sfm.num_threads", 1, 256),
    _P("sfm.first_octave", -1, "SIFT first octave: -1 = COLMAP default (upsampled), 0 = ~3x "
       "faster.", "sfm.first_octave", -1, 8),
    _P("sfm.overlap", 10, "Sequential matching: each frame is matched with the next N frames.",
       "sfm.overlap", 1, 1000),
    _P("sfm.init_min_tri_angle", 1.0, "Minimum triangulation angle (degrees) of the initial "
       "pair (COLMAP's 16 rejects forward driving).", "sfm.init_min_tri_angle", 0.0, 90.0),
    _P("sfm.refine_intrinsics", False, "Refine the focal length in bundle adjustment (the "
       "paper holds the known intrinsics fixed).", "sfm.refine_intrinsics"),
    _P("sfm.min_points", 20, "Fewer 3D points than this: the window's SfM failed.",
       "sfm.min_points", 1, 1_000_000),
    # -- alignment (live) -------------------------------------------------------------------
    _P("alignment.ransac_iterations", 20, "RANSAC iterations of the one-point scale model.",
       "alignment.ransac_iterations", 1, 1_000_000),
    _P("alignment.tau", 0.5, "RANSAC inlier threshold on (s*D_sfm - D_nn)^2 / (s*D_sfm).",
       "alignment.tau", 0.0, 1e6, constraints="> 0"),
    _P("alignment.relaxed_tau", 0.5, "Threshold of the relaxed second pass that selects the "
       "supervision points.", "alignment.relaxed_tau", 0.0, 1e6, constraints="> 0"),
    _P("min_supervision_points", 50, "Fewer selected points in a window: do not refine.",
       "ttr.min_supervision_points", 1, 1_000_000),
    # -- refinement (live) ------------------------------------------------------------------
    _P("refinement.steps", 200, "Adam steps per window (one frame per step); 0 = no "
       "refinement.", "refinement.steps", 0, 1_000_000),
    _P("refinement.lr", 1e-4, "Adam learning rate of the encoder.", "refinement.lr", 0.0, 1.0,
       constraints="> 0"),
    _P("refinement.bn_mode", "frozen", "BatchNorm mode during refinement.",
       "refinement.bn_mode", choices=tuple(BN_MODES)),
    _P("refinement.weighting", "observation", "Per-point weight: exp(-r^2) with r per "
       "observation or per track, or none (w = 1).", "refinement.weighting",
       choices=tuple(WEIGHTINGS)),
    _P("refinement.early_stop_patience", 0, "Stop a window's refinement when the running loss "
       "has not improved for N steps; 0 = off.", "refinement.early_stop_patience", 0,
       1_000_000),
    _P("refinement.frozen_encoder_levels", 0, "Speed option: keep the encoder fixed up to its "
       "L-th feature map too (1 = 1/2, 2 = 1/4, 3 = 1/8, 4 = 1/16 of the input), computed "
       "once per frame instead of once per step; 0 = the paper's whole-encoder refinement.",
       "refinement.frozen_encoder_levels", 0, 4),
    _P("reset_each_window", True, "True (default, measured better: BENCHMARKS.md): every "
       "window starts from the original weights; False: refinement continues from the "
       "previous window's weights.", "ttr.reset_each_window"),
    _P("seed", 0, "Random seed of SfM, RANSAC and refinement.",
       "sfm.seed,alignment.seed,refinement.seed", 0, INT_MAX),
    # -- model (start-up) -------------------------------------------------------------------
    _P("model_type", "default", "Depth network: 'default' (embedded weights), 'monodepth2', "
       "'mobilenet' or a plug-in 'python:<module>:<factory>'.", "model.type",
       constraints="default, monodepth2, mobilenet or python:<module>:<factory>", **_RO),
    _P("encoder_path", "", "Encoder weights file (monodepth2 / mobilenet); empty = none.",
       "model.encoder_path", **_RO),
    _P("decoder_path", "", "Decoder weights file (monodepth2 / mobilenet); empty = none.",
       "model.decoder_path", **_RO),
    _P("num_layers", 18, "ResNet depth of a randomly initialised monodepth2 model.",
       "model.num_layers", 18, 152, choices=(18, 34, 50, 101, 152), **_RO),
    _P("device", "cpu", "Torch device.", "model.device",
       constraints="cpu, cuda, cuda:N or auto", **_RO),
    _P("channels_last", False, "Run the network's convolutions in channels-last memory format "
       "(faster on CPU: ~13 % per refinement step; outputs equal to ~1e-5, not bit for bit).",
       "model.channels_last", **_RO),
    _P("torch_num_threads", 0, "torch.set_num_threads at start-up; 0 = torch's default.",
       "node.torch_num_threads", 0, 1024, **_RO),
    _P("load_weights_path", "", "Encoder state dict (torch.save of model.encoder.state_dict()) "
       "loaded at start-up, e.g. saved by a previous run; empty = none.",
       "node.load_weights_path", **_RO),
    _P("save_weights_path", "", "Where the refined encoder's state dict is saved on shutdown; "
       "empty = not saved.", "node.save_weights_path"),
    # -- camera (live) ----------------------------------------------------------------------
    _P("fx", 0.0, "Fallback focal length x (px) used until a CameraInfo arrives; 0 = unset.",
       "node.fx", 0.0, 1e7),
    _P("fy", 0.0, "Fallback focal length y (px); 0 = unset.", "node.fy", 0.0, 1e7),
    _P("cx", 0.0, "Fallback principal point x (px); 0 = image centre.", "node.cx", 0.0, 1e7),
    _P("cy", 0.0, "Fallback principal point y (px); 0 = image centre.", "node.cy", 0.0, 1e7),
    _P("camera_info_use_projection", "auto", "Intrinsics from CameraInfo P (rectified images: "
       "true) or K (false); auto: P when it is set and D is zero.",
       "node.camera_info_use_projection", choices=("auto", "true", "false"),
       dynamic_typing=True),
    # -- transport (start-up) -------------------------------------------------------------
    _P("qos_reliability", "reliable", "Reliability of the image and camera_info subscriptions "
       "(best_effort for sensor-data publishers).", "node.qos_reliability",
       choices=("reliable", "best_effort"), **_RO),
    _P("qos_depth", 30, "History depth (KEEP_LAST) of the subscriptions and publishers.",
       "node.qos_depth", 1, 10_000, **_RO),
    _P("publish_colored", True, "Publish ~/depth_colored (bgr8).", "node.publish_colored"),
    _P("publish_points", True, "Publish ~/points (the window's sparse SfM cloud).",
       "node.publish_points"),
    _P("publish_diagnostics", True, "Publish /diagnostics after each window and periodically.",
       "node.publish_diagnostics"),
    _P("diagnostics_period_s", 1.0, "Period of the /diagnostics timer, seconds.",
       "node.diagnostics_period_s", 0.05, 3600.0, **_RO),
)
SPECS: dict[str, ParamSpec] = {p.name: p for p in PARAMS}
DEFAULTS: dict[str, Any] = {p.name: p.default for p in PARAMS}


def declare(node) -> None:
    """Declare every parameter of the table on ``node`` (overrides from --params-file / -p
    are applied and checked against type and range by rclpy here)."""
    node.declare_parameters("", [(p.name, p.default, p.descriptor()) for p in PARAMS])


def current_values(node) -> dict[str, Any]:
    return {name: node.get_parameter(name).value for name in SPECS}


def parse_use_projection(value) -> bool | None:
    """``camera_info_use_projection`` → None (auto), True (P) or False (K)."""
    if isinstance(value, bool):
        return value
    text = str(value).strip().lower()
    if text == "auto":
        return None
    if text in ("true", "p"):
        return True
    if text in ("false", "k"):
        return False
    raise InputError(f"camera_info_use_projection must be auto, true or false, got {value!r}")


def _sections(values: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    for spec in PARAMS:
        value = values.get(spec.name, spec.default)
        for target in spec.target.split(","):
            section, attr = target.split(".", 1)
            out.setdefault(section, {})[attr] = value
    return out


def build_ttr_config(values: Mapping[str, Any]) -> TTRConfig:
    s = _sections(values)
    return TTRConfig(sfm=SfmConfig(**s["sfm"]), alignment=AlignmentConfig(**s["alignment"]),
                     refinement=RefinementConfig(**s["refinement"]), **s["ttr"])


def build_stream_settings(values: Mapping[str, Any]) -> StreamSettings:
    return StreamSettings(**_sections(values)["stream"])


def build_model_config(values: Mapping[str, Any]) -> ModelConfig:
    return ModelConfig(**_sections(values)["model"])


def node_values(values: Mapping[str, Any]) -> dict[str, Any]:
    """The ``node.*`` entries (read by the node itself)."""
    return _sections(values)["node"]


def validate(values: Mapping[str, Any]) -> str:
    """Why this set of values is not acceptable ("" when it is)."""
    for spec in PARAMS:
        v = values.get(spec.name, spec.default)
        if spec.name == "camera_info_use_projection":
            try:
                parse_use_projection(v)
            except InputError as exc:
                return str(exc)
        elif spec.choices and v not in spec.choices:
            return (f"{spec.name} must be one of {', '.join(map(str, spec.choices))}; "
                    f"got {v!r}")
    kind = str(values.get("model_type", "")).strip()
    if kind.lower() not in ("default", "monodepth2", "mobilenet") and ":" not in kind:
        return (f"model_type must be default, monodepth2, mobilenet or "
                f"python:<module>:<factory>; got {kind!r}")
    if bool(str(values.get("encoder_path", "")).strip()) != \
            bool(str(values.get("decoder_path", "")).strip()):
        return "give both encoder_path and decoder_path, or neither"
    fx, fy = float(values.get("fx", 0.0)), float(values.get("fy", 0.0))
    if (fx > 0) != (fy > 0):
        return f"set both fallback focal lengths fx and fy, or neither (got fx={fx}, fy={fy})"
    try:
        build_stream_settings(values)
        build_ttr_config(values)
        build_model_config(values)
    except (InputError, TypeError, ValueError) as exc:
        return str(exc)
    return ""
