"""The node's inputs (docs/node.md "QoS"): the image, camera_info and odom subscriptions, as
``subscriptions`` creates them with the schema's default ``qos_reliability`` (reliable), take a
publisher with ROS's default QoS and refuse a BEST_EFFORT one with an incompatible-QoS event;
under ``best_effort`` they take both."""

from __future__ import annotations

import collections
import random
import time

import pytest

from sfm_ttr_ros.core.params import SCHEMA
from sfm_ttr_ros.core.params.node import NodeSettings
from sfm_ttr_ros.ros import names

pytestmark = pytest.mark.ros
rclpy = pytest.importorskip("rclpy")


@pytest.fixture
def ros_context(monkeypatch):
    from rclpy.context import Context

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("ROS_DOMAIN_ID", str(random.SystemRandom().randint(1, 100)))
    ctx = Context()
    rclpy.init(context=ctx)
    yield ctx
    ctx.try_shutdown()


def _spin_until(executor, pred, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return
        executor.spin_once(timeout_sec=0.05)
    raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")


def _inputs(ctx, received, incompatible, reliability: str):
    """The node's three inputs, each callback noting which publisher (its frame_id) it heard."""
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import CameraInfo, Image

    from sfm_ttr_ros.ros import subscriptions

    def note(topic):
        return lambda msg: received[topic].add(msg.header.frame_id)

    node = rclpy.create_node(names.NODE_NAME, context=ctx)
    inputs = [subscriptions.Input(Image, names.IMAGE_TOPIC, note(names.IMAGE_TOPIC)),
              *subscriptions.camera_and_odometry(note(names.CAMERA_INFO_TOPIC),
                                                 note(names.ODOMETRY_TOPIC))]
    subscriptions.subscribe(node, inputs, subscriptions.input_qos(
        NodeSettings(qos_reliability=reliability)), lambda topic, event: incompatible.append(topic))
    return node, {Image: names.IMAGE_TOPIC, CameraInfo: names.CAMERA_INFO_TOPIC,
                  Odometry: names.ODOMETRY_TOPIC}


def _drivers(ctx, types):
    """A RELIABLE and a BEST_EFFORT publisher on each input topic."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    driver = rclpy.create_node("camera_drivers", context=ctx)
    pubs = []
    for policy, label in ((ReliabilityPolicy.RELIABLE, "reliable"),
                          (ReliabilityPolicy.BEST_EFFORT, "best_effort")):
        qos = QoSProfile(depth=10, reliability=policy)
        pubs += [(driver.create_publisher(cls, topic, qos), cls, label)
                 for cls, topic in types.items()]
    return driver, pubs


def _run(ctx, reliability: str, until) -> tuple[dict, list]:
    from rclpy.executors import SingleThreadedExecutor

    received: dict[str, set] = collections.defaultdict(set)
    incompatible: list[str] = []
    node, types = _inputs(ctx, received, incompatible, reliability)
    driver, pubs = _drivers(ctx, types)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    executor.add_node(driver)

    def publish_and_check():
        for pub, cls, label in pubs:
            msg = cls()
            msg.header.frame_id = label
            pub.publish(msg)
        return until(received, incompatible)

    try:
        _spin_until(executor, publish_and_check, 20, f"the inputs under {reliability}")
    finally:
        executor.shutdown()
        node.destroy_node()
        driver.destroy_node()
    return received, incompatible


def test_best_effort_inputs_take_reliable_and_best_effort_publishers(ros_context):
    both = {"reliable", "best_effort"}
    topics = (names.IMAGE_TOPIC, names.CAMERA_INFO_TOPIC, names.ODOMETRY_TOPIC)
    received, incompatible = _run(ros_context, "best_effort",
                                  lambda got, _: all(got[t] == both for t in topics))
    assert {t: received[t] for t in topics} == {t: both for t in topics}
    assert incompatible == []


def test_the_default_reliable_inputs_refuse_a_best_effort_publisher(ros_context):
    assert SCHEMA["qos_reliability"].default == NodeSettings().qos_reliability == "reliable"
    topics = {names.IMAGE_TOPIC, names.CAMERA_INFO_TOPIC, names.ODOMETRY_TOPIC}
    received, incompatible = _run(
        ros_context, NodeSettings().qos_reliability,
        lambda got, bad: set(bad) >= topics and all(got[t] == {"reliable"} for t in topics))
    assert all(received[t] == {"reliable"} for t in topics)  # never the best-effort one
    assert set(incompatible) == topics


def test_an_override_of_one_input_stays_on_that_input(monkeypatch):
    """rclpy writes a topic's qos_overrides into the profile it is given: each input has its
    own copy, so the image's override does not reach camera_info or odom."""
    from rclpy.context import Context
    from rclpy.qos import ReliabilityPolicy
    from sensor_msgs.msg import Image

    from sfm_ttr_ros.ros import subscriptions

    monkeypatch.setenv("ROS_DOMAIN_ID", str(random.SystemRandom().randint(1, 100)))
    ctx = Context()
    rclpy.init(context=ctx, args=["--ros-args", "-p",
                                  "qos_overrides./image.subscription.reliability:=best_effort"])
    try:
        node = rclpy.create_node(names.NODE_NAME, context=ctx)
        inputs = [subscriptions.Input(Image, names.IMAGE_TOPIC, lambda m: None),
                  *subscriptions.camera_and_odometry(lambda m: None, lambda m: None)]
        subscriptions.subscribe(node, inputs, subscriptions.input_qos(NodeSettings()),
                                lambda *a: None)
        got = {s.topic_name: s.qos_profile.reliability for s in node.subscriptions}
        node.destroy_node()
    finally:
        ctx.try_shutdown()
    assert got == {"/image": ReliabilityPolicy.BEST_EFFORT,
                   "/camera_info": ReliabilityPolicy.RELIABLE,
                   "/odom": ReliabilityPolicy.RELIABLE}
