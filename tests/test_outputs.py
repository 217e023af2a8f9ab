"""The messages the node publishes for one stream output (sfm_ttr_ros.ros.outputs; README
"Topics"): which topics, which encodings, whose header."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("sensor_msgs")

from std_msgs.msg import Header  # noqa: E402

from msg_adapters import image_to_numpy, pointcloud2_to_numpy  # noqa: E402
from sfm_ttr_ros.core.frames import Frame  # noqa: E402
from sfm_ttr_ros.core.stream.live import LiveOutput  # noqa: E402
from sfm_ttr_ros.core.stream.windows import FrameOutput, WindowStats  # noqa: E402
from sfm_ttr_ros.ros import names, outputs  # noqa: E402

pytestmark = pytest.mark.ros


def header(sec: int, frame_id: str) -> Header:
    h = Header(frame_id=frame_id)
    h.stamp.sec, h.stamp.nanosec = sec, 250
    return h


def test_live_and_refined_frames_keep_the_image_header():
    depth = np.full((4, 6), 2.0, np.float32)
    depth[0, 0] = 0.0  # invalid
    frame = Frame(index=0, image=np.zeros((4, 6, 3), np.uint8), header=header(7, "cam"))
    live = LiveOutput(frame, depth, version=3, weights_age_s=1.0, arrival=0.0, served=0.01)
    timings: dict[str, float] = {}
    msgs = outputs.live_messages(live, colored=True, timings=timings)
    assert list(msgs) == [names.DEPTH_TOPIC, names.DEPTH_COLORED_TOPIC]
    d, c = msgs[names.DEPTH_TOPIC], msgs[names.DEPTH_COLORED_TOPIC]
    assert (d.encoding, c.encoding) == ("32FC1", "bgr8")
    assert d.header == c.header == frame.header
    got = image_to_numpy(d)
    assert np.isnan(got[0, 0]) and np.all(got.ravel()[1:] == 2.0)
    assert set(timings) == {"depth_image", "colored_image"}
    assert list(outputs.live_messages(live, colored=False)) == [names.DEPTH_TOPIC]
    # the windowed output: ~/depth_refined only, same header and encoding
    refined = outputs.frame_messages(FrameOutput(frame, depth, refined=True))
    assert list(refined) == [names.DEPTH_REFINED_TOPIC]
    r = refined[names.DEPTH_REFINED_TOPIC]
    assert r.header == frame.header and r.encoding == "32FC1"
    np.testing.assert_array_equal(image_to_numpy(r), got)


def test_a_window_gives_its_cloud_in_the_newest_registered_frame():
    cloud_frame = Frame(index=3, image=np.zeros((4, 6, 3), np.uint8), header=header(9, "cam"))
    xyz = np.array([[0.0, 0.0, 1.0], [1.0, 2.0, 3.0]], np.float32)
    err = np.array([0.5, 1.5], np.float32)
    stats = WindowStats(index=1, names=["a", "b"], new_frames=2, refined=True,
                        cloud_frame=cloud_frame, cloud_xyz=xyz, cloud_error=err)
    msgs = outputs.window_messages(stats, points=True)
    assert list(msgs) == [names.POINTS_TOPIC]
    cloud = msgs[names.POINTS_TOPIC]
    assert cloud.header == cloud_frame.header
    pts = pointcloud2_to_numpy(cloud)
    assert pts.dtype.names == ("x", "y", "z", "reprojection_error")
    np.testing.assert_array_equal(pts["reprojection_error"], err)
    assert outputs.window_messages(stats, points=False) == {}
    # no cloud (the window did not reach refinement): nothing to publish
    empty = WindowStats(index=2, names=["a"], new_frames=1, refined=False)
    assert outputs.window_messages(empty) == {}
