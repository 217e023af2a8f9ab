"""Start the ``refiner`` node with a parameter file and its input topics remapped.

    ros2 launch sfm_ttr_ros refiner.launch.py [params_file:=FILE] [image_topic:=TOPIC] \\
        [camera_info_topic:=TOPIC] [namespace:=NS]

* ``params_file``: a ROS 2 parameter file (default: the installed ``params/kitti.yaml``);
* ``image_topic`` / ``camera_info_topic``: what the node's ``image`` and ``camera_info``
  subscriptions are remapped to (default: not remapped);
* ``namespace``: the node's namespace (default: none); the outputs are then
  ``/<namespace>/refiner/depth/image`` + ``.../depth/camera_info``, ``.../depth_refined/...``,
  ``.../depth_colored/...``, ``.../cloud``, ``.../points``.

The file's section for the node (``refiner:``, ``/refiner:``, ``/<ns>/refiner:`` and ``/**:``)
is read and checked here (an unknown name, a wrong type or an out-of-range value stops the
launch with the reason) and handed to the node as a file keyed ``/**``: a section keyed
``refiner:`` alone would be ignored by a node in a namespace (``/<ns>/refiner``).

The names come from :mod:`sfm_ttr_ros.ros.names`; ``launch`` / ``launch_ros`` are imported only
when the launch description is generated, so the helpers here can be tested without them.
"""

from __future__ import annotations

import os
import tempfile

from sfm_ttr_ros.ros import names

EXECUTABLE = "refiner"  # console script of setup.py
ARGUMENTS = {
    "params_file": "ROS 2 parameter file of the node (default: the installed params/kitti.yaml)",
    "image_topic": "topic the node's `image` subscription is remapped to",
    "camera_info_topic": "topic the node's `camera_info` subscription is remapped to",
    "namespace": "namespace of the node (empty: none)",
}


def default_params_file() -> str:
    """The installed ``share/sfm_ttr_ros/params/kitti.yaml``."""
    from ament_index_python.packages import get_package_share_directory

    return os.path.join(get_package_share_directory(names.PACKAGE), "params", "kitti.yaml")


def node_params_file(params_file: str, node_name: str = names.NODE_NAME) -> str:
    """The node's parameters of ``params_file``, checked, written to a new file keyed ``/**``
    (so they apply in any namespace); returns its path."""
    import yaml

    from sfm_ttr_ros.core.params import read_params_file

    values = read_params_file(params_file, node_name)
    with tempfile.NamedTemporaryFile("w", prefix=f"{node_name}_params_", suffix=".yaml",
                                     delete=False) as f:
        yaml.safe_dump({"/**": {"ros__parameters": values}}, f, sort_keys=False)
    return f.name


def generate_launch_description():
    from launch import LaunchDescription  # noqa: I001 (the ROS package, not ./launch)
    from launch.actions import DeclareLaunchArgument, OpaqueFunction
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node

    def refiner(context):
        params_file = LaunchConfiguration("params_file").perform(context)
        return [Node(
            package=names.PACKAGE,
            executable=EXECUTABLE,
            name=names.NODE_NAME,
            namespace=LaunchConfiguration("namespace"),
            parameters=[node_params_file(params_file)],
            remappings=[(names.IMAGE_TOPIC, LaunchConfiguration("image_topic")),
                        (names.CAMERA_INFO_TOPIC, LaunchConfiguration("camera_info_topic"))],
            output="screen",
            emulate_tty=True,
        )]

    defaults = {"params_file": default_params_file(), "image_topic": names.IMAGE_TOPIC,
                "camera_info_topic": names.CAMERA_INFO_TOPIC, "namespace": ""}
    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=defaults[name], description=text)
         for name, text in ARGUMENTS.items()]
        + [OpaqueFunction(function=refiner)])
