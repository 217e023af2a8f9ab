"""A distorted camera through the node: its CameraInfo (D != 0) read into a rectifier
(ros/camera.py), its frames undistorted once where they get their intrinsics (shared by live
serving and the window), their depth published beside a CameraInfo with D = 0 and the
rectified image's K; an unknown lens model refused, counted and logged once. In-process
rclpy, publishers and subscriptions with ROS's default QoS, in a namespace."""

from __future__ import annotations

import time

import numpy as np
import pytest
from conftest import tiny_model
from distorted_camera import (
    EQUIDISTANT,
    PLUMB_BOB,
    SIZE,
    K,
    directions,
    distorted_pixels,
    dot_centres,
    dots_image,
    pinhole_pixels,
)

rclpy = pytest.importorskip("rclpy")

from builtin_interfaces.msg import Time  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from msg_adapters import camera_info_msg, numpy_to_image  # noqa: E402
from sfm_ttr_ros.core.frames import Frame, Intrinsics  # noqa: E402
from sfm_ttr_ros.ros import names, outputs  # noqa: E402
from sfm_ttr_ros.ros.camera import CameraInfoReader, IntrinsicsResolver  # noqa: E402
from sfm_ttr_ros.ros.node import RefinerNode  # noqa: E402

pytestmark = pytest.mark.ros
K_RECT = np.array([[230.0, 0.0, 160.0], [0.0, 230.0, 119.5], [0.0, 0.0, 1.0]])
RAYS = directions()


def _info(model: str, D, P=None, stamp_ns: int = 0) -> CameraInfo:
    P = np.zeros((3, 4)) if P is None else P
    return camera_info_msg(*SIZE, K, P, D=D, distortion_model=model,
                           header=Header(stamp=Time(sec=stamp_ns // 10**9), frame_id="cam"))


class _Log:
    def __init__(self):
        self.warnings: list[str] = []

    def warning(self, message: str) -> None:
        self.warnings.append(message)


def _max_error(image: np.ndarray, K_new: np.ndarray) -> float:  # noqa: N803
    expected = pinhole_pixels(RAYS, K_new)
    return float(np.max(np.linalg.norm(dot_centres(image, expected) - expected, axis=1)))


@pytest.mark.parametrize("model, D", [("plumb_bob", PLUMB_BOB), ("equidistant", EQUIDISTANT)])
def test_a_frame_gets_rectified_with_the_rectified_intrinsics(model, D):
    refused = []
    reader = CameraInfoReader(_Log(), lambda: refused.append(1))
    source = reader.read(_info(model, D), None)
    resolver = IntrinsicsResolver()
    resolver.add_camera(source, 5)
    raw = Frame(0, dots_image(distorted_pixels(RAYS, model, D)))
    frame = resolver.rectified(raw, 5)
    assert frame.rectified and not raw.rectified and frame is not raw
    assert _max_error(frame.image, source.rectifier.K) < 1.0
    assert not _max_error(raw.image, source.rectifier.K) < 1.0  # the raw dots are off
    assert resolver.rectified(frame, 5) is frame  # never twice
    ready = resolver.add_frame(frame, 5).ready
    assert ready == [(frame, Intrinsics.from_K(source.rectifier.K, *SIZE))]
    # beside its depth (any size): D = 0, plumb_bob, the rectified K scaled to it
    info = outputs.camera_info_message(source, (160, 120), frame.header, frame.rectified)
    assert not np.any(info.d) and info.distortion_model == "plumb_bob"
    np.testing.assert_allclose(np.reshape(info.k, (3, 3))[:2], source.rectifier.K[:2] / 2)
    # a raw frame (served live before its camera was known): the CameraInfo as received
    assert outputs.camera_info_message(source, SIZE, None, False).d.tolist() == list(D)
    assert reader.read(_info(model, D), None).rectifier is source.rectifier  # maps built once
    assert reader.rectifiers.built == 1 and not refused


def test_a_held_frame_is_rectified_when_released():
    reader = CameraInfoReader(_Log(), lambda: None)
    resolver = IntrinsicsResolver()
    raw = Frame(0, dots_image(distorted_pixels(RAYS, "plumb_bob", PLUMB_BOB)))
    assert resolver.rectified(raw, 1) is raw and not resolver.add_frame(raw, 1).ready
    source = reader.read(_info("plumb_bob", PLUMB_BOB, np.hstack([K_RECT, np.zeros((3, 1))])),
                         None)
    [(frame, intr)] = resolver.add_camera(source, 1).ready
    assert frame.rectified and intr == Intrinsics.from_K(K_RECT, *SIZE)
    assert _max_error(frame.image, K_RECT) < 1.0


def test_images_declared_rectified_are_left_alone():
    source = CameraInfoReader(_Log(), lambda: None).read(
        _info("plumb_bob", PLUMB_BOB, np.hstack([K_RECT, np.zeros((3, 1))])), True)
    assert source.rectifier is None and source.intrinsics == Intrinsics.from_K(K_RECT, *SIZE)


def test_an_unknown_model_is_refused_counted_and_logged_once_per_camera_info():
    log, refused = _Log(), []
    reader = CameraInfoReader(log, lambda: refused.append(1))
    for _ in range(3):
        assert reader.read(_info("double_sphere", (0.1, 0.5)), None) is None
    reader.read(_info("double_sphere", (0.2, 0.5)), None)
    assert len(refused) == 4 and len(log.warnings) == 2
    assert "image_rect" in log.warnings[0] and "double_sphere" in log.warnings[0]


def _spin_until(executor, pred, what: str, timeout: float = 30.0, each=None):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if each is not None:
            each()
        executor.spin_once(timeout_sec=0.05)
        if pred():
            return
    raise AssertionError(f"timed out waiting for {what}")


def test_the_node_rectifies_frames_and_publishes_d_zero_and_the_new_k(context):
    node = RefinerNode(model=tiny_model(), context=context, namespace="cam")
    player = rclpy.create_node("camera_driver", namespace="cam", context=context)
    pub_info = player.create_publisher(CameraInfo, "camera_info", 10)  # ROS's default QoS
    pub_image = player.create_publisher(Image, "image", 10)
    infos: list[CameraInfo] = []  # beside the live depth (no metres: ~/depth_relative)
    player.create_subscription(CameraInfo, node.resolve_topic_name(
        names.DEPTH_RELATIVE_INFO_TOPIC), infos.append, 10)
    live, window = [], []
    submit_live, submit = node.online.submit_live, node.stream.submit
    node.online.submit_live = lambda f: (live.append(f), submit_live(f))[1]
    node.stream.submit = lambda f, i: (window.append((f, i)), submit(f, i))[1]
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    executor.add_node(player)
    raw = dots_image(distorted_pixels(RAYS, "plumb_bob", PLUMB_BOB))
    P = np.hstack([K_RECT, np.zeros((3, 1))])
    try:
        _spin_until(executor, lambda: node.intrinsics.latest is not None, "the CameraInfo",
                    each=lambda: pub_info.publish(_info("plumb_bob", PLUMB_BOB, P, 10**9)))
        sent = []

        def send():  # until the output is matched: one image every 0.2 s
            if len(sent) < len(live) + 1 and len(sent) < 5 * time.monotonic() - start:
                sent.append(Header(stamp=Time(sec=2 + len(sent)), frame_id="cam"))
                pub_image.publish(numpy_to_image(raw, "rgb8", sent[-1]))

        start = 5 * time.monotonic()
        _spin_until(executor, lambda: infos and len(window) == len(live), "the depth's "
                    "CameraInfo", each=send)
    finally:
        executor.shutdown()
        player.destroy_node()
        node.destroy_node()
    assert live and all(f.rectified and _max_error(f.image, K_RECT) < 1.0 for f in live)
    assert window == [(f, Intrinsics.from_K(K_RECT, *SIZE)) for f in live]  # one remap each
    for info in infos:
        assert info.distortion_model == "plumb_bob" and not np.any(info.d)
        scale = np.array([[info.width / SIZE[0]], [info.height / SIZE[1]]])
        np.testing.assert_allclose(np.reshape(info.k, (3, 3))[:2], K_RECT[:2] * scale)
    assert node.cameras.rectifiers.built == 1 and node.diagnostics.rejected_camera_info == 0


def test_the_node_counts_and_logs_an_unknown_model_once(context, capfd):
    node = RefinerNode(model=tiny_model(), context=context, namespace="cam")
    player = rclpy.create_node("camera_driver", namespace="cam", context=context)
    pub_info = player.create_publisher(CameraInfo, "camera_info", 10)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    executor.add_node(player)
    try:
        _spin_until(executor, lambda: node.diagnostics.rejected_camera_info >= 3,
                    "3 refused CameraInfos",
                    each=lambda: pub_info.publish(_info("double_sphere", (0.1, 0.5))))
    finally:
        executor.shutdown()
        player.destroy_node()
        node.destroy_node()
    assert node.intrinsics.latest is None
    assert capfd.readouterr().err.count("image_rect") == 1
