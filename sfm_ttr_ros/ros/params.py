"""The refiner node's parameters in ROS terms: one ``ParameterDescriptor`` per row of the schema
(:mod:`sfm_ttr_ros.core.params`, which holds names, defaults, types, ranges and descriptions),
declared on the node, read back, and turned into the core's configs.

Live parameters (not read-only) take effect at the next window: the node builds a new
:class:`~sfm_ttr_ros.core.pipeline.TTRConfig` and
:class:`~sfm_ttr_ros.core.stream.window_runner.StreamSettings` from the current values at the
start of every window (``SfmTTR.set_config``). rclpy itself enforces types, ranges and read-only;
:func:`validate` adds what descriptors cannot say (choices, ``window_stride <= window_size``,
``lr > 0``, both model files or neither, ...). The legacy names of
:mod:`sfm_ttr_ros.core.params.legacy` are declared too, with their old defaults, so that an old
parameter file or ``-p`` still works for one release (with a warning). This is the only module
that imports ``rcl_interfaces``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
)

from sfm_ttr_ros.core import params as schema
from sfm_ttr_ros.core.params import Param
from sfm_ttr_ros.core.params.legacy import BY_NAME, LEGACY
from sfm_ttr_ros.core.pipeline import TTRConfig

__all__ = ["DEFAULTS", "PARAMS", "SPECS", "build_settings", "build_ttr_config",
           "current_values", "declare", "descriptor", "ros_type", "validate"]

PARAMS: tuple[Param, ...] = schema.PARAMS
SPECS: dict[str, Param] = schema.SCHEMA
DEFAULTS: dict[str, Any] = schema.defaults()
_ROS_TYPES = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
              float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING}


def ros_type(param: Param) -> int:
    """The ``ParameterType`` of a schema row (NOT_SET for a dynamically typed one)."""
    if param.dynamic_typing:
        return ParameterType.PARAMETER_NOT_SET
    return _ROS_TYPES[param.type]


def descriptor(param: Param) -> ParameterDescriptor:
    """The full ROS descriptor of a schema row: type, description, range, read-only = not
    live, choices and constraints as ``additional_constraints``."""
    d = ParameterDescriptor(name=param.name, type=ros_type(param),
                            description=param.description, read_only=not param.live,
                            dynamic_typing=param.dynamic_typing)
    text = param.constraints
    if param.choices:
        text = f"one of: {', '.join(map(str, param.choices))}" + (f"; {text}" if text else "")
    d.additional_constraints = text
    if param.range is not None and param.type is int:
        lo, hi = param.range
        d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
    elif param.range is not None and param.type is float:
        lo, hi = param.range
        d.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi),
                                                     step=0.0)]
    return d


def declare(node) -> None:
    """Declare every parameter of the schema on ``node`` (overrides from --params-file / -p
    are applied and checked against type and range by rclpy here), and every legacy name with
    its old default and a description that says what replaces it."""
    node.declare_parameters("", [(p.name, p.default, descriptor(p)) for p in PARAMS])
    node.declare_parameters("", [
        (row.name, row.default, ParameterDescriptor(
            name=row.name, type=_ROS_TYPES[type(row.default)],
            description=f"deprecated, goes in the next release: use {row.becomes}"))
        for row in LEGACY])


def current_values(node) -> dict[str, Any]:
    """The schema's parameters, and the legacy names set to something else than their old
    default (those are translated, with a warning)."""
    values = {name: node.get_parameter(name).value for name in SPECS}
    for row in LEGACY:
        value = node.get_parameter(row.name).value
        if value != row.default:
            values[row.name] = value
    return values


def _ours(values: Mapping[str, Any]) -> dict[str, Any]:
    """The schema's parameters (and legacy names not at their old default) among a node's
    (which also has ``use_sim_time``, ``qos_overrides.*``, ...)."""
    return {k: v for k, v in values.items()
            if k in SPECS or (k in BY_NAME and v != BY_NAME[k].default)}


def validate(values: Mapping[str, Any]) -> str:
    """:func:`sfm_ttr_ros.core.params.validate` of the schema's parameters in ``values``."""
    return schema.validate(_ours(values))


def build_settings(values: Mapping[str, Any]) -> schema.Settings:
    return schema.build(_ours(values), as_node=True)


def build_ttr_config(values: Mapping[str, Any]) -> TTRConfig:
    return build_settings(values).ttr
