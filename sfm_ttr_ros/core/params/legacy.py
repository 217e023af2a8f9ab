"""Parameter names of the last release that still work, with a warning, for one more release.

Each :class:`Legacy` row names an old parameter, the default it had (so that the node can still
declare it, and a value equal to it can be ignored) and what became of it: replaced by a
parameter (``translate`` gives the new values), kept as a config field that is no longer a
parameter (``translate`` sets the field, as ``--set section.field`` does), or removed because
it lost its measurement (no ``translate``: its old default is ignored with a warning, any other
value is refused, since the behaviour it asked for is gone; docs/decisions.md says why).
:func:`resolve` applies the table to a set of values.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.params.node import OUTPUTS, NodeSettings, parse_outputs

#: (old value, every value given) → the values that replace it
Translate = Callable[[Any, Mapping[str, Any]], dict[str, Any]]


@dataclass(frozen=True)
class Legacy:
    name: str
    default: bool | int | float | str
    becomes: str  # what replaces it, for the warning
    translate: Translate | None = None  # None: removed


def _field(path: str) -> Translate:
    return lambda value, _: {path: value}


def _fallback(values: Mapping[str, Any]) -> dict[str, Any]:
    """fx / fy / cx / cy (whichever were given, the others 0) → ``fallback_intrinsics``."""
    k = [float(values.get(n, 0.0)) for n in ("fx", "fy", "cx", "cy")]
    text = "" if k[0] <= 0 and k[1] <= 0 else " ".join(repr(v) for v in k)
    return {"fallback_intrinsics": text}


def _output(name: str) -> Translate:
    def translate(value: Any, values: Mapping[str, Any]) -> dict[str, Any]:
        current = values.get("outputs", NodeSettings.outputs)  # the new name's, if given
        names = (parse_outputs(current) - {name}) | ({name} if value else set())
        return {"outputs": ",".join(n for n in OUTPUTS if n in names)}
    return translate


LEGACY: tuple[Legacy, ...] = (
    *(Legacy(k, 0.0, "fallback_intrinsics ('fx fy cx cy')", lambda _, v: _fallback(v))
      for k in ("fx", "fy", "cx", "cy")),
    Legacy("publish_live", True, "outputs (depth)", _output("depth")),
    Legacy("publish_colored", True, "outputs (depth_colored)", _output("depth_colored")),
    Legacy("publish_refined", True, "outputs (depth_refined)", _output("depth_refined")),
    Legacy("publish_points", True, "outputs (points)", _output("points")),
    Legacy("publish_diagnostics", True, "outputs (diagnostics)", _output("diagnostics")),
    Legacy("reset_each_window", False, "weight_policy (true = reset, false = continue)",
           lambda v, _: {"weight_policy": "reset" if v else "continue"}),
    # kept as config fields: settable as section.field for experiments
    Legacy("num_layers", 18, "the field model.num_layers", _field("model.num_layers")),
    Legacy("live_max_queue", 4, "the field stream.live_max_queue",
           _field("stream.live_max_queue")),
    Legacy("worker_nice", 10, "the field stream.worker_nice", _field("stream.worker_nice")),
    Legacy("sfm.prefetch", True, "the field stream.prefetch_sfm",
           _field("stream.prefetch_sfm")),
    Legacy("sfm.refine_intrinsics", False, "the field sfm.refine_intrinsics",
           _field("sfm.refine_intrinsics")),
    Legacy("sfm.min_points", 20, "the field sfm.min_points", _field("sfm.min_points")),
    Legacy("alignment.ransac_iterations", 20, "the field alignment.ransac_iterations",
           _field("alignment.ransac_iterations")),
    Legacy("sfm.retry_above_error", 0.8, "the field sfm.retry_above_error",
           _field("sfm.retry_above_error")),
    Legacy("sfm.retry_above_ratio", 1.3, "the field sfm.retry_above_ratio",
           _field("sfm.retry_above_ratio")),
    Legacy("alignment.relaxed_tau", 0.5, "the field alignment.relaxed_tau",
           _field("alignment.relaxed_tau")),
    Legacy("alignment.affine_ransac_iterations", 200, "the field "
           "alignment.affine_ransac_iterations", _field("alignment.affine_ransac_iterations")),
    Legacy("refinement.photometric_alpha", 0.85, "the field refinement.photometric_alpha",
           _field("refinement.photometric_alpha")),
    Legacy("refinement.smoothness_weight", 1e-3, "the field refinement.smoothness_weight",
           _field("refinement.smoothness_weight")),
    Legacy("refinement.photometric_sources", "-1,1", "the field "
           "refinement.photometric_sources", _field("refinement.photometric_sources")),
    Legacy("refinement.lora_rank", 8, "the field refinement.lora_rank",
           _field("refinement.lora_rank")),
    # 2026-11-29, kept as config fields (docs/decisions.md says why each left the schema)
    *(Legacy(path, default, f"the field {path}", _field(path)) for path, default in (
        ("sfm.init_min_tri_angle", 1.0), ("sfm.mapping_attempts", 2),
        ("refinement.photometric_weight", 10.0), ("refinement.sfm_residual", "relative"),
        ("refinement.bn_mode", "frozen"), ("refinement.precision", "fp32"),
        ("check.max_reprojection_error", 2.0), ("check.max_scale_jump", 2.0))),
    Legacy("min_keyframe_interval_s", 0.0, "the field stream.min_keyframe_interval_s",
           _field("stream.min_keyframe_interval_s")),
    Legacy("reuse_live_predictions", True, "the field ttr.reuse_live_predictions",
           _field("ttr.reuse_live_predictions")),
    Legacy("compressed_depth.png_level", 1, "the field node.compressed_depth_png_level",
           _field("node.compressed_depth_png_level")),
    # removed: lost their measurement
    Legacy("carried_steps", 0, "nothing (removed)"),
    Legacy("continual.replay_windows", 3, "nothing (removed with weight_policy continual)"),
    Legacy("continual.replay_ratio", 0.5, "nothing (removed with weight_policy continual)"),
    Legacy("continual.anchor_weight", 0.01, "nothing (removed with weight_policy continual)"),
    Legacy("check.holdout_fraction", 0.0, "nothing (the held-out check was removed)"),
    Legacy("check.holdout_margin", 0.0, "nothing (the held-out check was removed)"),
    Legacy("check.min_track_length", 0.0, "nothing (removed; still reported)"),
    Legacy("check.min_inlier_ratio", 0.0, "nothing (removed; still reported)"),
    Legacy("check.max_scale_spread", 0.0, "nothing (removed; still reported)"),
    Legacy("refinement.hybrid_min_parallax", 0.0, "nothing (the parallax gate was removed)"),
    Legacy("refinement.early_stop_patience", 0, "nothing (removed)"),
)
BY_NAME: dict[str, Legacy] = {row.name: row for row in LEGACY}


def same_field(row: Legacy) -> bool:
    """A parameter that became the config field of the same name (``sfm.min_points``): as a
    ``section.field`` value it is an experiment's setting, not a legacy name."""
    return row.becomes == f"the field {row.name}"


def resolve(values: Mapping[str, Any], defaults: Mapping[str, Any], *,
            as_node: bool = False) -> tuple[dict[str, Any], list[str]]:
    """``values`` with every legacy name replaced by what it became, and one warning per
    legacy name (a same-named config field only for the node, ``as_node``: there it is a
    parameter that goes away). A value given under its new name wins over a translated one
    unless it is that parameter's default (a node holds every parameter, given or not). Raises
    :class:`InputError` for a removed parameter set to anything but its old default."""
    new = {k: v for k, v in values.items() if k not in BY_NAME}
    warnings, translated = [], {}
    for name, value in values.items():
        row = BY_NAME.get(name)
        if row is None:
            continue
        if same_field(row) and not as_node:
            new[name] = value
            continue
        if row.translate is None:
            if value != row.default:
                raise InputError(f"parameter {name!r} was removed (docs/decisions.md): it "
                                 f"cannot be set to {value!r} any more")
            warnings.append(f"parameter {name!r} was removed; its default is ignored")
            continue
        translated.update(row.translate(value, {**values, **translated}))
        warnings.append(f"parameter {name!r} is deprecated and goes in the next release: use "
                        f"{row.becomes}")
    for key, value in translated.items():
        if key not in new or (key in defaults and new[key] == defaults[key]):
            new[key] = value
    return new, warnings
