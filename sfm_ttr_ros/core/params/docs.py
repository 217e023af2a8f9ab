"""The parameter reference: ``sfm-ttr params`` prints it, docs/parameters.md holds it."""

from __future__ import annotations

from typing import Any

from sfm_ttr_ros.core.params.schema import PARAMS, Param


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


def number(v: int | float) -> str:
    """A range bound, short: 0, 3600, 0.05, 1e6, 2147483647."""
    text = f"{v:g}"
    if isinstance(v, int) and float(text) != v:
        return str(v)
    return text.replace("e+0", "e").replace("e+", "e")


def _limits(p: Param) -> str:
    parts = []
    if p.range is not None and not p.choices:
        parts.append(f"{number(p.range[0])} … {number(p.range[1])}")
    if p.choices:
        parts.append(", ".join(f"`{c}`" for c in p.choices))
    if p.constraints:
        parts.append(p.constraints.replace("<=", "≤"))
    return "; ".join(parts) or "—"


def markdown_table() -> str:
    """The parameter table (name, type, default, range / choices, live or start-up,
    description) as Markdown."""
    lines = ["| parameter | type | default | range / values | set | description |",
             "| --- | --- | --- | --- | --- | --- |"]
    for p in PARAMS:
        lines.append(f"| `{p.name}` | {p.type_name} | `{ros_literal(p.default)}` | {_limits(p)} | "
                     f"{'live' if p.live else 'start-up'} | {p.description} |")
    return "\n".join(lines) + "\n"
