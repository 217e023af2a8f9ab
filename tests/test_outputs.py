"""The messages the node publishes for one stream output (sfm_ttr_ros.ros.outputs; README
"Topics"): which topics, which encodings, whose header."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("sensor_msgs")

from std_msgs.msg import Header  # noqa: E402

from msg_adapters import camera_info_msg, image_to_numpy, pointcloud2_to_numpy  # noqa: E402
from sfm_ttr_ros.core.frames import Frame, Intrinsics  # noqa: E402
from sfm_ttr_ros.core.pipeline import WindowResult  # noqa: E402
from sfm_ttr_ros.core.stream.live import LiveOutput  # noqa: E402
from sfm_ttr_ros.core.stream.records import FrameOutput, WindowStats  # noqa: E402
from sfm_ttr_ros.ros import names, outputs  # noqa: E402
from sfm_ttr_ros.ros.camera import CameraSource  # noqa: E402

pytestmark = pytest.mark.ros


def header(sec: int, frame_id: str) -> Header:
    h = Header(frame_id=frame_id)
    h.stamp.sec, h.stamp.nanosec = sec, 250
    return h


def test_live_and_refined_frames_keep_the_image_header():
    depth = np.full((4, 6), 2.0, np.float32)
    depth[0, 0] = 0.0  # invalid
    frame = Frame(index=0, image=np.zeros((4, 6, 3), np.uint8), header=header(7, "cam"))
    live = LiveOutput(frame, depth, version=3, weights_age_s=1.0, arrival=0.0, served=0.01,
                      metres_per_unit=1.0)
    timings: dict[str, float] = {}
    # no intrinsics known yet: the images go out alone (the node counts it), no cloud
    msgs = outputs.live_messages(live, ("depth", "depth_colored", "cloud"), timings=timings)
    assert list(msgs) == [names.DEPTH_TOPIC, names.DEPTH_COLORED_TOPIC]
    d, c = msgs[names.DEPTH_TOPIC], msgs[names.DEPTH_COLORED_TOPIC]
    assert (d.encoding, c.encoding) == ("32FC1", "bgr8")
    assert d.header == c.header == frame.header
    got = image_to_numpy(d)
    assert np.isnan(got[0, 0]) and np.all(got.ravel()[1:] == 2.0)
    assert set(timings) == {"depth_image", "colored_image", "camera_info"}
    assert list(outputs.live_messages(live, ("depth",))) == [names.DEPTH_TOPIC]
    # the windowed output: ~/depth_refined/image only, same header and encoding
    refined = outputs.frame_messages(FrameOutput(frame, depth, refined=True, metres_per_unit=1.0))
    assert list(refined) == [names.DEPTH_REFINED_TOPIC]
    r = refined[names.DEPTH_REFINED_TOPIC]
    assert r.header == frame.header and r.encoding == "32FC1"
    np.testing.assert_array_equal(image_to_numpy(r), got)


def test_every_depth_image_has_a_camera_info_with_its_header_and_size():
    depth = np.full((4, 6), 2.0, np.float32)
    frame = Frame(index=0, image=np.zeros((4, 6, 3), np.uint8), header=header(7, "cam"))
    live = LiveOutput(frame, depth, version=0, weights_age_s=0.0, arrival=0.0, served=0.0,
                      metres_per_unit=2.0)
    # received for a 12x8 image (e.g. before a downscale), with distortion and a stereo Tx
    received = camera_info_msg(12, 8, [[10, 0, 5.5], [0, 11, 3.5], [0, 0, 1]],
                               [[9, 0, 5, -1.2], [0, 9.5, 3, 0], [0, 0, 1, 0]],
                               D=[0.1, -0.02, 0, 0, 0], header=header(1, "elsewhere"))
    camera = CameraSource(Intrinsics(10, 11, 5.5, 3.5, 12, 8), received)
    msgs = outputs.live_messages(live, ("depth", "depth_colored", "cloud"), camera)
    assert list(msgs) == [names.DEPTH_TOPIC, names.DEPTH_INFO_TOPIC, names.DEPTH_COLORED_TOPIC,
                          names.DEPTH_COLORED_INFO_TOPIC, names.CLOUD_TOPIC]
    info = msgs[names.DEPTH_INFO_TOPIC]
    assert msgs[names.DEPTH_COLORED_INFO_TOPIC] == info
    assert info.header == frame.header and (info.width, info.height) == (6, 4)
    np.testing.assert_allclose(np.reshape(info.p, (3, 4)),
                               [[4.5, 0, 2.5, -0.6], [0, 4.75, 1.5, 0], [0, 0, 1, 0]])
    np.testing.assert_allclose(np.reshape(info.k, (3, 3))[:2], [[5, 0, 2.75], [0, 5.5, 1.75]])
    assert list(info.d) == [0.1, -0.02, 0, 0, 0] and info.distortion_model == "plumb_bob"
    assert msgs[names.CLOUD_TOPIC].header == frame.header
    # the same size: the received CameraInfo as it is, the header only replaced
    same = CameraSource(Intrinsics(10, 11, 5.5, 3.5, 6, 4), camera_info_msg(
        6, 4, [[10, 0, 2.5], [0, 11, 1.5], [0, 0, 1]], [[9, 0, 2, 0], [0, 9, 1, 0], [0, 0, 1, 0]],
        D=[0.3], header=header(1, "elsewhere"), distortion_model="rational_polynomial"))
    metric = FrameOutput(frame, depth, refined=True, metres_per_unit=1.0)
    info = outputs.frame_messages(metric, same)[names.DEPTH_REFINED_INFO_TOPIC]
    assert info.header == frame.header and info.distortion_model == "rational_polynomial"
    for field in ("k", "p", "d", "r"):
        np.testing.assert_array_equal(getattr(info, field), getattr(same.message, field))
    # the fallback intrinsics: K, P = [K | 0], D empty, at the image's size
    fallback = CameraSource(Intrinsics(7, 7, 2.5, 1.5, 6, 4), None, fallback=True)
    unrefined = FrameOutput(frame, depth, refined=False, metres_per_unit=1.0)
    info = outputs.frame_messages(unrefined, fallback)[names.DEPTH_REFINED_INFO_TOPIC]
    np.testing.assert_array_equal(np.reshape(info.p, (3, 4)),
                                  [[7, 0, 2.5, 0], [0, 7, 1.5, 0], [0, 0, 1, 0]])
    assert len(info.d) == 0 and (info.width, info.height) == (6, 4)


def test_a_window_gives_its_cloud_in_the_newest_registered_frame():
    cloud_frame = Frame(index=3, image=np.zeros((4, 6, 3), np.uint8), header=header(9, "cam"))
    xyz = np.array([[0.0, 0.0, 1.0], [1.0, 2.0, 3.0]], np.float32)
    err = np.array([0.5, 1.5], np.float32)
    stats = WindowStats(index=1, new_frames=2, cloud_frame=cloud_frame, result=WindowResult(
        ["a", "b"], {}, {}, refined=True, cloud_frame="b", cloud_xyz=xyz, cloud_error=err))
    msgs = outputs.window_messages(stats, points=True, metric=True)
    assert list(msgs) == [names.POINTS_TOPIC]
    cloud = msgs[names.POINTS_TOPIC]
    assert cloud.header == cloud_frame.header
    pts = pointcloud2_to_numpy(cloud)
    assert pts.dtype.names == ("x", "y", "z", "reprojection_error")
    np.testing.assert_array_equal(pts["reprojection_error"], err)
    assert outputs.window_messages(stats, points=False) == {}
    # no cloud (the window did not reach refinement): nothing to publish
    empty = WindowStats(index=2, new_frames=1, result=WindowResult(["a"], {}, {}, False))
    assert outputs.window_messages(empty) == {}


def test_depth_not_in_metres_goes_out_on_the_relative_topics_or_not_at_all():
    """REP 118: the metric topics carry metres only; the relative twins (or nothing) the rest;
    the colour image has no unit and stays."""
    depth = np.full((4, 6), 2.0, np.float32)
    frame = Frame(index=0, image=np.zeros((4, 6, 3), np.uint8), header=header(7, "cam"))
    camera = CameraSource(Intrinsics(7, 7, 2.5, 1.5, 6, 4), None, fallback=True)
    live = LiveOutput(frame, depth, version=0, weights_age_s=0.0, arrival=0.0, served=0.0)
    every = ("depth", "depth_colored", "cloud")
    msgs = outputs.live_messages(live, every, camera)
    assert list(msgs) == [names.DEPTH_RELATIVE_TOPIC, names.DEPTH_RELATIVE_INFO_TOPIC,
                          names.DEPTH_COLORED_TOPIC, names.DEPTH_COLORED_INFO_TOPIC,
                          names.CLOUD_RELATIVE_TOPIC]
    np.testing.assert_array_equal(image_to_numpy(msgs[names.DEPTH_RELATIVE_TOPIC]), depth)
    dropped = outputs.live_messages(live, every, camera, relative="drop")
    assert list(dropped) == [names.DEPTH_COLORED_TOPIC, names.DEPTH_COLORED_INFO_TOPIC]
    refined = FrameOutput(frame, depth, refined=True)
    assert list(outputs.frame_messages(refined, camera)) == [
        names.DEPTH_REFINED_RELATIVE_TOPIC, names.DEPTH_REFINED_RELATIVE_INFO_TOPIC]
    assert outputs.frame_messages(refined, camera, relative="drop") == {}
    stats = WindowStats(index=1, new_frames=2, cloud_frame=frame, result=WindowResult(
        ["a"], {}, {}, refined=True, cloud_frame="a", cloud_xyz=np.ones((2, 3), np.float32),
        cloud_error=np.zeros(2, np.float32)))
    assert list(outputs.window_messages(stats)) == [names.POINTS_RELATIVE_TOPIC]
    assert outputs.window_messages(stats, relative="drop") == {}


def test_compressed_depth_follows_each_depth_image_on_its_own_topic():
    """compressed_depth: <image>/compressedDepth after each depth image, metric or relative,
    decoding back to the depth within one quantisation step of inverse depth."""
    from msg_adapters.compressed_depth import compressed_depth_to_depth, quantisation_error

    depth = np.linspace(0.5, 20.0, 24, dtype=np.float32).reshape(4, 6)
    frame = Frame(index=0, image=np.zeros((4, 6, 3), np.uint8), header=header(7, "cam"))
    packed = outputs.Compression(depth_max=15.0, png_level=1)
    live = LiveOutput(frame, depth, version=0, weights_age_s=0.0, arrival=0.0, served=0.0,
                      metres_per_unit=1.0)
    timings: dict[str, float] = {}
    msgs = outputs.live_messages(live, ("depth",), compressed=packed, timings=timings)
    topic = names.DEPTH_TOPIC + "/compressedDepth"
    assert list(msgs) == [names.DEPTH_TOPIC, topic] and "compressed_depth" in timings
    c = msgs[topic]
    assert c.format == "32FC1; compressedDepth png" and c.header == frame.header
    back = compressed_depth_to_depth(c)
    near = depth < 15.0
    assert np.all(np.isnan(back[~near]))
    assert np.max(np.abs(1 / depth[near] - 1 / back[near])) <= quantisation_error(15.0) * 1.001
    refined = outputs.frame_messages(FrameOutput(frame, depth, refined=True), compressed=packed)
    assert list(refined) == [names.DEPTH_REFINED_RELATIVE_TOPIC,
                             names.DEPTH_REFINED_RELATIVE_TOPIC + "/compressedDepth"]


@pytest.mark.parametrize("state, factor, topic, level", [
    ("metric", 2.0, names.DEPTH_TOPIC, 0),
    ("confirming", 2.0, names.DEPTH_TOPIC, 1),  # metres by one window's estimate: WARN
    ("stale", 2.0, names.DEPTH_TOPIC, 1),  # the source stopped, the last factor holds: WARN
    ("waiting", None, names.DEPTH_RELATIVE_TOPIC, 1),
    ("not_metric", None, names.DEPTH_RELATIVE_TOPIC, 1)])
def test_depth_scale_says_where_the_depth_goes_as_each_frame_is_routed(state, factor, topic,
                                                                        level):
    """~/depth_scale's depth_topic follows the rule every frame is routed by (a factor known:
    metres), its level says whether the metres are confirmed and current."""
    from sfm_ttr_ros.core.metric.scale import MetricStatus
    from sfm_ttr_ros.ros import units

    status = MetricStatus("camera_height", state, factor, 0.0, 1, 0, 0, reason="why")
    msg = units.scale_status_message(status, "publish", "/refiner")
    values = {kv.key: kv.value for kv in msg.values}
    assert values["depth_topic"] == topic and values["state"] == state
    assert values["reason"] == "why" and msg.level == bytes([level])
    routed = units.route({names.DEPTH_TOPIC: "m"}, factor is not None, "publish")
    assert list(routed) == [topic]


@pytest.mark.parametrize("metric, relative, odom, depth", [
    (True, "drop", names.ODOM_OUTPUT_TOPIC, names.DEPTH_REFINED_TOPIC),
    (False, "publish", names.ODOM_RELATIVE_TOPIC, names.DEPTH_REFINED_RELATIVE_TOPIC),
    (False, "drop", None, None)])
def test_the_camera_path_and_the_depth_follow_one_relative_topic_rule(metric, relative, odom,
                                                                      depth):
    """~/odom goes where the depth goes (ros/units.py topic_now): its metric topic, its
    relative twin, or nowhere; a topic without units (~/depth_colored) always stays."""
    from sfm_ttr_ros.ros import units

    assert units.topic_now(names.ODOM_OUTPUT_TOPIC, metric, relative) == odom
    assert units.topic_now(names.DEPTH_REFINED_TOPIC, metric, relative) == depth
    assert units.topic_now(names.DEPTH_COLORED_TOPIC, metric, relative) == (
        names.DEPTH_COLORED_TOPIC)
    assert names.relative_twin_of(names.ODOM_OUTPUT_TOPIC_RESOLVED) == (
        names.ODOM_RELATIVE_TOPIC_RESOLVED)
