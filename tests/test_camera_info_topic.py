"""Where the node takes its CameraInfo from (ros/subscriptions.py, camera_info_topic): beside
the image, as image_transport's camera subscriber does, unless ``camera_info`` itself is
remapped; and an uncalibrated camera's CameraInfo (K all zero) giving assumed intrinsics, with
``intrinsics.source`` on /diagnostics. In-process rclpy, publishers with ROS's default QoS."""

from __future__ import annotations

import time

import numpy as np
import pytest
from conftest import tiny_model

rclpy = pytest.importorskip("rclpy")

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from sensor_msgs.msg import CameraInfo  # noqa: E402

from msg_adapters import intrinsics_to_camera_info  # noqa: E402
from sfm_ttr_ros.core.frames import Intrinsics  # noqa: E402
from sfm_ttr_ros.ros.node import RefinerNode  # noqa: E402

pytestmark = pytest.mark.ros
INTR = Intrinsics(200.0, 200.0, 159.5, 47.5, 320, 96)


def _received_on(context, topic: str, remaps: list[str], namespace: str = "",
                 message: CameraInfo | None = None):
    """A refiner started with ``remaps`` (``--ros-args -r`` rules) in ``namespace``, a
    CameraInfo published on ``topic``: the node (its resolver knows the intrinsics, or the
    camera is uncalibrated) once it took it, or fails after 20 s."""
    args = ["--ros-args"] + [a for r in remaps for a in ("-r", r)]
    node = RefinerNode(model=tiny_model(), context=context, cli_args=args, namespace=namespace)
    player = rclpy.create_node("camera_driver", context=context)
    pub = player.create_publisher(CameraInfo, topic, 10)  # ROS's default QoS
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    executor.add_node(player)
    msg = message or intrinsics_to_camera_info(INTR)
    try:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            pub.publish(msg)
            executor.spin_once(timeout_sec=0.1)
            if node.intrinsics.latest is not None or node.intrinsics.kind("assumed") != "none":
                return node
        raise AssertionError(f"no CameraInfo taken from {topic} (node listens on "
                             f"{node.camera_info_topic})")
    finally:
        executor.shutdown()
        player.destroy_node()
        node.destroy_node()


def test_camera_info_comes_from_beside_a_remapped_image(context):
    node = _received_on(context, "/cam/camera_info", ["image:=/cam/image_raw"])
    assert node.camera_info_topic == "/cam/camera_info" and node.intrinsics.latest == INTR


def test_a_remap_of_camera_info_itself_wins(context):
    node = _received_on(context, "/calib/info", ["image:=/cam/image_raw",
                                                 "camera_info:=/calib/info"])
    assert node.camera_info_topic == "/calib/info"


def test_in_a_namespace_without_remaps_camera_info_is_the_namespace_s(context):
    node = _received_on(context, "/cam1/camera_info", [], namespace="cam1")
    assert node.camera_info_topic == "/cam1/camera_info"


def test_an_uncalibrated_camera_gives_assumed_intrinsics(context):
    zero_k = intrinsics_to_camera_info(INTR)
    zero_k.k, zero_k.p = [0.0] * 9, [0.0] * 12  # an uncalibrated driver's CameraInfo
    node = _received_on(context, "/camera_info", [], message=zero_k)
    assert node.diagnostics_values()["intrinsics.source"] == "assumed"
    assert node.diagnostics.rejected_camera_info == 0
    source = node.intrinsics.camera_for((320, 96), None)
    assert source.assumed and source.intrinsics == Intrinsics.from_fov(320, 96, 65.0)
    np.testing.assert_allclose(source.intrinsics.fx, 160 / np.tan(np.radians(32.5)))
