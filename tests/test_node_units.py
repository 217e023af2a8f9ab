"""The node's depth as a depth_image_proc-style consumer reads it (REP 118): only metres on
``~/depth/image``, the rest on ``~/depth_relative/image``, the scale's state on the latched
``~/depth_scale`` even for a late subscriber, compressedDepth by image_transport's convention,
and an output's QoS overridden by ROS's ``qos_overrides`` parameters."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from conftest import tiny_model
from helpers import wait_for

rclpy = pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticStatus  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import CompressedImage, Image  # noqa: E402

from msg_adapters import diagnostic_values, image_to_depth, numpy_to_image  # noqa: E402
from msg_adapters.compressed_depth import compressed_depth_to_depth  # noqa: E402
from sfm_ttr_ros.ros import names  # noqa: E402
from sfm_ttr_ros.ros.node import RefinerNode  # noqa: E402
from sfm_ttr_ros.ros.publishers import LATCHED_QOS  # noqa: E402

pytestmark = pytest.mark.ros
W, H = 208, 64
# no window runs: only the live output (the units of a window's outputs: tests/test_outputs.py)
QUIET = {"window_size": 50, "idle_flush_s": 0.0, "fallback_intrinsics": "100 100 0 0",
         "outputs": "depth,depth_refined,compressed_depth,diagnostics",
         "diagnostics_period_s": 0.2}



class Consumer:
    """A refiner with ``params`` and an outside client of its depth topics, spun in a thread."""

    def __init__(self, context, **params):
        overrides = [Parameter(k, value=v) for k, v in {**QUIET, **params}.items()]
        self.refiner = RefinerNode(model=tiny_model(), context=context,
                                   parameter_overrides=overrides)
        self.client = Node("depth_consumer", context=context)
        self.got: dict[str, list] = {}
        qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.BEST_EFFORT)
        for msg_type, topic in ((Image, names.DEPTH_TOPIC), (Image, names.DEPTH_RELATIVE_TOPIC),
                                (CompressedImage, names.compressed_depth_topic(names.DEPTH_TOPIC)),
                                (CompressedImage,
                                 names.compressed_depth_topic(names.DEPTH_RELATIVE_TOPIC))):
            sink = self.got.setdefault(topic, [])
            self.client.create_subscription(msg_type, names.resolve(topic), sink.append, qos)
        self.image = self.client.create_publisher(Image, names.IMAGE_TOPIC, 50)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.refiner)
        self.executor.add_node(self.client)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        wait_for(lambda: self.image.get_subscription_count() >= 1
                 and self.refiner.pubs.by_topic[names.DEPTH_TOPIC].get_subscription_count() >= 1
                 and self.refiner.pubs.by_topic[names.DEPTH_RELATIVE_TOPIC]
                 .get_subscription_count() >= 1, 20, "discovery")

    def send(self, n: int) -> None:
        rng = np.random.default_rng(0)
        for i in range(n):
            msg = numpy_to_image(rng.integers(0, 255, (H, W, 3), dtype=np.uint8), "rgb8")
            msg.header.stamp.sec, msg.header.frame_id = i + 1, "cam"
            self.image.publish(msg)
        depth, relative = self.got[names.DEPTH_TOPIC], self.got[names.DEPTH_RELATIVE_TOPIC]
        wait_for(lambda: len(depth) + len(relative) >= n, 30, f"{n} live depth images")

    def late_scale(self) -> dict[str, str]:
        """What a subscriber that comes now reads on ~/depth_scale (transient local)."""
        got: list[DiagnosticStatus] = []
        late = self.client.create_subscription(DiagnosticStatus,
                                               names.resolve(names.DEPTH_SCALE_TOPIC),
                                               got.append, LATCHED_QOS)
        wait_for(lambda: got, 10, "the latched ~/depth_scale")
        self.client.destroy_subscription(late)
        return {"level": got[-1].level, **diagnostic_values(got[-1])}

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=2.0)
        self.refiner.destroy_node()
        self.client.destroy_node()


@pytest.fixture
def consumer(context, one_thread):
    made: list[Consumer] = []
    yield lambda **params: made.append(Consumer(context, **params)) or made[-1]
    for c in made:
        c.close()


@pytest.mark.slow
def test_depth_not_in_metres_never_reaches_the_metric_topic(consumer):
    c = consumer()  # metric.source none: the network's units
    c.send(4)
    assert c.got[names.DEPTH_TOPIC] == [] and len(c.got[names.DEPTH_RELATIVE_TOPIC]) == 4
    scale = c.late_scale()
    assert (scale["source"], scale["state"], scale["factor"]) == ("none", "not_metric", "nan")
    assert scale["depth_topic"] == names.DEPTH_RELATIVE_TOPIC and scale["level"] == b"\x01"
    packed = c.got[names.compressed_depth_topic(names.DEPTH_RELATIVE_TOPIC)]
    wait_for(lambda: len(packed) == 4, 10, "the compressedDepth copies")
    raw = image_to_depth(c.got[names.DEPTH_RELATIVE_TOPIC][0])
    back = compressed_depth_to_depth(packed[0])
    assert packed[0].header == c.got[names.DEPTH_RELATIVE_TOPIC][0].header
    np.testing.assert_allclose(1 / back, 1 / raw, atol=1 / (100 * 101) * 1.001)
    # a change is published at the next timer tick: relative_depth drop, nothing sent
    results = c.refiner.set_parameters([Parameter("relative_depth", value="drop")])
    assert all(r.successful for r in results), [r.reason for r in results]
    wait_for(lambda: c.late_scale()["depth_topic"] == "dropped", 10, "the new scale state")
    c.image.publish(numpy_to_image(np.zeros((H, W, 3), np.uint8), "rgb8"))
    wait_for(lambda: c.refiner.online.counters_live()["published"] == 5, 10, "the live frame")
    time.sleep(0.3)
    assert c.got[names.DEPTH_TOPIC] == [] and len(c.got[names.DEPTH_RELATIVE_TOPIC]) == 4


@pytest.mark.slow
def test_metres_on_the_metric_topic_and_an_output_qos_overridden(consumer):
    # a fixed factor: metres at once; ~/depth/image best effort by ROS's qos_overrides
    c = consumer(**{"metric.source": "fixed", "metric.factor": 2.0,
                    f"qos_overrides.{names.DEPTH_TOPIC_RESOLVED}.publisher.reliability":
                    "best_effort"})
    assert c.refiner.pubs.by_topic[names.DEPTH_TOPIC].qos_profile.reliability == \
        ReliabilityPolicy.BEST_EFFORT
    assert c.refiner.pubs.by_topic[names.DEPTH_REFINED_TOPIC].qos_profile.reliability == \
        ReliabilityPolicy.RELIABLE
    c.send(3)
    assert len(c.got[names.DEPTH_TOPIC]) == 3 and c.got[names.DEPTH_RELATIVE_TOPIC] == []
    scale = c.late_scale()
    assert (scale["source"], scale["state"], float(scale["factor"])) == ("fixed", "metric", 2.0)
    assert scale["depth_topic"] == names.DEPTH_TOPIC and scale["level"] == b"\x00"


def test_a_remapped_depth_topic_takes_its_compressed_depth_along(context, one_thread):
    """image_transport's naming: the compressedDepth topic hangs under the depth topic as
    resolved and remapped, in the node's namespace."""
    node = RefinerNode(model=tiny_model(), context=context, namespace="cam1",
                       cli_args=["--ros-args", "-r", "~/depth/image:=/front/depth"],
                       parameter_overrides=[Parameter(k, value=v) for k, v in QUIET.items()])
    try:
        topic = node.pubs.by_topic[names.compressed_depth_topic(names.DEPTH_TOPIC)].topic_name
        relative = node.pubs.by_topic[
            names.compressed_depth_topic(names.DEPTH_RELATIVE_TOPIC)].topic_name
    finally:
        node.destroy_node()
    assert topic == "/front/depth/compressedDepth"
    assert relative == "/cam1/refiner/depth_relative/image/compressedDepth"


def test_the_node_says_where_its_depth_goes_in_its_log_and_its_scale_status(context, one_thread,
                                                                            capfd):
    """As a user starts it (no parameter file, in a namespace, rclpy's real logger): the
    start-up line says which topic carries the depth and why (WARN: not metres), the ``scale``
    status on /diagnostics says it too (WARN), and a change of where the depth goes is logged
    again; in metres (a fixed factor) the line is an INFO and the status OK."""
    from sfm_ttr_ros.ros import outputs

    def said(what: str) -> list[str]:
        return [x for x in capfd.readouterr().err.splitlines() if what in x]

    line = ("depth on /cam1/refiner/depth_relative/image, /cam1/refiner/depth_refined_relative/"
            "image (relative: metric.source none; set metric.source to camera_height, odometry "
            "or fixed to get metres on /cam1/refiner/depth/image, "
            "/cam1/refiner/depth_refined/image)")
    node = RefinerNode(model=tiny_model(), context=context, namespace="cam1")
    try:
        (start,) = said(line)
        assert start.startswith("[WARN]")
        scale = {s.task: s for s in node.diagnostics.statuses()}["scale"]
        assert (scale.level, scale.message) == ("warn", line)
        (named,) = outputs.diagnostics_message([scale], 0.0, node.get_name(),
                                               node.get_fully_qualified_name()).status
        assert (named.name, named.hardware_id) == ("refiner: scale", "/cam1/refiner")
        results = node.set_parameters([Parameter("relative_depth", value="drop")])
        assert all(r.successful for r in results), [r.reason for r in results]
        node._on_timer()  # the diagnostics timer's tick: the scale is checked
        node._on_timer()  # no change: said once
        (dropped,) = said("depth not published (relative: metric.source none")
        assert dropped.startswith("[WARN]") and dropped.endswith("; relative_depth drop)")
    finally:
        node.destroy_node()
    node = RefinerNode(model=tiny_model(), context=context, namespace="cam1",
                       parameter_overrides=[Parameter("metric.source", value="fixed")])
    try:
        metres = ("depth in metres on /cam1/refiner/depth/image, /cam1/refiner/depth_refined/"
                  "image (metric.source fixed, metric; 1 m per network unit)")
        (start,) = said(metres)
        assert start.startswith("[INFO]")
        scale = {s.task: s for s in node.diagnostics.statuses()}["scale"]
        assert (scale.level, scale.message) == ("ok", metres)
    finally:
        node.destroy_node()
