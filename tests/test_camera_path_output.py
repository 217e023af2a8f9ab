"""``~/odom``: the stream's camera path published by the refiner node in a real ROS 2 graph
(in-process, like tests/test_node.py), its covariance, its frames, its units' topic, and TF
refused clearly where tf2_msgs is missing."""

from __future__ import annotations

import importlib.util
import time

import numpy as np
import pytest
from conftest import tiny_model

rclpy = pytest.importorskip("rclpy")

from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from test_node import FRAME_ID, Graph, sequence, wait_for  # noqa: E402, F401

from msg_adapters.odometry import odometry_msg, odometry_to_pose  # noqa: E402
from sfm_ttr_ros.core.errors import InputError  # noqa: E402
from sfm_ttr_ros.ros import names  # noqa: E402
from sfm_ttr_ros.ros.node import RefinerNode  # noqa: E402

pytestmark = pytest.mark.ros


@pytest.fixture
def graph(context, sequence):  # noqa: F811
    g = Graph(context, window_size=6, window_stride=3, outputs="depth_refined,odom",
              **{"metric.source": "camera_height",
                 "metric.camera_height": float(sequence.params.camera_height)})
    yield g
    g.close()


@pytest.mark.slow
def test_the_node_publishes_the_cameras_path_on_odom_with_covariance(graph, sequence):  # noqa: F811
    by_units: dict[str, list[Odometry]] = {"m": [], "sfm": []}
    for units, topic in (("m", names.ODOM_OUTPUT_TOPIC_RESOLVED),
                         ("sfm", names.ODOM_RELATIVE_TOPIC_RESOLVED)):
        graph.node.create_subscription(Odometry, topic, by_units[units].append, 100)
    output = graph.refiner.camera_path
    wait_for(lambda: all(p.get_subscription_count() > 0
                         for p in output.publishers.values()), 10, "discovery")
    sent = []
    for rgb, t in zip(sequence.images, sequence.stamps, strict=True):
        graph.send_info(sequence.intrinsics, t)
        sent.append(graph.send_image(rgb, t).header.stamp)
        time.sleep(0.03)
    wait_for(lambda: len(graph.depths) == len(sent), 120, "every depth image")
    path = graph.refiner.stream.path

    def every_window_on_odom() -> bool:  # a window's odom goes out after its depth images
        windows = list(graph.refiner.stream.windows)
        posed = sum(1 for w in windows if w.result.sfm is not None and w.result.sfm.frames)
        return (len(windows) == 3 and path.summary()["windows"] == posed > 0
                and output.published == path.summary()["poses"]
                == sum(map(len, by_units.values())))

    wait_for(every_window_on_odom, 20, "every window's path on ~/odom")
    # the poses the windows reported, each on the topic of its units: metres on ~/odom, SfM
    # units on ~/odom_relative (the depth's units, window by window)
    reported = [p for w in graph.refiner.stream.windows for p in w.path_poses]
    assert [len(by_units[u]) for u in ("m", "sfm")] == [
        sum(p.units == u for p in reported) for u in ("m", "sfm")]
    odoms = by_units["sfm"] + by_units["m"]  # a path turns metric, never back
    assert len(odoms) >= graph.refiner.stream.windows[0].registered >= 2
    stamps = [(m.header.stamp.sec, m.header.stamp.nanosec) for m in odoms]
    assert stamps == sorted(set(stamps))  # forward in time, each frame once
    assert set(stamps) <= {(s.sec, s.nanosec) for s in sent}
    for msg, pose in zip(odoms, reported, strict=True):
        assert (msg.header.frame_id, msg.child_frame_id) == ("odom", FRAME_ID)
        assert msg.header.stamp == pose.frame.header.stamp
        _, T, cov = odometry_to_pose(msg)
        np.testing.assert_allclose(T, pose.pose.odom_from_camera, atol=1e-9)
        np.testing.assert_allclose(cov, pose.pose.covariance())
        assert (np.diag(cov) > 0).all() and np.isfinite(cov).all()
    # odom is the first camera's body frame (REP 103): it starts at the origin, the camera's
    # optical axis along odom's x
    _, first, _ = odometry_to_pose(odoms[0])
    np.testing.assert_allclose(first[:3, 3], 0.0, atol=1e-9)
    np.testing.assert_allclose(first[:3, 2], [1.0, 0.0, 0.0], atol=1e-9)
    assert np.linalg.norm(odometry_to_pose(odoms[-1])[1][:3, 3]) > 0


def test_odometry_covariance_is_written_and_read_back_and_a_bad_one_refused():
    T = np.eye(4)
    T[:3, 3] = [1.0, -2.0, 0.5]
    cov = np.diag([0.1, 0.1, 0.1, 0.01, 0.01, 0.01])
    _, back, cov_back = odometry_to_pose(odometry_msg(5, "odom", "cam", T, covariance=cov))
    np.testing.assert_allclose(back, T)
    np.testing.assert_allclose(cov_back, cov)
    _, _, zero = odometry_to_pose(odometry_msg(5, "odom", "cam", T))
    assert not zero.any()
    for bad in (np.ones(35), -np.eye(6), np.triu(np.ones((6, 6))), np.full(36, np.nan)):
        with pytest.raises(InputError, match="covariance"):
            odometry_msg(5, "odom", "cam", T, covariance=bad)


@pytest.mark.skipif(importlib.util.find_spec("tf2_msgs") is not None,
                    reason="tf2_msgs is installed here: TF can be published")
def test_tf_without_tf2_msgs_stops_the_start_with_a_clear_error(context):
    with pytest.raises(InputError, match="tf2_msgs"):
        RefinerNode(model=tiny_model(), context=context, parameter_overrides=[
            Parameter("outputs", value="odom"), Parameter("odom.publish_tf", value=True)])


@pytest.mark.parametrize("name, value", [("odom.frame_id", ""), ("odom.frame_id", "/odom"),
                                         ("odom.child_frame_id", "my camera")])
def test_frame_names_that_tf_refuses_stop_the_start(context, name, value):
    with pytest.raises(ValueError, match=name.replace(".", r"\.")):
        RefinerNode(model=tiny_model(), context=context,
                    parameter_overrides=[Parameter(name, value=value)])
