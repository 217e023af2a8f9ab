"""A plain camera as a new user brings it: the node started with no parameter file (every value
at its default), an uncalibrated driver (a CameraInfo with K all zero), image and CameraInfo
publishers at ROS's default QoS. The node says where its depth goes, refines within its second
window and serves the refined weights live on ``~/depth_relative/image``; with a metric source
the same depth comes in metres on ``~/depth/image``."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from conftest import tiny_model
from helpers import stop_spun, wait_for

rclpy = pytest.importorskip("rclpy")

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402

from msg_adapters import image_to_depth, intrinsics_to_camera_info, numpy_to_image  # noqa: E402
from sfm_ttr_ros.ros import names  # noqa: E402
from sfm_ttr_ros.ros.node import RefinerNode  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]
WIDTH, HEIGHT, FRAMES, RATE_HZ = 320, 96, 40, 5.0



@pytest.fixture(scope="module")
def drive():
    synthetic = pytest.importorskip("sfm_ttr_ros.data.synthetic")
    return synthetic.make_sequence(seed=0, domain="A", num_frames=FRAMES, width=WIDTH,
                                   height=HEIGHT)


class PlainCamera:
    """The node with ``ros_args`` only (no parameter file), a camera driver publishing at ROS's
    default QoS (depth 10, reliable) and a client of the depth topics, spun in a thread."""

    def __init__(self, context, ros_args: list[str]):
        self.refiner = RefinerNode(model=tiny_model(), context=context,
                                   cli_args=["--ros-args", *ros_args] if ros_args else None)
        self.driver = Node("camera_driver", context=context)
        self.image = self.driver.create_publisher(Image, names.IMAGE_TOPIC, 10)
        self.info = self.driver.create_publisher(CameraInfo, names.CAMERA_INFO_TOPIC, 10)
        self.got: dict[str, list[Image]] = {}
        for topic in (names.DEPTH_TOPIC, names.DEPTH_RELATIVE_TOPIC):
            sink = self.got.setdefault(topic, [])
            self.driver.create_subscription(Image, names.resolve(topic), sink.append, 100)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.refiner)
        self.executor.add_node(self.driver)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        wait_for(lambda: self.image.get_subscription_count() >= 1
                 and self.info.get_subscription_count() >= 1, 20, "discovery")

    def send(self, rgb: np.ndarray, t: float, intrinsics) -> None:
        info = intrinsics_to_camera_info(intrinsics)
        info.k, info.p = [0.0] * 9, [0.0] * 12  # an uncalibrated driver's CameraInfo
        msg = numpy_to_image(np.ascontiguousarray(rgb), "rgb8")
        for m in (info, msg):
            m.header.stamp.sec, m.header.stamp.nanosec = int(t), int(round((t % 1) * 1e9))
            m.header.frame_id = "camera"
        self.info.publish(info)
        self.image.publish(msg)

    def drive_through(self, drive) -> None:
        for i, rgb in enumerate(drive.images):
            self.send(rgb, 1.0 + i / RATE_HZ, drive.intrinsics)
            time.sleep(1.0 / RATE_HZ)

    def close(self) -> None:
        stop_spun(self.refiner, self.executor, self.thread, self.driver)


@pytest.fixture
def plain_camera(context):
    made: list[PlainCamera] = []
    yield lambda *args: made.append(PlainCamera(context, list(args))) or made[-1]
    for c in made:
        c.close()


def _refined_within_two_windows(c: PlainCamera) -> None:
    """A window refines, the first or the second, and its weights are the live ones."""
    wait_for(lambda: any(w.refined for w in c.refiner.stream.windows), 240,
             "a refined window")
    windows = list(c.refiner.stream.windows)
    assert any(w.refined for w in windows[:2]), [w.reason for w in windows]
    wait_for(lambda: c.refiner.online.serving.generation >= 1, 30, "the refined weights served")


def test_no_parameter_file_and_a_zero_k_refine_on_the_relative_topic(plain_camera, drive,
                                                                     capfd):
    c = plain_camera()
    c.drive_through(drive)
    _refined_within_two_windows(c)
    values = c.refiner.diagnostics_values()
    assert values["intrinsics.source"] in ("assumed", "refining", "settled")
    # the same image before and after: served by the start-up weights, then the refined ones
    relative = c.got[names.DEPTH_RELATIVE_TOPIC]
    first = next(m for m in relative if m.header.stamp.sec == 1 and m.header.stamp.nanosec == 0)
    c.send(drive.images[0], 100.0, drive.intrinsics)
    wait_for(lambda: any(m.header.stamp.sec == 100 for m in relative), 20, "the image again")
    again = next(m for m in relative if m.header.stamp.sec == 100)
    assert not np.allclose(image_to_depth(first), image_to_depth(again), rtol=1e-4)
    assert c.got[names.DEPTH_TOPIC] == []  # not in metres: never on the metric topic
    err = capfd.readouterr().err
    assert f"depth on {names.resolve(names.DEPTH_RELATIVE_TOPIC)}" in err, err[-3000:]


def test_a_metric_source_puts_the_same_camera_in_metres(plain_camera, drive, capfd):
    c = plain_camera("-p", "metric.source:=fixed", "-p", "metric.factor:=2.0")
    c.drive_through(drive)
    _refined_within_two_windows(c)
    wait_for(lambda: len(c.got[names.DEPTH_TOPIC]) >= FRAMES // 2, 30, "metres on ~/depth")
    assert c.got[names.DEPTH_RELATIVE_TOPIC] == []
    err = capfd.readouterr().err
    assert f"depth in metres on {names.resolve(names.DEPTH_TOPIC)}" in err, err[-3000:]
