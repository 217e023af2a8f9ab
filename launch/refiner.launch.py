"""Start the ``refiner`` node with a parameter file, a namespace, sim time and its topics
remapped (docs/node.md "Launch").

    ros2 launch sfm_ttr_ros refiner.launch.py [params_file:=FILE] [namespace:=NS] \\
        [use_sim_time:=true|false] [image_topic:=TOPIC] [camera_info_topic:=TOPIC] \\
        [odom_topic:=TOPIC] [depth_topic:=TOPIC] ... (one ``<output>_topic`` per output)

* ``params_file``: a ROS 2 parameter file (default: the installed generic
  ``params/refiner.yaml``, every parameter at its default; ``params/kitti.yaml`` is KITTI's
  camera and must be asked for). Its sections apply as rcl applies them to the node's full
  name ``/<namespace>/refiner`` (``/**``, ``/<namespace>/refiner``, ``/**/refiner``, ...; later
  sections override earlier ones). A shared file with wildcard sections for several nodes,
  and the keys ROS owns (``use_sim_time``, ``qos_overrides.*``), are accepted; an unknown key
  in the node's own section, or no section for the node, stops the launch with the key or the
  sections named (:func:`sfm_ttr_ros.ros.launch_params.node_parameters`);
* ``namespace``: the node's namespace (default: none): ``/<namespace>/refiner``, its outputs
  ``/<namespace>/refiner/depth/image``, ..., its inputs ``/<namespace>/image``, ...;
* ``use_sim_time``: ``true`` or ``false`` override the file; empty (default): as the file says;
* one remap argument per input and output topic
  (:data:`sfm_ttr_ros.ros.launch_params.REMAPS`); empty (default): not remapped.

The node's parameters go on its command line (``--ros-args -p NAME:=VALUE``), so they apply in
any namespace and no parameter file is written. ``launch`` / ``launch_ros`` are imported only
when the launch description is generated, so the helpers can be tested without them.
"""

from __future__ import annotations

import os

from sfm_ttr_ros.ros import launch_params, names

EXECUTABLE = "refiner"  # console script of setup.py
ARGUMENTS = {
    "params_file": "ROS 2 parameter file of the node (default: the installed params/refiner.yaml)",
    "namespace": "namespace of the node (empty: none)",
    "use_sim_time": "true: the node follows /clock (bag replay), false: wall time, empty: as "
                    "the parameter file says",
    **{arg: f"topic the node's `{topic}` is remapped to (empty: not remapped)"
       for arg, topic in launch_params.REMAPS.items()},
}


def default_params_file() -> str:
    """The installed ``share/sfm_ttr_ros/params/refiner.yaml``."""
    from ament_index_python.packages import get_package_share_directory

    return os.path.join(get_package_share_directory(names.PACKAGE), "params", "refiner.yaml")


def defaults() -> dict[str, str]:
    """Each launch argument's default value."""
    return {name: "" for name in ARGUMENTS} | {"params_file": default_params_file()}


def generate_launch_description():
    from launch import LaunchDescription  # noqa: I001 (the ROS package, not ./launch)
    from launch.actions import DeclareLaunchArgument, OpaqueFunction
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node

    def refiner(context):
        given = {name: LaunchConfiguration(name).perform(context) for name in ARGUMENTS}
        values = launch_params.node_parameters(given["params_file"],
                                               namespace=given["namespace"])
        return [Node(
            package=names.PACKAGE,
            executable=EXECUTABLE,
            name=names.NODE_NAME,
            namespace=given["namespace"],
            remappings=launch_params.remappings(given),
            ros_arguments=launch_params.parameter_arguments(values, given["use_sim_time"]),
            output="screen",
            emulate_tty=True,
        )]

    default = defaults()
    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=default[name], description=text)
         for name, text in ARGUMENTS.items()]
        + [OpaqueFunction(function=refiner)])
