"""Where the benchmark's settings come from: the node's parameter file (``params/kitti.yaml``
by default) read and built through the one parameter schema, exactly as the node builds them."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from sfm_ttr_ros.core import params as schema
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.models.registry import ModelConfig
from sfm_ttr_ros.core.pipeline import TTRConfig
from sfm_ttr_ros.core.stream.window_runner import StreamSettings
from sfm_ttr_ros.ros.names import NODE_NAME
from sfm_ttr_ros.ros.share import find_share_file, share_candidates

PARAMS_FILE = "kitti.yaml"


def default_params_file(name: str = PARAMS_FILE) -> Path:
    """``params/<name>`` (:func:`~sfm_ttr_ros.ros.share.find_share_file`); :class:`InputError`
    when it is nowhere."""
    found = find_share_file("params", name)
    if found is None:
        raise InputError(f"parameter file {name} not found (looked in "
                         f"{', '.join(str(p) for p in share_candidates('params', name))}); "
                         "pass --params-file")
    return found


def read_params_file(path: str | Path, node_name: str = NODE_NAME) -> dict[str, Any]:
    """:func:`sfm_ttr_ros.core.params.read_params_file` for the refiner node: the tools' one
    reader of parameter files (``sfm-ttr run`` / ``benchmark`` / ``speed`` through
    :func:`~sfm_ttr_ros.tools.cli_args.parameter_values`, the demo, the benchmark's defaults)."""
    return schema.read_params_file(path, node_name)


def settings_from_params(values: Mapping[str, Any]
                         ) -> tuple[TTRConfig, StreamSettings, ModelConfig]:
    """(TTRConfig, StreamSettings, ModelConfig) for the parameter ``values`` (missing ones take
    their defaults), exactly as the node builds them."""
    s = schema.build(values)
    return s.ttr, s.stream, s.model
