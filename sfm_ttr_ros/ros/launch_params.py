"""What ``launch/refiner.launch.py`` hands the ``refiner`` node, without the ``launch``
packages (docs/node.md "Launch"): the node's parameters read from a ROS 2 parameter file, as
``--ros-args -p NAME:=VALUE`` arguments (no file is written), and the topic remappings of its
launch arguments.

Which keys of a parameter file are the node's: those of the sections that apply to the node's
full name (``/<namespace>/refiner``) as rcl matches them (:mod:`sfm_ttr_ros.core.params.sections`:
``/**``, ``/*``, ``/**/refiner``, ``/<ns>/*``, ``refiner`` = ``/refiner``, ...), a later section
overriding an earlier one key by key, as rcl applies them:

* sections that name the node (no wildcard): every key is checked as the node checks it (the
  one reader of parameter files, :func:`~sfm_ttr_ros.core.params.values.read_params_file`); a
  key that is neither a parameter of the node nor owned by ROS itself (:data:`ROS_OWNED`:
  ``use_sim_time``, ``qos_overrides.*``, ...) stops the launch, with the key named;
* wildcard sections: the node's parameters among them are checked the same way, the keys ROS
  owns pass through, any other key is another node's (a shared file) and is left to it.

A file none of whose sections applies to the node stops the launch, its sections named (rcl
would start the node with every value at its default, silently).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.params import read_params_file, ros_literal
from sfm_ttr_ros.ros import names

#: Parameters every rclpy node declares itself, and the prefix of those its QoS overriding
#: options declare (``qos_overrides.<topic>.<entity>.<policy>``).
ROS_OWNED = frozenset({"use_sim_time", "start_type_description_service"})
ROS_OWNED_PREFIXES = ("qos_overrides.",)

#: launch argument -> the node's topic it remaps (inputs: relative names; outputs: private)
REMAPS: dict[str, str] = {
    "image_topic": names.IMAGE_TOPIC,
    "camera_info_topic": names.CAMERA_INFO_TOPIC,
    "odom_topic": names.ODOMETRY_TOPIC,
    "depth_topic": names.DEPTH_TOPIC,
    "depth_camera_info_topic": names.DEPTH_INFO_TOPIC,
    "depth_colored_topic": names.DEPTH_COLORED_TOPIC,
    "depth_colored_camera_info_topic": names.DEPTH_COLORED_INFO_TOPIC,
    "depth_refined_topic": names.DEPTH_REFINED_TOPIC,
    "depth_refined_camera_info_topic": names.DEPTH_REFINED_INFO_TOPIC,
    "cloud_topic": names.CLOUD_TOPIC,
    "points_topic": names.POINTS_TOPIC,
    "depth_relative_topic": names.DEPTH_RELATIVE_TOPIC,
    "depth_relative_camera_info_topic": names.DEPTH_RELATIVE_INFO_TOPIC,
    "depth_refined_relative_topic": names.DEPTH_REFINED_RELATIVE_TOPIC,
    "depth_refined_relative_camera_info_topic": names.DEPTH_REFINED_RELATIVE_INFO_TOPIC,
    "cloud_relative_topic": names.CLOUD_RELATIVE_TOPIC,
    "points_relative_topic": names.POINTS_RELATIVE_TOPIC,
    "depth_scale_topic": names.DEPTH_SCALE_TOPIC,
    "odom_output_topic": names.ODOM_OUTPUT_TOPIC,
    "odom_relative_topic": names.ODOM_RELATIVE_TOPIC,
}
SIM_TIME_CHOICES = ("", "true", "false")


def ros_owned(key: str) -> bool:
    """True for a parameter ROS itself declares on every node (not the node's schema)."""
    return key in ROS_OWNED or key.startswith(ROS_OWNED_PREFIXES)


def node_parameters(path: str | Path, node_name: str = names.NODE_NAME,
                    namespace: str = "") -> dict[str, Any]:
    """The parameters the file at ``path`` gives node ``node_name`` in ``namespace``, checked
    (see the module's docstring) by the one reader of parameter files,
    :func:`~sfm_ttr_ros.core.params.values.read_params_file`, with ROS's own keys passed
    through; an unknown key of the node's own sections, a wrong type, a value out of range or
    no section for the node raises :class:`InputError` saying which."""
    return read_params_file(path, node_name, namespace=namespace, passed_through=ros_owned)


def parameter_arguments(values: Mapping[str, Any], use_sim_time: str = "") -> list[str]:
    """``-p NAME:=VALUE`` for each of ``values`` (``--ros-args`` arguments: no parameter file
    is written), then ``use_sim_time`` when the launch argument sets it (``true``/``false``;
    empty: as the file says)."""
    flag = str(use_sim_time).strip().lower()
    if flag not in SIM_TIME_CHOICES:
        raise InputError(f"use_sim_time must be true, false or empty, got {use_sim_time!r}")
    args: list[str] = []
    for key, value in values.items():
        args += ["-p", f"{key}:={ros_literal(value)}"]
    if flag:
        args += ["-p", f"use_sim_time:={flag}"]
    return args


def remappings(arguments: Mapping[str, str]) -> list[tuple[str, str]]:
    """``(topic, target)`` for each remap argument of :data:`REMAPS` that is set (an empty
    argument leaves its topic as it is)."""
    return [(topic, str(arguments[arg]).strip()) for arg, topic in REMAPS.items()
            if str(arguments.get(arg, "")).strip()]
