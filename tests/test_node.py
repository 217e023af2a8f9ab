"""The refiner node in a real ROS 2 graph (in-process, own context), tuned the way `ros2 param`
does it, fed bad input, and installed with colcon then stopped with SIGINT."""

from __future__ import annotations

import os
import random

# Before rclpy is imported (tests/conftest.py does the same): DDS stays on this machine.
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("ROS_DOMAIN_ID", str(random.SystemRandom().randint(1, 100)))

import array  # noqa: E402
import json  # noqa: E402
import shutil  # noqa: E402
import signal  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402
from conftest import tiny_model  # noqa: E402
from helpers import wait_for

rclpy = pytest.importorskip("rclpy")

from builtin_interfaces.msg import Time  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from rcl_interfaces.msg import ParameterType  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.parameter_client import AsyncParameterClient  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from msg_adapters import (  # noqa: E402
    camera_info_msg,
    diagnostic_values,
    intrinsics_to_camera_info,
    numpy_to_image,
    pointcloud2_to_numpy,
    unpack_rgb,
)
from sfm_ttr_ros.ros import names  # noqa: E402
from sfm_ttr_ros.ros import params as node_params  # noqa: E402
from sfm_ttr_ros.ros.node import RefinerNode  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
PKG = "sfm_ttr_ros"
WIDTH, HEIGHT = 320, 96
FRAME_ID = "camera_color_left"
pytestmark = pytest.mark.ros


# republish_unrefined: these tests follow ~/depth_refined frame by frame; the default (not
# again) is tested on its own below
# sfm.first_octave -1: the 320 x 96 test frames need SIFT's upsampled octave (from octave 0, the
# default for real footage, too few features: the windows' scales jump and are refused)
FAST = {"refinement.steps": 5, "sfm.max_num_features": 2048, "min_supervision_points": 20,
        "diagnostics_period_s": 0.5, "republish_unrefined": True, "sfm.first_octave": -1}



def stamp_of(seconds: float) -> Time:
    ns = round(seconds * 1e9)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


@pytest.fixture(scope="module")
def sequence():
    synthetic = pytest.importorskip("sfm_ttr_ros.data.synthetic")
    return synthetic.make_sequence(seed=0, domain="A", num_frames=12, width=WIDTH, height=HEIGHT)


class Graph:
    """A refiner node and a player/recorder node spun by one executor in a thread. The node runs
    the tiny test network, or with ``own_model`` the model its parameters describe (model_type,
    model_path, ...)."""

    def __init__(self, context, *, own_model: bool = False, **params):
        overrides = [Parameter(k, value=v) for k, v in {**FAST, **params}.items()]
        self.refiner = RefinerNode(model=None if own_model else tiny_model(), context=context,
                                   parameter_overrides=overrides)
        self.node = Node("player", context=context)
        reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        if params.get("image_transport") == "compressed":
            self.pub_image = self.node.create_publisher(
                CompressedImage, names.compressed_topic(names.IMAGE_TOPIC), reliable)
        else:
            self.pub_image = self.node.create_publisher(Image, names.IMAGE_TOPIC, reliable)
        self.pub_info = self.node.create_publisher(CameraInfo, names.CAMERA_INFO_TOPIC, reliable)
        self.depths: list[Image] = []  # ~/depth_refined: each frame once its window is done
        self.live: list[Image] = []  # ~/depth: every frame at once
        self.colored: list[Image] = []
        self.points: list[PointCloud2] = []
        self.diags: list[DiagnosticArray] = []
        # what an outside client pairs with the images: their CameraInfos, the dense cloud
        self.live_infos: list[CameraInfo] = []
        self.refined_infos: list[CameraInfo] = []
        self.clouds: list[PointCloud2] = []
        for msg_type, topic, sink in (
                (Image, names.DEPTH_REFINED_TOPIC_RESOLVED, self.depths),
                (Image, names.DEPTH_TOPIC_RESOLVED, self.live),
                (Image, names.DEPTH_COLORED_TOPIC_RESOLVED, self.colored),
                (PointCloud2, names.POINTS_TOPIC_RESOLVED, self.points),
                (CameraInfo, names.DEPTH_INFO_TOPIC_RESOLVED, self.live_infos),
                (CameraInfo, names.DEPTH_REFINED_INFO_TOPIC_RESOLVED, self.refined_infos),
                (PointCloud2, names.CLOUD_TOPIC_RESOLVED, self.clouds)):
            self.node.create_subscription(msg_type, topic, sink.append, reliable)
            # metric.source none: the depth is not in metres, it comes on the relative twin
            twin = names.RELATIVE_TWIN.get("~/" + topic.split("/", 2)[2])
            if twin is not None:
                self.node.create_subscription(msg_type, names.resolve(twin), sink.append,
                                              reliable)
        self.node.create_subscription(DiagnosticArray, names.DIAGNOSTICS_TOPIC,
                                      self.diags.append, 10)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.refiner)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        outputs = [self.refiner.pubs.by_topic[t]
                   for t in (names.DEPTH_TOPIC, names.DEPTH_REFINED_TOPIC)]
        wait_for(lambda: self.pub_image.get_subscription_count() >= 1
                 and self.pub_info.get_subscription_count() >= 1
                 and all(p.get_subscription_count() >= 1 for p in outputs), 20, "discovery")

    def close(self) -> None:
        self.refiner.stop_worker()
        self.executor.shutdown(timeout_sec=2.0)
        self.thread.join(5)
        assert not self.thread.is_alive()
        self.refiner.destroy_node()
        self.node.destroy_node()

    def send_info(self, intr, t: float) -> None:
        self.pub_info.publish(intrinsics_to_camera_info(intr, Header(stamp=stamp_of(t),
                                                                     frame_id=FRAME_ID)))

    def send_image(self, rgb: np.ndarray, t: float, encoding: str = "rgb8") -> Image:
        msg = numpy_to_image(rgb, encoding, Header(stamp=stamp_of(t), frame_id=FRAME_ID))
        self.pub_image.publish(msg)
        return msg

    def last_diag(self) -> dict[str, str]:
        """The key/values of the node's last statuses (stream, scale, live, worker: each key
        in one of them), merged."""
        for msg in reversed(self.diags):
            if any(s.hardware_id == names.NODE_FQN for s in msg.status):
                return diagnostic_values(msg, hardware_id=names.NODE_FQN)
        return {}

    def last_status(self, task: str) -> DiagnosticStatus:
        """The node's last status of ``task`` (``stream``, ``scale``, ``live``, ``worker``)."""
        for msg in reversed(self.diags):
            for status in msg.status:
                if status.name == names.DIAG_NAMES[task]:
                    return status
        raise AssertionError(f"no {task} status received")


@pytest.fixture
def graph_factory(context):
    graphs = []

    def make(**params):
        g = Graph(context, **params)
        graphs.append(g)
        return g

    yield make
    for g in graphs:
        g.close()


def counts_add_up(d: dict[str, str]) -> bool:
    n = {k: int(d[k]) for k in ("frames_received", "frames_refined", "frames_unrefined",
                                "frames_dropped", "frames_pending")}
    return n["frames_received"] == (n["frames_refined"] + n["frames_unrefined"]
                                    + n["frames_dropped"] + n["frames_pending"])


@pytest.mark.slow
def test_every_frame_comes_back_with_its_header(graph_factory, sequence):
    g = graph_factory(window_size=6, window_stride=3)
    sent = []
    for i, (rgb, t) in enumerate(zip(sequence.images, sequence.stamps, strict=True)):
        g.send_info(sequence.intrinsics, t)
        bgr = np.ascontiguousarray(rgb[:, :, ::-1])
        sent.append(g.send_image(bgr if i % 2 else rgb, t, "bgr8" if i % 2 else "rgb8"))
        time.sleep(0.03)
    wait_for(lambda: len(g.depths) == len(sent), 120, "every depth image")
    by_stamp = {(m.header.stamp.sec, m.header.stamp.nanosec): m for m in g.depths}
    assert len(by_stamp) == len(sent)
    for m in sent:
        d = by_stamp[(m.header.stamp.sec, m.header.stamp.nanosec)]
        assert d.header.frame_id == FRAME_ID
        assert (d.encoding, d.width, d.height, d.step) == ("32FC1", WIDTH, HEIGHT, WIDTH * 4)
        depth = np.frombuffer(d.data, np.float32)
        assert np.isfinite(depth).mean() > 0.99 and np.nanmin(depth) > 0
    # the live path: each frame once on ~/depth and ~/depth_colored, or skipped and counted
    # (live_max_queue: a slow moment serves the newest frames)
    live = g.refiner.online.live
    wait_for(lambda: live.pending == 0 and len(g.colored) == len(g.live) == live.published,
             20, "every live depth")
    assert live.received == len(sent) == live.published + sum(live.skipped.values())
    assert all(c.encoding == "bgr8" for c in g.colored)

    windows = list(g.refiner.stream.windows)
    assert len(windows) == 3 and all(w.refined for w in windows), [w.reason for w in windows]
    wait_for(lambda: len(g.points) == 3, 10, "one cloud per window")
    for cloud, w in zip(g.points, windows, strict=True):
        assert cloud.header == w.cloud_frame.header  # the newest registered frame's header
        pts = pointcloud2_to_numpy(cloud)
        assert pts.dtype.names == ("x", "y", "z", "reprojection_error")
        xyz = np.stack([pts["x"], pts["y"], pts["z"]], 1)
        finite = np.isfinite(w.result.cloud_xyz).all(1)
        assert np.isfinite(xyz).all(1).sum() == finite.sum() == w.points
        np.testing.assert_allclose(xyz, w.result.cloud_xyz, rtol=1e-6)

    d = wait_for(lambda: (lambda v: v if v.get("frames_pending") == "0" else None)(
        g.last_diag()), 10, "final diagnostics")
    assert counts_add_up(d)
    assert (d["frames_received"], d["frames_refined"], d["frames_dropped"]) == ("12", "12", "0")
    assert d["windows_ok"] == "3" and d["last_window.steps_done"] == "5"
    assert int(d["last_window.registered_frames"]) >= 2
    assert 0 < float(d["last_window.inlier_ratio"]) <= 1
    assert float(d["last_window.scale"]) > 0 and "last_window.time.sfm_s" in d


def _key(msg) -> tuple[int, int]:
    return msg.header.stamp.sec, msg.header.stamp.nanosec


def _t_key(seconds: float) -> tuple[int, int]:
    stamp = stamp_of(seconds)
    return stamp.sec, stamp.nanosec


def _back_projected(depth_msg: Image, info: CameraInfo, rgb: np.ndarray, stride: int,
                    max_range: float) -> tuple[np.ndarray, np.ndarray]:
    """depth_image_proc's point_cloud_xyzrgb, pixel by pixel: P's fx, fy, cx, cy, every
    ``stride``-th pixel, invalid and far points left out; (xyz, rgb)."""
    P = np.reshape(info.p, (3, 4))
    fx, fy, cx, cy = P[0, 0], P[1, 1], P[0, 2], P[1, 2]
    depth = np.frombuffer(depth_msg.data, np.float32).reshape(depth_msg.height, depth_msg.width)
    xyz, colours = [], []
    for v in range(0, depth.shape[0], stride):
        for u in range(0, depth.shape[1], stride):
            z = float(depth[v, u])
            if not (np.isfinite(z) and z > 0):
                continue
            x, y = (u - cx) * z / fx, (v - cy) * z / fy
            if max_range > 0 and x * x + y * y + z * z > max_range ** 2:
                continue
            xyz.append((x, y, z))
            colours.append(rgb[v, u])
    return np.array(xyz).reshape(-1, 3), np.array(colours, np.uint8).reshape(-1, 3)


@pytest.mark.slow
def test_an_outside_client_pairs_every_depth_with_its_camera_info_and_the_cloud(graph_factory,
                                                                               sequence):
    stride, max_range = 3, 30.0
    g = graph_factory(window_size=3, window_stride=3, idle_flush_s=1.0,
                      outputs="depth,depth_colored,depth_refined,cloud,diagnostics",
                      **{"cloud.stride": stride, "cloud.max_range": max_range})
    pubs = [g.refiner.pubs.by_topic[t] for t in (
        names.DEPTH_INFO_TOPIC, names.DEPTH_REFINED_INFO_TOPIC, names.CLOUD_TOPIC)]
    wait_for(lambda: all(p.get_subscription_count() >= 1 for p in pubs), 20, "discovery")
    # what a calibrated camera driver sends: rectified images (P = [K | 0], zero distortion)
    K = sequence.intrinsics.K
    infos = {}
    for t in sequence.stamps[:6]:
        infos[_t_key(t)] = camera_info_msg(
            WIDTH, HEIGHT, K, np.hstack([K, np.zeros((3, 1))]), D=np.zeros(5),
            header=Header(stamp=stamp_of(t), frame_id=FRAME_ID))
    # the first image before any CameraInfo: its live depth goes out alone, counted
    g.send_image(sequence.images[0], sequence.stamps[0])
    wait_for(lambda: len(g.live) == 1, 30, "the first live depth")
    d = wait_for(lambda: (lambda v: v if v.get("live.without_camera_info") == "1" else None)(
        g.last_diag()), 10, "live.without_camera_info on /diagnostics")
    assert d["frames_without_camera_info"] == "0"
    for i in range(6):
        g.pub_info.publish(infos[_t_key(sequence.stamps[i])])
        if i:
            rgb = sequence.images[i]
            bgr = np.ascontiguousarray(rgb[:, :, ::-1])
            g.send_image(bgr if i % 2 else rgb, sequence.stamps[i], "bgr8" if i % 2 else "rgb8")
        time.sleep(0.05)
    wait_for(lambda: len(g.depths) == 6 and len(g.refined_infos) == 6, 120, "refined depths")
    wait_for(lambda: len(g.live) == 6 and len(g.live_infos) == 5 and len(g.clouds) == 5, 30,
             "live depths, their CameraInfos and clouds")
    rgb_by_stamp = {_t_key(t): im
                    for t, im in zip(sequence.stamps[:6], sequence.images[:6], strict=True)}
    first = _key(g.live[0])
    for images, pairs in ((g.live, g.live_infos), (g.depths, g.refined_infos)):
        by_stamp = {_key(m): m for m in pairs}
        assert len(by_stamp) == len(pairs)
        for img in images:
            if images is g.live and _key(img) == first:
                assert first not in by_stamp  # published before any CameraInfo
                continue
            info = by_stamp[_key(img)]
            assert info.header.frame_id == img.header.frame_id == FRAME_ID
            assert (info.width, info.height) == (img.width, img.height)
            sent = infos[_key(img)]
            for field in ("k", "p", "d", "r"):
                np.testing.assert_array_equal(getattr(info, field), getattr(sent, field))
    clouds = {_key(c): c for c in g.clouds}
    for img in g.live[1:]:
        cloud = clouds[_key(img)]
        assert cloud.header == img.header and cloud.is_dense
        pts = pointcloud2_to_numpy(cloud)
        xyz, colours = _back_projected(img, infos[_key(img)], rgb_by_stamp[_key(img)], stride,
                                       max_range)
        assert 0 < len(pts) == len(xyz) < (WIDTH // stride + 1) * (HEIGHT // stride + 1)
        np.testing.assert_allclose(np.stack([pts["x"], pts["y"], pts["z"]], 1), xyz,
                                   rtol=1e-5, atol=1e-5)
        np.testing.assert_array_equal(unpack_rgb(pts["rgb"]), colours)
    assert g.refiner.diagnostics.without_camera_info == {"live": 1}


@pytest.mark.slow
def test_parameters_tuned_like_ros2_param(graph_factory, sequence):
    g = graph_factory(window_size=3, window_stride=3)
    client = AsyncParameterClient(g.node, names.NODE_NAME)
    assert client.wait_for_services(timeout_sec=10)

    def call(future):
        return wait_for(lambda: future.result() if future.done() else None, 10, "service")

    declared = call(client.list_parameters()).result.names
    assert set(node_params.SPECS) <= set(declared)
    desc = {d.name: d for d in call(client.describe_parameters(
        ["window_size", "refinement.lr", "model_type", "refinement.loss"])).descriptors}
    assert desc["window_size"].integer_range[0].from_value == 2
    assert desc["refinement.lr"].type == ParameterType.PARAMETER_DOUBLE
    assert desc["model_type"].read_only and not desc["window_size"].read_only
    assert "hybrid" in desc["refinement.loss"].additional_constraints

    def set_(name, value):
        return call(client.set_parameters([Parameter(name, value=value)])).results[0]

    ok = set_("refinement.steps", 3)
    assert ok.successful, ok.reason
    # the tiny test model has no encoder stages: frozen levels apply as its whole encoder
    whole = set_("refinement.frozen_encoder_levels", 1)
    assert whole.successful, whole.reason
    refused = {
        "window_size": set_("window_size", 1),  # out of range
        "refinement.lr": set_("refinement.lr", 1),  # an integer for a double
        "model_type": set_("model_type", "mobilenet"),  # read-only
        "window_stride": set_("window_stride", 4),  # > window_size
        "refinement.loss": set_("refinement.loss", "banana"),
        "refinement.lr ": set_("refinement.lr", 0.0),
    }
    assert all(not r.successful for r in refused.values())
    assert "range" in refused["window_size"].reason
    assert "type" in refused["refinement.lr"].reason.lower()
    assert "read-only" in refused["model_type"].reason
    assert "window_stride" in refused["window_stride"].reason
    assert "loss" in refused["refinement.loss"].reason
    assert "lr" in refused["refinement.lr "].reason
    got = call(client.get_parameters(["refinement.steps", "window_size"])).values
    assert (got[0].integer_value, got[1].integer_value) == (3, 3)

    # the next window uses the live value
    g.send_info(sequence.intrinsics, sequence.stamps[0])
    for rgb, t in zip(sequence.images[:3], sequence.stamps[:3], strict=True):
        g.send_image(rgb, t)
    wait_for(lambda: len(g.depths) == 3, 60, "the window's depths")
    w = g.refiner.stream.last_window
    assert w.steps == 3 and (w.steps_done == 3 or not w.refined), w
    d = wait_for(lambda: (lambda v: v if v.get("last_window.steps") else None)(g.last_diag()),
                 10, "window diagnostics")
    assert d["last_window.steps"] == "3"


def _raw_image(width, height, encoding, data, step) -> Image:
    msg = Image(width=width, height=height, encoding=encoding, step=step)
    msg.header.frame_id = FRAME_ID
    msg.data = array.array("B", data)
    return msg


@pytest.mark.slow
def test_bad_input_is_counted_never_fatal(graph_factory, sequence):
    # reliable: a best-effort publisher is refused below; never STALE: the last status is the
    # WARN of the frames passed unrefined, however long the input has been silent by then
    g = graph_factory(window_size=3, window_stride=3, idle_flush_s=1.0,
                      qos_reliability="reliable", **{"diagnostics.stale_after_s": 0.0})
    refiner = g.refiner
    ok_rgb, other_rgb = sequence.images[0], sequence.images[1]

    # broken images: truncated data, unknown encoding, zero size
    g.pub_image.publish(_raw_image(WIDTH, HEIGHT, "rgb8", bytes(100), WIDTH * 3))
    g.pub_image.publish(_raw_image(4, 4, "yuv422_weird", bytes(64), 16))
    g.pub_image.publish(_raw_image(0, 0, "rgb8", b"", 0))
    wait_for(lambda: refiner.stream.counters()["dropped_by_reason"].get("bad_image") == 3, 10,
             "3 rejected images")
    # a CameraInfo of a zero image size (K all zero: an uncalibrated camera, intrinsics
    # assumed: tests/test_camera_info_topic.py)
    bad = CameraInfo()
    g.pub_info.publish(bad)
    wait_for(lambda: refiner.diagnostics.rejected_camera_info == 1, 10, "rejected CameraInfo")
    # no intrinsics at all yet: frames are held
    g.send_image(ok_rgb, 10.0)
    g.send_image(ok_rgb, 11.0, "rgb8")
    wait_for(lambda: refiner.intrinsics.held == 2, 10, "2 held frames")
    assert refiner.diagnostics_values()["frames_held_no_intrinsics"] == 2
    g.send_info(sequence.intrinsics, 11.0)
    wait_for(lambda: not refiner.intrinsics.held, 10, "held frames released")
    g.send_image(ok_rgb, 11.0)  # duplicate stamp: rejected
    wait_for(lambda: refiner.stream.counters()["dropped_by_reason"].get("duplicate_stamp"), 10,
             "duplicate rejected")
    g.send_image(ok_rgb, 12.0)  # third identical frame: static camera, SfM fails
    wait_for(lambda: len(g.depths) == 3, 60, "the static window")
    # a stamp back in time, then a resolution change mid-stream; the CameraInfos go first and
    # are matched to the images by stamp
    small = sequence.intrinsics.scaled(160, 48)
    g.send_info(sequence.intrinsics, 5.0)
    g.send_info(small, 6.0)
    wait_for(lambda: refiner.intrinsics.latest == small, 10, "new CameraInfo")
    g.send_image(other_rgb, 5.0)
    g.send_image(np.ascontiguousarray(other_rgb[::2, ::2]), 6.0)
    wait_for(lambda: refiner.stream.counters()["non_monotonic_stamps"] == 1, 10, "jump back")
    # the 160x48 frame is alone in its window: the idle flush publishes it unrefined
    wait_for(lambda: len(g.depths) == 5, 30, "every frame accounted for")
    # a best-effort publisher cannot feed a reliable subscription: an incompatible-QoS event
    g.node.create_publisher(Image, names.IMAGE_TOPIC, QoSProfile(
        depth=5, reliability=ReliabilityPolicy.BEST_EFFORT))
    wait_for(lambda: refiner.diagnostics.qos_incompatible[names.IMAGE_TOPIC] > 0, 15,
             "incompatible QoS event")

    c = refiner.stream.counters()
    assert c["unrefined_by_reason"] == {"sfm_failed": 3, "resolution_change": 1,
                                        "end_of_stream": 1}
    assert c["dropped_by_reason"] == {"bad_image": 3, "duplicate_stamp": 1}
    assert (c["received"], c["refined"], c["pending"]) == (9, 0, 0)
    assert refiner.stream.windows[0].reason.startswith("SfM failed: ")
    assert [(m.width, m.height) for m in g.depths][-1] == (160, 48)
    d = wait_for(lambda: (lambda v: v if v.get("qos_incompatible", "0") != "0" else None)(
        g.last_diag()), 10, "diagnostics with the QoS event")
    assert counts_add_up(d)
    assert (d["rejected_bad_image"], d["rejected_camera_info"], d["non_monotonic_stamps"]) == \
        ("3", "1", "1")
    assert d["unrefined.sfm_failed"] == "3" and d["dropped.duplicate_stamp"] == "1"
    assert g.last_status("stream").level == DiagnosticStatus.WARN  # frames passed unrefined


def test_fallback_intrinsics_and_camera_info_projection(graph_factory, sequence):
    intr = sequence.intrinsics
    # fx, fy: the names of the last release, which still work (translated, with a warning)
    g = graph_factory(window_size=50, window_stride=1, fx=intr.fx, fy=intr.fy,
                      camera_info_use_projection=True)
    assert g.refiner.settings.fallback == (intr.fx, intr.fy, 0.0, 0.0)
    g.send_image(sequence.images[0], 1.0)
    wait_for(lambda: g.refiner.stream._intr is not None, 10, "frame with fallback intrinsics")
    assert g.refiner.stream._intr.fx == intr.fx
    assert g.refiner.stream._intr.cx == (WIDTH - 1) / 2
    # beside the live depth: a CameraInfo built from the fallback (P = [K | 0], D empty)
    info = wait_for(lambda: g.live_infos and g.live_infos[0], 10, "the fallback's CameraInfo")
    assert info.header == g.live[0].header and len(info.d) == 0
    np.testing.assert_allclose(np.reshape(info.p, (3, 4)), [
        [intr.fx, 0, (WIDTH - 1) / 2, 0], [0, intr.fy, (HEIGHT - 1) / 2, 0], [0, 0, 1, 0]])
    # P, not K, when camera_info_use_projection is true
    msg = intrinsics_to_camera_info(intr)
    msg.k = [0.0] * 9
    g.pub_info.publish(msg)
    wait_for(lambda: g.refiner.intrinsics.latest == intr, 10, "intrinsics from P")


def test_an_unrefined_frame_already_on_depth_is_counted_not_sent_again(graph_factory,
                                                                       sequence):
    g = graph_factory(window_size=50, window_stride=1, idle_flush_s=0.5,
                      republish_unrefined=False)
    g.send_info(sequence.intrinsics, 1.0)
    g.send_image(sequence.images[0], 1.0)
    wait_for(lambda: len(g.live) == 1, 30, "the live depth")
    # alone in its window: the idle flush passes it unrefined; ~/depth already carried it
    wait_for(lambda: g.refiner.stream.counters()["pending"] == 0
             and g.refiner.stream.counters()["unrefined"] == 1, 30, "the idle flush")
    c = g.refiner.stream.counters()
    assert c["unrefined_by_reason"] == {"end_of_stream": 1} and c["live_only"] == 1
    d = wait_for(lambda: (lambda v: v if v.get("frames_live_only") == "1" else None)(
        g.last_diag()), 10, "frames_live_only on /diagnostics")
    assert d["frames_unrefined"] == "1" and d["frames_received"] == "1"
    # without the live output the frame must come back on ~/depth_refined
    assert g.refiner.set_parameters([Parameter(
        "outputs", value="depth_refined,points,diagnostics")])[0].successful
    g.send_info(sequence.intrinsics, 2.0)
    g.send_image(sequence.images[1], 2.0)
    wait_for(lambda: len(g.depths) == 1, 30, "the frame on ~/depth_refined")
    c = g.refiner.stream.counters()
    assert c["unrefined"] == 2 and c["live_only"] == 1 and len(g.live) == 1
    assert g.depths[0].header.stamp.sec == 2


def test_fallback_principal_point_outside_the_frame_is_a_mismatch_not_fatal(graph_factory,
                                                                            sequence):
    # params/kitti.yaml's fallback (cx, cy) on a smaller frame ended the process
    g = graph_factory(window_size=50, window_stride=1,
                      fallback_intrinsics="721.5377 721.5377 609.5593 172.854")
    small = np.ascontiguousarray(sequence.images[0][:50, :100])
    g.send_image(small, 1.0)
    g.send_image(np.ascontiguousarray(sequence.images[1][:128, :300]), 2.0)
    wait_for(lambda: len(g.depths) == 2, 30, "both frames back, unrefined")
    assert [(m.width, m.height) for m in g.depths] == [(100, 50), (300, 96)]
    c = g.refiner.stream.counters()
    assert c["unrefined_by_reason"] == {"intrinsics_mismatch": 2} and c["pending"] == 0
    # a live principal point far outside every frame: accepted, the next frames pass unrefined
    result = g.refiner.set_parameters([Parameter(
        "fallback_intrinsics", value="721.5377 721.5377 5000 172.854")])[0]
    assert result.successful, result.reason
    g.send_image(sequence.images[2], 3.0)
    wait_for(lambda: len(g.depths) == 3, 30, "the third frame")
    c = g.refiner.stream.counters()
    assert c["unrefined_by_reason"] == {"intrinsics_mismatch": 3}
    assert g.refiner.worker_alive and g.refiner.diagnostics.faults == {}
    assert sum(c["dropped_by_reason"].values()) == 0


def test_faults_in_callbacks_are_counted_never_fatal(graph_factory, sequence, monkeypatch):
    from sfm_ttr_ros.ros import node as node_module

    g = graph_factory(window_size=50, window_stride=1)
    refiner = g.refiner
    intr = sequence.intrinsics

    def boom(*args, **kwargs):
        raise ZeroDivisionError("injected")

    # a decoder raising something unforeseen: the message is dropped as bad_image, with the type
    monkeypatch.setattr(node_module, "image_to_rgb8", boom)
    g.send_image(sequence.images[0], 1.0)
    wait_for(lambda: refiner.stream.counters()["dropped_by_reason"].get("bad_image") == 1, 10,
             "the image dropped")
    monkeypatch.undo()
    # the CameraInfo adapter raising: the CameraInfo is rejected
    monkeypatch.setattr(node_module.camera, "camera_info_to_intrinsics", boom)
    g.send_info(intr, 1.0)
    wait_for(lambda: refiner.diagnostics.rejected_camera_info == 1, 10, "CameraInfo rejected")
    monkeypatch.undo()
    # a fault building the output messages (worker side): counted, the worker goes on
    monkeypatch.setattr(node_module.outputs, "frame_messages", boom)
    g.send_info(intr, 2.0)
    g.send_image(sequence.images[1], 2.0)
    wait_for(lambda: refiner.diagnostics.faults.get("publish") == 1, 20, "publish fault")
    monkeypatch.undo()
    # the timer and the parameter check raising
    monkeypatch.setattr(refiner.intrinsics, "release", boom)
    wait_for(lambda: refiner.diagnostics.faults.get("timer", 0) >= 1, 10, "timer fault")
    monkeypatch.undo()
    monkeypatch.setattr(node_params, "validate", boom)
    result = refiner.set_parameters([Parameter("refinement.steps", value=3)])[0]
    monkeypatch.undo()
    assert not result.successful and "ZeroDivisionError: injected" in result.reason
    assert refiner.diagnostics.faults["parameters"] == 1

    # still serving: the next frame comes back
    g.send_image(sequence.images[2], 3.0)
    wait_for(lambda: len(g.depths) == 1, 30, "a depth after the faults")
    assert refiner.worker_alive
    d = wait_for(lambda: (lambda v: v if v.get("faults.parameters") else None)(g.last_diag()),
                 10, "diagnostics with the faults")
    assert int(d["faults"]) >= 3 and d["faults.publish"] == "1"
    assert counts_add_up(d)


def test_compressed_transport_decodes_jpeg_and_png_and_drops_the_undecodable(graph_factory,
                                                                           sequence):
    from msg_adapters import rgb8_to_compressed

    intr = sequence.intrinsics
    g = graph_factory(image_transport="compressed", window_size=50, window_stride=1,
                      fallback_intrinsics=f"{intr.fx} {intr.fy} 0 0")
    assert g.refiner.image_topic == "/image/compressed"
    for i, codec in enumerate(("jpeg", "png")):
        g.pub_image.publish(rgb8_to_compressed(sequence.images[i], codec,
                                               Header(stamp=stamp_of(i + 1.0), frame_id=FRAME_ID)))
    junk = CompressedImage(format="rgb8; jpeg compressed bgr8")
    junk.data = array.array("B", b"\xff\xd8\xff\xe0 not really a jpeg")
    g.pub_image.publish(junk)
    wait_for(lambda: len(g.depths) == 2, 30, "the two decoded frames back")
    assert [(m.width, m.height) for m in g.depths] == [(WIDTH, HEIGHT)] * 2
    wait_for(lambda: g.refiner.stream.counters()["dropped_by_reason"].get("bad_image") == 1, 10,
             "the undecodable one dropped")
    assert g.refiner.diagnostics.faults == {}


def test_unwritable_save_weights_path_is_logged_and_the_stop_clean(context, tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    node = RefinerNode(model=tiny_model(), context=context, parameter_overrides=[
        Parameter("save_weights_path", value=str(blocker / "sub" / "enc.pth"))])
    node.destroy_node()  # stop_worker tries to save: logged, no exception
    assert blocker.read_text() == "not a folder" and not node.worker_alive


@pytest.mark.parametrize("case", ["corrupt_weights", "missing_model_files", "corrupt_model"])
def test_start_up_failures_exit_1_with_one_line_before_spinning(case, tmp_path):
    corrupt = tmp_path / "corrupt.pth"
    corrupt.write_bytes(b"PK\x03\x04 this is not a torch file")
    args = {"corrupt_weights": ["-p", f"load_weights_path:={corrupt}"],
            "missing_model_files": ["-p", "model_type:=monodepth2", "-p",
                                    f"encoder_path:={tmp_path / 'no_enc.pth'}", "-p",
                                    f"decoder_path:={tmp_path / 'no_dec.pth'}"],
            "corrupt_model": ["-p", "model_type:=mobilenet", "-p", f"encoder_path:={corrupt}",
                              "-p", f"decoder_path:={corrupt}"]}[case]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    out = subprocess.run([sys.executable, "-m", "sfm_ttr_ros.ros.node", "--ros-args", *args],
                         cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    text = out.stdout + out.stderr
    assert out.returncode == 1, text[-2000:]
    assert "Traceback" not in text and "refiner ready" not in text, text[-2000:]
    lines = [ln for ln in text.splitlines() if "cannot start" in ln]
    assert len(lines) == 1, text[-2000:]


def test_a_pycolmap_too_old_for_sfm_stops_the_start_with_one_line(tmp_path):
    # 4.0.x / 4.1.x lack pycolmap.CancellationToken: every window would fail, silently
    (tmp_path / "fake").mkdir()
    (tmp_path / "fake" / "pycolmap.py").write_text('__version__ = "4.1.1"\n')
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "fake"), str(REPO)])}
    out = subprocess.run([sys.executable, "-m", "sfm_ttr_ros.ros.node", "--ros-args"],
                         cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    text = out.stdout + out.stderr
    assert out.returncode == 1, text[-2000:]
    lines = [ln for ln in text.splitlines() if "cannot start" in ln]
    assert len(lines) == 1 and "pycolmap 4.1.1 is too old" in lines[0], text[-2000:]
    assert "Traceback" not in text and "refiner ready" not in text


def test_the_final_accounting_is_kept_as_data_when_the_node_stops(context):
    node = RefinerNode(model=tiny_model(), context=context)
    assert node.final_accounting is None
    node.destroy_node()
    v = node.final_accounting
    assert list(v) == list(node.diagnostics.values())  # every key of the 'stopped:' line
    assert v["frames_received"] == 0 and v["live.received"] == v["live.skipped"] == 0


def test_the_refiner_writes_its_accounting_file_on_sigint(tmp_path):
    path = tmp_path / "out" / "accounting.json"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "sfm_ttr_ros.ros.node", "--accounting", str(path), "--ros-args",
         "-p", "model_type:=mobilenet", "-p", "window_size:=7", "-p", "window_stride:=7"],
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        seen = []
        for line in proc.stdout:  # until the node is up (subscribed, warmed up)
            seen.append(line)
            if "refiner ready" in line:
                break
        time.sleep(1.0)  # out of the constructor, spinning: a SIGINT now stops the node
        assert proc.poll() is None, "".join(seen)[-2000:]
        proc.send_signal(signal.SIGINT)
        text = "".join(seen) + proc.communicate(timeout=30)[0]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0 and "Traceback" not in text, text[-2000:]
    assert path.is_file(), text[-2000:]
    v = json.loads(path.read_text())
    assert v["frames_received"] == v["frames_pending"] == 0 and v["faults"] == 0
    assert (v["live.received"], v["live.published"], v["live.skipped"]) == (0, 0, 0)
    assert "live ~/depth: 0 received, 0 published, 0 skipped" in text  # the same, as a line


@pytest.mark.slow
def test_stop_cancels_a_running_window(graph_factory, sequence):
    # a 3-frame window has little parallax: the parallax check would refuse it before refining
    g = graph_factory(window_size=3, window_stride=3, **{"refinement.steps": 1_000_000,
                                                         "check.min_parallax": 0.0})
    g.send_info(sequence.intrinsics, sequence.stamps[0])
    for rgb, t in zip(sequence.images[:3], sequence.stamps[:3], strict=True):
        g.send_image(rgb, t)
    wait_for(lambda: g.refiner.stream.queued() == 0 and g.refiner.stream.pending() == 3, 10,
             "the window to start")
    time.sleep(3.0)  # SfM done, refinement running (a million steps)
    t0 = time.monotonic()
    g.refiner.stop_worker()
    assert time.monotonic() - t0 < 3.0
    assert not g.refiner.worker_alive
    assert g.depths == []  # nothing is published once stopping


def test_weights_are_loaded_at_start_and_saved_on_stop(context, tmp_path):
    donor = tiny_model()
    for p in donor.encoder.parameters():
        p.data.add_(1.0)
    start, end = tmp_path / "start.pth", tmp_path / "out" / "end.pth"
    torch.save(donor.encoder.state_dict(), start)
    node = RefinerNode(model=tiny_model(), context=context, parameter_overrides=[
        Parameter("load_weights_path", value=str(start)),
        Parameter("save_weights_path", value=str(end))])
    try:
        for a, b in zip(node.ttr.model.encoder.parameters(), donor.encoder.parameters(),
                        strict=True):
            assert torch.equal(a, b)
    finally:
        node.destroy_node()
    saved = torch.load(end, weights_only=True)
    assert all(torch.equal(saved[k], v) for k, v in donor.encoder.state_dict().items())
    with pytest.raises(ValueError, match="load_weights_path"):
        RefinerNode(model=tiny_model(), context=context, parameter_overrides=[
            Parameter("load_weights_path", value=str(tmp_path / "missing.pth"))])


def test_start_up_fails_cleanly_on_inconsistent_parameters(context):
    with pytest.raises(ValueError, match="window_stride"):
        RefinerNode(model=tiny_model(), context=context, parameter_overrides=[
            Parameter("window_size", value=3), Parameter("window_stride", value=4)])


# -- installed with colcon, started like `ros2 run`, stopped with SIGINT ---------------------
@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    colcon = Path(sys.executable).parent / "colcon"
    if not colcon.is_file():
        colcon = shutil.which("colcon")
        if colcon is None:
            pytest.skip("colcon is not installed")
    tmp = tmp_path_factory.mktemp("colcon_node")
    out = subprocess.run(
        [str(colcon), "--log-base", str(tmp / "log"), "build", "--paths", str(REPO),
         "--build-base", str(tmp / "build"), "--install-base", str(tmp / "install")],
        cwd=tmp, capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    return tmp / "install" / PKG


@pytest.mark.slow
def test_installed_refiner_runs_and_stops_on_sigint(installed, context, tmp_path,
                                                    monkeypatch):
    ament_index = pytest.importorskip("ament_index_python.packages")
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(installed))
    prefix = Path(ament_index.get_package_prefix(PKG))
    exe = prefix / "lib" / PKG / "refiner"
    assert exe.is_file() and os.access(exe, os.X_OK)
    shebang = exe.read_text().splitlines()[0]
    assert shebang.startswith("#!/") and Path(shebang[2:]).parent == Path(sys.executable).parent
    params = Path(ament_index.get_package_share_directory(PKG)) / "params" / "refiner.yaml"
    env = dict(os.environ)
    env["PYTHONPATH"] = str(prefix / "lib" / f"python{sys.version_info[0]}."
                            f"{sys.version_info[1]}" / "site-packages")
    proc = subprocess.Popen(
        [str(exe), "--ros-args", "--params-file", str(params), "-p", "model_type:=mobilenet",
         "-p", "window_size:=7"],
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    node = Node("param_reader", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        client = AsyncParameterClient(node, names.NODE_NAME)
        assert client.wait_for_services(timeout_sec=60), "the installed node never came up"
        future = client.get_parameters(["window_size", "model_type", "refinement.lr"])
        executor.spin_until_future_complete(future, timeout_sec=60)
        assert future.done(), "no answer from the installed node's parameter service"
        values = future.result().values
        assert values[0].integer_value == 7
        assert values[1].string_value == "mobilenet"
        assert values[2].double_value == pytest.approx(1e-4)
        time.sleep(0.5)
        assert proc.poll() is None
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=15)
        elapsed = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        executor.shutdown()
        node.destroy_node()
    assert proc.returncode == 0, stderr[-3000:]
    assert "Traceback" not in stderr, stderr[-3000:]
    assert "refiner ready" in stdout + stderr and "stopped:" in stdout + stderr
    assert "live ~/depth: 0 received, 0 published, 0 skipped" in stdout + stderr  # accounted
    assert elapsed < 10


@pytest.mark.slow
def test_live_depth_serves_every_frame_at_once_and_takes_the_refined_weights(graph_factory,
                                                                             sequence):
    # ~/depth answers every frame from the serving copy, without waiting for windows
    g = graph_factory(window_size=6, window_stride=6, **{"refinement.steps": 20,
                                                          "refinement.lr": 1e-2})
    g.send_info(sequence.intrinsics, sequence.stamps[0])
    for rgb, t in zip(sequence.images[:3], sequence.stamps[:3], strict=True):
        g.send_image(rgb, t)
    # three frames: no window yet (6 keyframes needed), yet all three are served live
    wait_for(lambda: len(g.live) == 3, 20, "three live depths")
    assert g.depths == [] and g.refiner.online.serving.version == 0
    assert [m.header.stamp.sec for m in g.live] == [stamp_of(t).sec for t in sequence.stamps[:3]]
    assert all((m.encoding, m.width, m.height) == ("32FC1", WIDTH, HEIGHT) for m in g.live)
    before = np.frombuffer(g.live[0].data, np.float32).copy()
    for rgb, t in zip(sequence.images[3:6], sequence.stamps[3:6], strict=True):
        g.send_image(rgb, t)
    wait_for(lambda: len(g.depths) == 6, 120, "the window's refined depths")
    assert g.refiner.stream.last_window.refined
    wait_for(lambda: g.refiner.online.serving.version == 1, 10, "the refined weights served")
    g.send_image(sequence.images[0], sequence.stamps[6])  # the first image again, new stamp
    wait_for(lambda: len(g.live) == 7, 20, "a live depth with the refined weights")
    after = np.frombuffer(g.live[-1].data, np.float32)
    assert not np.allclose(before, after)  # served by the refined network now
    d = wait_for(lambda: (lambda v: v if v.get("live.received") == "7" and
                          v.get("live.pending") == "0" and
                          v.get("serving.version") == "1" else None)(g.last_diag()),
                 10, "live diagnostics")
    assert d["live.published"] == "7" and d["live.skipped"] == "0" and d["live.pending"] == "0"
    assert int(d["serving.updates"]) == 1 and float(d["serving.age_s"]) >= 0
    lat = [float(d[f"live.latency_{k}_s"]) for k in ("p50", "p95", "max")]
    assert 0 < lat[0] <= lat[1] <= lat[2] < 30 and 0 < float(d["live.publish_max_s"]) <= lat[2]


def test_odometry_on_odom_feeds_the_metric_scale(graph_factory):
    """nav_msgs/Odometry on ``odom`` reaches the metric scale's track (metric.source
    odometry); a message out of order is rejected and counted, and /diagnostics says so."""
    from nav_msgs.msg import Odometry

    from msg_adapters.odometry import odometry_msg

    g = graph_factory(**{"metric.source": "odometry"})
    pub = g.node.create_publisher(Odometry, names.ODOMETRY_TOPIC, 10)
    wait_for(lambda: pub.get_subscription_count() > 0, 10, "the odometry subscription")
    for k, stamp_s in enumerate((1, 2, 3, 2)):
        pose = np.eye(4)
        pose[2, 3] = 0.5 * k
        pub.publish(odometry_msg(stamp_s * 10**9, "odom", FRAME_ID, pose))
    track = g.refiner.ttr.odometry
    wait_for(lambda: track.received == 4, 10, "four odometry messages")
    assert len(track) == 3 and track.rejected == 1
    assert np.allclose(track.positions_at([1.5]), [[0.0, 0.0, 0.25]])
    v = g.refiner.diagnostics_values()
    assert (v["metric.source"], v["metric.state"]) == ("odometry", "waiting")
    assert (v["metric.odometry_received"], v["metric.odometry_rejected"]) == (4, 1)
