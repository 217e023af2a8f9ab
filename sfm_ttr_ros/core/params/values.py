"""Values of the schema's parameters: checked, read from parameter files and ``--set``, and
built into the typed configs (:class:`Settings`).

A *values* mapping holds parameter names, the legacy names of :mod:`.legacy` (translated, with
a warning) and, for experiments, ``section.field`` paths of config fields that no parameter
targets (e.g. ``ttr.predict_batch``).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sfm_ttr_ros.core.alignment.scale import AlignmentConfig
from sfm_ttr_ros.core.checks.measures import CheckConfig
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.metric.metric_config import MetricConfig, check_source_for_output
from sfm_ttr_ros.core.models.registry import ModelConfig
from sfm_ttr_ros.core.params import legacy
from sfm_ttr_ros.core.params.docs import number
from sfm_ttr_ros.core.params.node import NodeSettings
from sfm_ttr_ros.core.params.schema import (
    PARAMS,
    SCHEMA,
    SECTIONS,
    TARGETS,
    config_field,
    settable,
)
from sfm_ttr_ros.core.params.sections import (
    full_node_name,
    is_wildcard_section,
    no_section_message,
    parameter_sections,
    section_matches,
)
from sfm_ttr_ros.core.refinement.refinement_config import RefinementConfig
from sfm_ttr_ros.core.sfm.sfm_config import SfmConfig
from sfm_ttr_ros.core.stream.settings import StreamSettings
from sfm_ttr_ros.core.window_io import TTRConfig

BUILTIN_MODELS = ("default", "monodepth2", "mobilenet", "hf")
_ARTICLES = {bool: "a bool", int: "an integer", float: "a double", str: "a string"}


@dataclass
class Settings:
    """Everything a set of parameter values configures; ``warnings``: the legacy names used."""

    ttr: TTRConfig
    stream: StreamSettings
    model: ModelConfig
    node: NodeSettings
    warnings: list[str] = field(default_factory=list)


def defaults() -> dict[str, Any]:
    """Every parameter at its default (the dataclass fields' defaults)."""
    return {p.name: p.default for p in PARAMS}


def _close(name: str, fields: bool = True) -> str:
    """" (did you mean a, b?)" for the parameters (and settable fields) close to ``name``."""
    paths = (f"{s}.{f.name}" for s, c in SECTIONS.items() for f in dataclasses.fields(c))
    candidates = [*SCHEMA, *(p for p in paths if fields and p not in TARGETS and settable(p))]
    close = difflib.get_close_matches(name, candidates, n=3, cutoff=0.6)
    return f" (did you mean {', '.join(close)}?)" if close else ""


def _unknown(name: str) -> str:
    return f"unknown parameter {name!r}{_close(name)}; `sfm-ttr params` lists them"


def _value_type(name: str) -> type:
    if name in SCHEMA:
        return SCHEMA[name].type
    if name in legacy.BY_NAME:
        return type(legacy.BY_NAME[name].default)
    return type(config_field(name).default)


def check_value(name: str, value: Any) -> str:
    """Why ``value`` is not acceptable for parameter (legacy name, or settable config field)
    ``name``: its type (a double given as an integer is an error, as for rclpy), range and
    choices; "" when it is acceptable."""
    param = SCHEMA.get(name)
    if param is None and name not in legacy.BY_NAME \
            and not (name not in TARGETS and settable(name)):
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
            side = f">= {number(lo)}" if not value >= lo else f"<= {number(hi)}"
            return f"{name} must be {side} (range {number(lo)} … {number(hi)}), got {value!r}"
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
    if kind.lower() == "hf":  # a detected output kind is checked once the model is loaded
        check_source_for_output(str(values["metric.source"]), str(values["output_kind"]))


def build(values: Mapping[str, Any], *, as_node: bool = False) -> Settings:
    """The configs of ``values`` (parameters not given keep their defaults; legacy names are
    translated, :attr:`Settings.warnings` says which; ``section.field`` entries set config
    fields no parameter targets; ``as_node``: the values of the node's declared parameters,
    see :func:`~sfm_ttr_ros.core.params.legacy.resolve`). :class:`InputError` says what is
    wrong."""
    for name, value in values.items():
        reason = check_value(name, value)
        if reason:
            raise InputError(reason)
    given, warnings = legacy.resolve(values, defaults(), as_node=as_node)
    full = {**defaults(), **given}
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
                          metric=MetricConfig(**sections["metric"]),
                          refinement=RefinementConfig(**sections["refinement"]), **ttr_top),
            model=ModelConfig(**sections["model"]),
            node=NodeSettings(**sections["node"]), warnings=warnings)
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


def read_params_file(path: str | Path, node_name: str, *, namespace: str = "",
                     passed_through: Callable[[str], bool] | None = None) -> dict[str, Any]:
    """The ``ros__parameters`` a ROS 2 parameter file gives node ``node_name`` in ``namespace``
    (the sections that match its full name as rcl matches them, applied in the file's order,
    a later one overriding an earlier one key by key: :mod:`.sections`; nested mappings
    flattened with dots), checked as the node checks them: every key a parameter (or a legacy
    name), of its type (a double written as ``1`` is an error, as for rclpy) and within its
    range and choices. The one reader of parameter files (the CLI, the benchmark, the launch).
    A file that gives the node nothing is an :class:`InputError` naming its sections.

    ``passed_through(key)``: keys the caller hands on unchecked (ROS's own parameters, for the
    launch). With it, a file is read as one shared by several nodes: a wildcard section's keys
    that are neither the node's nor passed through are other nodes' and are left out; without
    it every key must be the node's."""
    path = Path(path)
    fqn = full_node_name(node_name, namespace)

    def ours(key: str) -> bool:
        return key in SCHEMA or key in legacy.BY_NAME

    def kept(key: str) -> bool:
        return passed_through is not None and passed_through(key)

    sections = parameter_sections(path)
    values: dict[str, Any] = {}
    for section, params in sections:
        if not section_matches(section, fqn):
            continue
        if passed_through is not None and is_wildcard_section(section):
            params = {k: v for k, v in params.items() if ours(k) or kept(k)}
        values.update(params)
    if not values:
        raise InputError(no_section_message(path, fqn, [s for s, _ in sections]))
    for key, value in values.items():
        if kept(key):
            continue
        if not ours(key):
            raise InputError(f"{path}: {key!r} is not a parameter of the {node_name} node"
                             f"{_close(key, fields=False)} (`sfm-ttr params` lists them)")
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
    parameter, a legacy name, or a ``section.field`` path: one that a parameter targets means
    that parameter (``model.channels_last`` = ``channels_last``), any other plain config field
    is set as it is (``ttr.predict_batch=4``, experiments). Values are typed by the schema;
    later items win."""
    out: dict[str, Any] = {}
    for item in items:
        name, sep, text = str(item).partition("=")
        name, text = name.strip(), text.strip()
        if not sep or not name:
            raise InputError(f"--set {item!r}: expected NAME=VALUE")
        name = TARGETS.get(name, name)
        if name not in SCHEMA and name not in legacy.BY_NAME and not settable(name):
            raise InputError(f"--set {item!r}: {_unknown(name)}")
        param = SCHEMA.get(name)
        value = _typed(_value_type(name), bool(param and param.dynamic_typing), text)
        reason = check_value(name, value)
        if reason:
            raise InputError(f"--set {item!r}: {reason}")
        out[name] = value
    return out
