"""The node as a ROS user plugs a camera in, with its DEFAULT settings: a frame held for
intrinsics that never come is published unrefined after the idle period, never kept; a
best-effort (sensor-data) driver refused by the reliable default input gets an ERROR, through
rclpy's real logger, naming the fix; real-size frames from a publisher with ROS's default QoS
all reach the node (sfm_ttr_ros/tools/transport_check.py) at 10 and 20 Hz."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import tiny_model
from helpers import stop_spun, wait_for

rclpy = pytest.importorskip("rclpy")

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from msg_adapters import numpy_to_image  # noqa: E402
from sfm_ttr_ros.ros import names  # noqa: E402
from sfm_ttr_ros.ros.node import RefinerNode  # noqa: E402

pytestmark = pytest.mark.ros
REPO = Path(__file__).resolve().parents[1]



class Spun:
    """A refiner (the tiny network; ``params`` over the defaults) and a camera driver node
    whose image publisher has ``qos`` (ROS's default: depth 10), spun in a thread."""

    def __init__(self, context, qos=10, **params):
        self.refiner = RefinerNode(model=tiny_model(), context=context, parameter_overrides=[
            Parameter(k, value=v) for k, v in params.items()])
        self.driver = rclpy.create_node("camera_driver", context=context)
        self.pub = self.driver.create_publisher(Image, names.IMAGE_TOPIC, qos)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.refiner)
        self.executor.add_node(self.driver)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def send(self, t: float) -> None:
        rgb = np.random.default_rng(int(t)).integers(0, 255, (48, 160, 3), np.uint8)
        sec, frac = divmod(t, 1.0)
        header = Header(frame_id="camera")
        header.stamp.sec, header.stamp.nanosec = int(sec), int(frac * 1e9)
        self.pub.publish(numpy_to_image(rgb, "rgb8", header))

    def close(self) -> None:
        stop_spun(self.refiner, self.executor, self.thread, self.driver)


def test_a_frame_held_for_intrinsics_that_never_come_is_published_unrefined(context):
    g = Spun(context, idle_flush_s=0.5, diagnostics_period_s=0.2)
    try:
        wait_for(lambda: g.pub.get_subscription_count() >= 1, 20, "discovery")
        g.send(1.0)
        g.send(2.0)
        wait_for(lambda: g.refiner.intrinsics.held == 2, 10, "2 frames held")
        c = g.refiner.stream.counters
        wait_for(lambda: c()["unrefined_by_reason"].get("no_intrinsics") == 2, 10,
                 "the held frames published unrefined after the idle period")
        wait_for(lambda: c()["pending"] == 0, 10, "nothing pending")
        v = g.refiner.diagnostics_values()
        assert v["frames_held_no_intrinsics"] == 0 and v["frames_pending"] == 0
        assert v["frames_received"] == 2 == v["frames_unrefined"]
        assert v["faults"] == 0
    finally:
        g.close()


def test_a_best_effort_driver_is_refused_with_an_error_naming_the_fix(context, capfd):
    sensor_data = QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT)
    g = Spun(context, qos=sensor_data)
    try:
        wait_for(lambda: g.refiner.diagnostics_values()["qos_incompatible"] >= 1, 20,
                 "the incompatible-QoS event")
        g.send(1.0)
        time.sleep(0.5)
        assert g.refiner.diagnostics_values()["frames_received"] == 0  # nothing gets through
    finally:
        g.close()
    err = capfd.readouterr().err
    lines = [ln for ln in err.splitlines() if "incompatible QoS on input /image" in ln]
    assert lines and lines[0].startswith("[ERROR]"), err[-2000:]
    assert "qos_overrides./image.subscription.reliability:=best_effort" in lines[0]
    assert "qos_reliability:=best_effort" in lines[0]


@pytest.mark.slow
def test_real_size_frames_from_a_default_qos_publisher_all_arrive(tmp_path):
    """30 1242x375 rgb8 frames at 10 and at 20 Hz from ``create_publisher(Image, topic, 10)``
    into the node with its defaults: every one received (a best-effort input got 4 and 3)."""
    report = tmp_path / "transport.json"
    out = subprocess.run(
        [sys.executable, "-m", "sfm_ttr_ros.tools.transport_check", "--frames", "30",
         "--rate", "10", "--rate", "20", "--json", str(report), "--log-dir", str(tmp_path)],
        capture_output=True, text=True, timeout=300, cwd=REPO)
    assert report.is_file(), out.stdout[-2000:] + out.stderr[-2000:]
    runs = json.loads(report.read_text())
    assert [(r["rate_hz"], r["received"], r["published"]) for r in runs] == [
        (10.0, 30, 30), (20.0, 30, 30)], out.stdout
    assert all(r["exit_code"] == 0 for r in runs)
