"""``~/odom``: the stream's camera path published by the refiner node in a real ROS 2 graph
(in-process, like tests/test_node.py) as the base's odometry (core/stream/base_odometry.py):
its frames, the base's pose, continuity, twist and covariance message by message, its units'
topic, and TF refused clearly where tf2_msgs is missing."""

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

from msg_adapters.odometry import (  # noqa: E402
    odometry_msg,
    odometry_to_pose,
    odometry_to_twist,
)
from sfm_ttr_ros.core.errors import InputError  # noqa: E402
from sfm_ttr_ros.core.stream.base_odometry import (  # noqa: E402
    BaseOdometry,
    parse_camera_mount,
)
from sfm_ttr_ros.ros import names  # noqa: E402
from sfm_ttr_ros.ros.node import RefinerNode  # noqa: E402

pytestmark = pytest.mark.ros
MOUNT = "0.4 0.1 1.3 -95 0 -90"  # the camera 0.4 m ahead of the base, 1.3 m up, 5 deg down


@pytest.fixture
def graph(context, sequence):  # noqa: F811
    g = Graph(context, window_size=6, window_stride=3, outputs="depth_refined,odom",
              **{"metric.source": "camera_height",
                 "metric.camera_height": float(sequence.params.camera_height),
                 "odom.camera_mount": MOUNT})
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
    for units in ("sfm", "m"):  # each topic: the base's odometry of its own poses
        poses = [p for p in reported if p.units == units]
        mount = parse_camera_mount(MOUNT)
        if units == "sfm":  # SfM units: the mount's metres left out
            mount[:3, 3] = 0.0
        base = BaseOdometry(mount)
        for i, (msg, pose) in enumerate(zip(by_units[units], poses, strict=True)):
            expected = base.add(pose.pose)
            assert (msg.header.frame_id, msg.child_frame_id) == ("sfm_odom", "base_link")
            assert msg.header.stamp == pose.frame.header.stamp
            _, T, cov = odometry_to_pose(msg)
            twist, twist_cov = odometry_to_twist(msg)
            np.testing.assert_allclose(T, expected.odom_from_base, atol=1e-9)
            np.testing.assert_allclose(cov, expected.covariance)
            assert (np.linalg.eigvalsh(cov) > 0).all()
            if i == 0:  # no previous pose: the twist is unknown
                assert twist_cov[0, 0] == -1.0 and not twist.any()
                np.testing.assert_allclose(T[:3, 3], 0.0, atol=1e-9)  # odom starts at the base
                continue
            np.testing.assert_allclose(twist, expected.twist, atol=1e-9)
            assert (np.linalg.eigvalsh(twist_cov) > 0).all()
            # the base's pose, not the camera's: the camera it carries (T·mount) moves as the
            # path's camera did (where no jump was absorbed into odom)
            if pose.pose.jump is None:
                _, before, _ = odometry_to_pose(by_units[units][i - 1])
                np.testing.assert_allclose(
                    np.linalg.inv(before @ mount) @ T @ mount,
                    np.linalg.inv(poses[i - 1].pose.odom_from_camera)
                    @ pose.pose.odom_from_camera, atol=1e-7)
    metric = by_units["m"]
    assert len(metric) >= 2
    _, first, _ = odometry_to_pose(metric[0])
    assert abs(first[1, 0]) < 1e-9  # odom's x: the first base's heading
    # a car drives forward: the base moves along odom's x, and odom's z is the ground's up
    # (camera_height): the base stays near z = 0 while the camera is 5 deg down on it
    _, last, _ = odometry_to_pose(metric[-1])
    assert last[0, 3] > 0.5 and abs(last[2, 3]) < 0.1 * last[0, 3]


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
        with pytest.raises(InputError, match="twist covariance"):
            odometry_msg(5, "odom", "cam", T, twist_covariance=bad)
    # a twist and its covariance, or the twist unknown: -1 first, zeros after (nav_msgs)
    twist = np.array([2.0, 0.1, 0.0, 0.0, 0.0, 0.3])
    msg = odometry_msg(5, "odom", "base", T, twist=twist, twist_covariance=0.01 * np.eye(6))
    back, back_cov = odometry_to_twist(msg)
    np.testing.assert_allclose(back, twist)
    np.testing.assert_allclose(back_cov, 0.01 * np.eye(6))
    unknown = np.zeros(36)
    unknown[0] = -1.0
    back, back_cov = odometry_to_twist(odometry_msg(5, "odom", "base", T,
                                                    twist_covariance=unknown))
    assert back_cov[0, 0] == -1.0 and not back.any()
    with pytest.raises(InputError, match="twist"):
        odometry_msg(5, "odom", "base", T, twist=[1.0, 2.0])


@pytest.mark.skipif(importlib.util.find_spec("tf2_msgs") is not None,
                    reason="tf2_msgs is installed here: TF can be published")
def test_tf_without_tf2_msgs_stops_the_start_with_a_clear_error(context):
    with pytest.raises(InputError, match="tf2_msgs"):
        RefinerNode(model=tiny_model(), context=context, parameter_overrides=[
            Parameter("outputs", value="odom"), Parameter("odom.publish_tf", value=True)])


@pytest.mark.parametrize("name, value", [("odom.frame_id", ""), ("odom.frame_id", "/odom"),
                                         ("odom.child_frame_id", "my camera"),
                                         ("odom.child_frame_id", ""),
                                         ("odom.camera_mount", "0 0 0 -90 0")])
def test_frame_names_that_tf_refuses_stop_the_start(context, name, value):
    with pytest.raises(ValueError, match=name.replace(".", r"\.")):
        RefinerNode(model=tiny_model(), context=context,
                    parameter_overrides=[Parameter(name, value=value)])
