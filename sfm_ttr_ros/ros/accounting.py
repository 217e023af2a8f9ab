"""The ``refiner`` node's final accounting: every frame received published or counted with a
reason (docs/node.md, "Diagnostics"), as the node stops.

It is written twice: as the ``stopped: ...`` log line (:func:`stopped_line`) for a person, and,
when the node is started with ``--accounting FILE`` (an argument of the executable, before
``--ros-args``), as data: the final /diagnostics key/values in a JSON object
(:func:`write_accounting`), which ``sfm-ttr demo`` reads back (:func:`read_accounting`).
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Sequence
from pathlib import Path

ACCOUNTING_ARG = "--accounting"


def accounting_path(args: Sequence[str]) -> Path | None:
    """The ``--accounting FILE`` among the executable's arguments (``args`` as ``sys.argv``:
    the program first; the ROS arguments, ``--ros-args ... [--]``, and anything else left
    alone); None without it."""
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument(ACCOUNTING_ARG, default=None)
    known, _ = parser.parse_known_args(_non_ros_args(list(args)[1:]))
    return Path(known.accounting) if known.accounting else None


def _non_ros_args(args: list[str]) -> list[str]:
    """``args`` without the ROS arguments: each ``--ros-args`` up to its ``--`` or the end."""
    out, in_ros = [], False
    for arg in args:
        if arg == "--ros-args":
            in_ros = True
        elif in_ros and arg == "--":
            in_ros = False
        elif not in_ros:
            out.append(arg)
    return out


def stopped_line(v: dict) -> str:
    """The shutdown log line of the final values ``v`` (pending frames are not flushed)."""
    return (f"stopped: {v['frames_received']} received, {v['frames_refined']} refined, "
            f"{v['frames_unrefined']} unrefined, {v['frames_dropped']} dropped, "
            f"{v['frames_pending']} pending not published (no flush on shutdown)"
            + live_summary(v))


def live_summary(v: dict) -> str:
    """The live output's accounting for the shutdown line ("" when ~/depth is off)."""
    if "live.received" not in v:
        return ""
    why = ", ".join(f"{k[len('live.skipped.'):]} {n}" for k, n in v.items()
                    if k.startswith("live.skipped.") and n)
    return (f"; live ~/depth: {v['live.received']} received, {v['live.published']} published, "
            f"{v['live.skipped']} skipped" + (f" ({why})" if why else ""))


def write_accounting(path: Path, v: dict) -> None:
    """The final values ``v`` as one strict JSON object at ``path`` (parent folders created; a
    value not yet measured, NaN, is written as null; one JSON has no type for, as its text)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    data = {k: None if isinstance(x, float) and not math.isfinite(x) else x
            for k, x in v.items()}
    path.write_text(json.dumps(data, indent=1, default=str, allow_nan=False) + "\n")


def read_accounting(path: Path) -> dict | None:
    """The values :func:`write_accounting` wrote at ``path``; None when there is no such file
    (the node did not stop cleanly) or it cannot be read."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
