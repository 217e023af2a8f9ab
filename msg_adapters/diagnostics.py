"""diagnostic_msgs/DiagnosticArray from plain Python values (for /diagnostics)."""

from __future__ import annotations

import math
import numbers

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from sfm_ttr_ros.core.errors import InputError

LEVELS = {
    "ok": DiagnosticStatus.OK,
    "warn": DiagnosticStatus.WARN,
    "error": DiagnosticStatus.ERROR,
    "stale": DiagnosticStatus.STALE,
}


def _stamp(stamp) -> Time:
    if stamp is None:
        return Time()
    if isinstance(stamp, Time):
        return stamp
    if hasattr(stamp, "to_msg"):  # rclpy.time.Time
        return stamp.to_msg()
    if isinstance(stamp, numbers.Real) and math.isfinite(float(stamp)) and stamp >= 0:
        ns = round(float(stamp) * 1e9)
        return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
    raise InputError(
        f"stamp must be a builtin_interfaces Time, an rclpy Time or seconds >= 0, got {stamp!r}"
    )


def format_value(value: object) -> str:
    """A compact string for a KeyValue: floats with 6 significant digits (``0.0563``,
    ``1.23e+04``), bools ``true``/``false``, None ``""``, everything else ``str()``."""
    if value is None:
        return ""
    if isinstance(value, bool | np.bool_):
        return "true" if value else "false"
    if isinstance(value, numbers.Integral):
        return str(int(value))
    if isinstance(value, numbers.Real):
        return f"{float(value):.6g}"
    return str(value)


def make_diagnostic_status(name: str, hardware_id: str, level: str, message: str,
                           values: dict[str, object] | None = None) -> DiagnosticStatus:
    """A DiagnosticStatus. ``level``: ``'ok'``, ``'warn'``, ``'error'`` or ``'stale'``
    (case-insensitive). ``values`` become KeyValue pairs (see :func:`format_value`), in the
    dict's order."""
    key = str(level).lower()
    if key not in LEVELS:
        raise InputError(f"diagnostic level must be one of {sorted(LEVELS)}, got {level!r}")
    status = DiagnosticStatus(
        level=LEVELS[key], name=str(name), message=str(message), hardware_id=str(hardware_id)
    )
    status.values = [KeyValue(key=str(k), value=format_value(v)) for k, v in (values or {}).items()]
    return status


def diagnostic_array(stamp, statuses: list[DiagnosticStatus]) -> DiagnosticArray:
    """A DiagnosticArray of ``statuses``; ``stamp``: builtin_interfaces Time, rclpy Time,
    seconds (float) or None (zero)."""
    arr = DiagnosticArray()
    arr.header.stamp = _stamp(stamp)
    arr.status = list(statuses)
    return arr


def make_diagnostic_array(
    stamp,
    name: str,
    hardware_id: str,
    level: str,
    message: str,
    values: dict[str, object] | None = None,
) -> DiagnosticArray:
    """A DiagnosticArray holding one DiagnosticStatus (:func:`make_diagnostic_status`),
    stamped as :func:`diagnostic_array`."""
    return diagnostic_array(stamp, [make_diagnostic_status(name, hardware_id, level, message,
                                                           values)])


def diagnostic_values(array_msg: DiagnosticArray | DiagnosticStatus, name: str | None = None,
                      hardware_id: str | None = None):
    """The KeyValues of a DiagnosticArray (all statuses merged, later ones winning; only the
    status called ``name`` and / or those of ``hardware_id``) or of a single DiagnosticStatus,
    as ``dict[str, str]``."""
    if isinstance(array_msg, DiagnosticStatus):
        statuses = [array_msg]
    else:
        statuses = list(array_msg.status)
    if name is not None:
        statuses = [s for s in statuses if s.name == name]
        if not statuses:
            raise KeyError(f"no diagnostic status named {name!r}")
    if hardware_id is not None:
        statuses = [s for s in statuses if s.hardware_id == hardware_id]
        if not statuses:
            raise KeyError(f"no diagnostic status of hardware_id {hardware_id!r}")
    out: dict[str, str] = {}
    for s in statuses:
        for kv in s.values:
            out[kv.key] = kv.value
    return out
