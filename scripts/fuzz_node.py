#!/usr/bin/env python3
"""Fuzz the INSTALLED refiner node through DDS: no single message may stop it.

Starts ``refiner`` (the installed console script, default ``<venv>/bin/refiner``) as a
subprocess with ``params/kitti.yaml`` (its fallback_intrinsics set: the case that once ended
the process) plus a few overrides that make windows cheap, then, as an outside rclpy client on
a private ROS_DOMAIN_ID, sends ``--messages`` hostile and valid messages:

* images the node must drop as ``bad_image``: unknown, empty, unicode and wrong-case encodings
  (``RGB8``, ``MONO8``), 32FC1, truncated and over-long data, a step below the row size, zero
  and huge declared sizes;
* images it must take (every one comes back on ``~/depth_refined/image`` or is counted as dropped or
  live-only, ``frames_live_only``):
  every supported encoding, padded rows, big- and little-endian 16 bit, blank / noise / static
  frames, tiny (1x1) and extreme-aspect (1x600, 2000x2) images, frames smaller than the fallback
  principal point before any CameraInfo (and after a live one at cx 5000), duplicate / backwards /
  absurd stamps, unicode frame ids, mid-stream resolution and intrinsics changes, real windows
  (a 320x96 synthetic drive with its CameraInfo) and a burst far above ``max_pending``;
* CameraInfos: zeros, NaN, inf, negative focal, zero size, absurd ROI and binning, tiny and
  huge focal lengths;
* invalid parameter sets (through the parameter services, like ``ros2 param set``), each of
  which must be refused with a reason, and a few valid ones that must be accepted.

Then it waits for the drain and checks: the process is alive; exact accounting from the last
/diagnostics (every image received, ``received = refined + unrefined + dropped``, nothing
pending); ``dropped.bad_image`` = the bad images sent; every valid frame back on
``~/depth_refined/image`` or counted dropped or live-only; ``rejected_camera_info`` = the bad
CameraInfos; no contained fault (in the last /diagnostics and in the final accounting the node
writes as it stops, ``--accounting``: any place, the worker's included) and no frame pending
at the end; no ``Traceback`` in the node's log; RSS bounded (final
<= 2 x the RSS after the first phase + 200 MiB); every invalid parameter set refused with a
reason. Exit 0 when every check passes, 1 otherwise; ``--json`` writes the figures.

    .venv/bin/python scripts/fuzz_node.py                  # full size: >= 1000 messages
    .venv/bin/python scripts/fuzz_node.py --messages 300   # CI size (tests/test_fuzz.py)
"""

from __future__ import annotations

import argparse
import array
import json
import math
import os
import random
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # msg_adapters / sfm_ttr_ros from this checkout (the client side)

from sfm_ttr_ros.ros.accounting import ACCOUNTING_ARG, read_accounting  # noqa: E402
from sfm_ttr_ros.tools.demo import node_arguments  # noqa: E402
from sfm_ttr_ros.tools.process import rss_mib  # noqa: E402

# the node under test: cheap windows on top of params/kitti.yaml, a deep input history so DDS
# itself never drops a message (every image sent must be counted by the node)
LIGHT = ["refinement.steps=2", "window_size=4", "window_stride=4", "sfm.max_image_size=320",
         "sfm.max_num_features=1024", "min_supervision_points=10", "idle_flush_s=1.0",
         "qos_depth=2000", "max_pending=40", "overload_pending=12",
         "diagnostics_period_s=0.5", "outputs=depth,depth_refined,diagnostics"]
PAD = 3


class Fuzzer:
    """The outside client: publishers, the recorder of outputs and diagnostics, the script."""

    def __init__(self, n_messages: int, seed: int):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.parameter_client import AsyncParameterClient
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, Image

        from msg_adapters import diagnostic_values
        from sfm_ttr_ros.ros import names

        self.rclpy, self.names = rclpy, names
        self.Image, self.CameraInfo = Image, CameraInfo
        self.diagnostic_values = diagnostic_values
        self.rng = random.Random(seed)
        self.n = n_messages
        self.node = Node("fuzzer")
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=2000,
                         reliability=ReliabilityPolicy.RELIABLE)
        self.pub_image = self.node.create_publisher(Image, names.IMAGE_TOPIC, qos)
        self.pub_info = self.node.create_publisher(CameraInfo, names.CAMERA_INFO_TOPIC, qos)
        self.refined_back = 0
        self.live_back = 0
        self.diag: dict[str, str] = {}
        self._lock = threading.Lock()
        # each output on its metric topic and its relative twin (REP 118)
        for topic, callback in ((names.DEPTH_REFINED_TOPIC_RESOLVED, self._on_refined),
                                (names.DEPTH_TOPIC_RESOLVED, self._on_live)):
            for t in (topic, names.relative_twin_of(topic)):
                self.node.create_subscription(Image, t, callback, qos)
        from diagnostic_msgs.msg import DiagnosticArray
        self.node.create_subscription(DiagnosticArray, names.DIAGNOSTICS_TOPIC, self._on_diag,
                                      10)
        self.params = AsyncParameterClient(self.node, names.NODE_NAME)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        # what was sent
        self.images = self.bad_images = self.valid_images = 0
        self.infos = self.bad_infos = 0
        self.kinds: dict[str, int] = {}
        self.param_sets: list[dict] = []
        self.t_ns = 1_600_000_000 * 10**9
        self.last_stamp_ns = self.t_ns

    # -- sinks ---------------------------------------------------------------------------------
    def _on_refined(self, msg) -> None:
        with self._lock:
            self.refined_back += 1

    def _on_live(self, msg) -> None:
        with self._lock:
            self.live_back += 1

    def _on_diag(self, msg) -> None:
        # the node's statuses (stream, scale, live, worker), each key in one: merged
        if any(s.hardware_id == self.names.NODE_FQN for s in msg.status):
            v = self.diagnostic_values(msg, hardware_id=self.names.NODE_FQN)
            with self._lock:
                self.diag = v

    def last_diag(self) -> dict[str, str]:
        with self._lock:
            return dict(self.diag)

    def wait_drained(self, timeout: float) -> bool:
        """Wait until the node reports every image sent so far received and none pending."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            d = self.last_diag()
            if d.get("frames_pending") == "0" and int(d.get("frames_received", -1)) == \
                    self.images:
                return True
            time.sleep(0.2)
        return False

    @property
    def sent(self) -> int:
        return self.images + self.infos

    # -- messages ------------------------------------------------------------------------------
    def _stamp(self, kind: str):
        from builtin_interfaces.msg import Time

        if kind == "duplicate":
            ns = self.last_stamp_ns
        elif kind == "backwards":
            ns = max(0, self.t_ns - 50 * 10**9)
        elif kind == "absurd":
            ns = self.rng.choice([0, (2**31 - 1) * 10**9 + 999_999_999, 1])
        else:
            self.t_ns += 100_000_000
            ns = self.t_ns
        self.last_stamp_ns = ns
        return Time(sec=ns // 10**9, nanosec=ns % 10**9)

    def image(self, kind: str, width: int, height: int, encoding: str, data: bytes, step: int,
              *, valid: bool, big: int = 0, stamp: str = "next", frame_id: str = "cam") -> None:
        msg = self.Image(width=width, height=height, encoding=encoding, step=step,
                         is_bigendian=big)
        msg.header.stamp = self._stamp(stamp)
        msg.header.frame_id = frame_id
        msg.data = array.array("B", data)
        self.pub_image.publish(msg)
        self.images += 1
        self.valid_images += valid
        self.bad_images += not valid
        self.kinds[kind] = self.kinds.get(kind, 0) + 1

    def rgb(self, kind: str, a, encoding: str = "rgb8", **kw) -> None:
        """A valid image of array ``a`` (H x W x C or H x W) in ``encoding``."""
        import numpy as np

        from msg_adapters import numpy_to_image

        msg = numpy_to_image(np.ascontiguousarray(a), encoding)
        self.image(kind, msg.width, msg.height, encoding, bytes(msg.data), msg.step, valid=True,
                   **kw)

    def info(self, kind: str, width: int, height: int, k, p=None, *, binning=(0, 0),
             roi=(0, 0, 0, 0)) -> None:
        from msg_adapters import UncalibratedCameraInfo, camera_info_to_intrinsics

        msg = self.CameraInfo(width=width, height=height)
        msg.header.stamp = self._stamp("next")
        msg.header.frame_id = "cam"
        msg.k = [float(v) for v in k]
        msg.p = [float(v) for v in (p if p is not None else [k[0], k[1], k[2], 0.0, k[3], k[4],
                                                              k[5], 0.0, k[6], k[7], k[8], 0.0])]
        msg.binning_x, msg.binning_y = binning
        msg.roi.x_offset, msg.roi.y_offset, msg.roi.width, msg.roi.height = roi
        try:  # the node reads P (kitti.yaml: camera_info_use_projection true)
            camera_info_to_intrinsics(msg, True)
        except UncalibratedCameraInfo:
            pass  # K all zero: the node assumes intrinsics (docs/node.md, "Intrinsics")
        except ValueError:
            self.bad_infos += 1
        self.pub_info.publish(msg)
        self.infos += 1
        self.kinds[kind] = self.kinds.get(kind, 0) + 1

    # -- parameters ----------------------------------------------------------------------------
    def set_param(self, name: str, value, expect_ok: bool) -> None:
        from rclpy.parameter import Parameter

        try:
            param = Parameter(name, value=value)
        except Exception as exc:  # e.g. a value rclpy cannot even carry
            self.param_sets.append({"name": name, "value": repr(value), "ok": False,
                                    "expected_ok": expect_ok, "reason": f"client: {exc}"})
            return
        future = self.params.set_parameters([param])
        deadline = time.monotonic() + 20
        while not future.done() and time.monotonic() < deadline:
            time.sleep(0.01)
        if not future.done():
            self.param_sets.append({"name": name, "value": repr(value), "ok": None,
                                    "expected_ok": expect_ok, "reason": "no answer"})
            return
        r = future.result().results[0]
        self.param_sets.append({"name": name, "value": repr(value), "ok": r.successful,
                                "expected_ok": expect_ok, "reason": r.reason})


def hostile_images(f: Fuzzer, count: int) -> None:
    """``count`` images drawn from the hostile and odd-but-valid kinds."""
    import numpy as np

    rng = f.rng
    npr = np.random.default_rng(rng.randrange(2**32))
    small = (160, 48)

    def noise(w, h, c=3, dtype=np.uint8):
        hi = 255 if dtype == np.uint8 else 65535
        shape = (h, w, c) if c > 1 else (h, w)
        return npr.integers(0, hi, shape, dtype=dtype)

    static = noise(*small)
    kinds = [
        "bad_encoding", "wrong_case", "float_image", "truncated", "over_long", "short_step",
        "zero_size", "huge_declared", "ok_encodings", "padded", "mono16_endian", "blank",
        "noise", "static", "tiny", "extreme_aspect", "duplicate_stamp", "backwards_stamp",
        "absurd_stamp", "unicode_frame_id"]
    for _ in range(count):
        kind = rng.choice(kinds)
        w, h = small
        good = noise(w, h)
        raw = good.tobytes()
        if kind == "bad_encoding":
            enc = rng.choice(["yuv422", "bayer_rggb8", "16SC1", "", "rgb8✓", "ЯGB8", "8UC2",
                              "64FC1", "rgb16", "jpeg"])
            f.image(kind, w, h, enc, raw, w * 3, valid=False)
        elif kind == "wrong_case":
            enc = rng.choice(["RGB8", "MONO8", "Bgr8", "BGRA8", "8uc3", "Mono16"])
            f.image(kind, w, h, enc, raw, w * 3, valid=False)
        elif kind == "float_image":
            f.image(kind, w, h, "32FC1", noise(w, h, 1).astype(np.float32).tobytes(), w * 4,
                    valid=False)
        elif kind == "truncated":
            f.image(kind, w, h, "rgb8", raw[:rng.randrange(len(raw))], w * 3, valid=False)
        elif kind == "over_long":
            f.image(kind, w, h, "rgb8", raw + bytes(rng.randrange(1, 5000)), w * 3,
                    valid=False)
        elif kind == "short_step":
            f.image(kind, w, h, "rgb8", raw, rng.randrange(0, w * 3), valid=False)
        elif kind == "zero_size":
            zw, zh = rng.choice([(0, 0), (0, h), (w, 0)])
            f.image(kind, zw, zh, "rgb8", b"", zw * 3, valid=False)
        elif kind == "huge_declared":
            hw, hh = rng.choice([(2**31, 2), (100_000, 100_000), (2**32 - 1, 2**32 - 1)])
            f.image(kind, hw, hh, "rgb8", raw[:300], (hw * 3) % 2**32, valid=False)
        elif kind == "ok_encodings":
            enc = rng.choice(["rgb8", "bgr8", "rgba8", "bgra8", "mono8", "8UC1", "8UC3",
                              "mono16", "16UC1"])
            c = {"rgba8": 4, "bgra8": 4, "mono8": 1, "8UC1": 1, "mono16": 1, "16UC1": 1}.get(
                enc, 3)
            dtype = np.uint16 if enc in ("mono16", "16UC1") else np.uint8
            f.rgb(kind, noise(w, h, c, dtype), enc)
        elif kind == "padded":
            rows = np.pad(good.reshape(h, w * 3), ((0, 0), (0, PAD)))
            f.image(kind, w, h, "rgb8", rows.tobytes(), w * 3 + PAD, valid=True)
        elif kind == "mono16_endian":
            a = noise(w, h, 1, np.uint16)
            big = rng.random() < 0.5
            f.image(kind, w, h, "mono16", a.astype(">u2" if big else "<u2").tobytes(), w * 2,
                    valid=True, big=int(big))
        elif kind == "blank":
            f.rgb(kind, np.full((h, w, 3), rng.choice([0, 255]), np.uint8))
        elif kind == "noise":
            f.rgb(kind, good)
        elif kind == "static":
            f.rgb(kind, static)
        elif kind == "tiny":
            tw, th = rng.choice([(1, 1), (2, 2), (3, 1), (1, 3), (8, 8)])
            f.rgb(kind, noise(tw, th))
        elif kind == "extreme_aspect":
            ew, eh = rng.choice([(1, 600), (600, 1), (2000, 2), (3, 900)])
            f.rgb(kind, noise(ew, eh))
        elif kind in ("duplicate_stamp", "backwards_stamp", "absurd_stamp"):
            f.rgb(kind, good, stamp=kind.split("_")[0])
        elif kind == "unicode_frame_id":
            f.rgb(kind, good, frame_id=rng.choice(["カメラ", "cam/🙂", "", "a" * 300, "\u200b"]))
        time.sleep(0.02)


def camera_infos(f: Fuzzer, count: int) -> None:
    """``count`` CameraInfos (hostile and valid), each followed by a frame of its size."""
    import numpy as np

    rng = f.rng
    nan, inf = float("nan"), float("inf")
    for _ in range(count):
        w, h = rng.choice([(160, 48), (320, 96), (100, 50)])
        fx, cx, cy = 200.0, (w - 1) / 2, (h - 1) / 2
        k = [fx, 0, cx, 0, fx, cy, 0, 0, 1]
        kind = rng.choice(["zeros", "nan", "inf", "negative_focal", "zero_size", "absurd_roi",
                           "absurd_binning", "tiny_focal", "huge_focal", "valid", "valid_other"])
        if kind == "zeros":
            f.info(kind, w, h, [0.0] * 9, [0.0] * 12)
        elif kind == "nan":
            f.info(kind, w, h, [fx, 0, nan, 0, fx, cy, 0, 0, 1])
        elif kind == "inf":
            f.info(kind, w, h, [inf, 0, cx, 0, fx, cy, 0, 0, 1])
        elif kind == "negative_focal":
            f.info(kind, w, h, [-fx, 0, cx, 0, fx, cy, 0, 0, 1])
        elif kind == "zero_size":
            f.info(kind, 0, rng.choice([0, h]), k)
        elif kind == "absurd_roi":
            f.info(kind, w, h, k, roi=(rng.choice([2**32 - 1, 10_000]), 5, 2**31, 7))
        elif kind == "absurd_binning":
            f.info(kind, w, h, k, binning=(rng.choice([2**32 - 1, 1000]), 2))
        elif kind == "tiny_focal":
            f.info(kind, w, h, [1e-9, 0, cx, 0, 1e-9, cy, 0, 0, 1])
        elif kind == "huge_focal":
            f.info(kind, w, h, [1e12, 0, cx, 0, 1e12, cy, 0, 0, 1])
        elif kind == "valid_other":  # intrinsics change mid-stream
            f.info(kind, w, h, [fx * 1.5, 0, cx, 0, fx * 1.5, cy, 0, 0, 1])
        else:
            f.info(kind, w, h, k)
        time.sleep(0.01)
        f.rgb("after_" + kind, np.random.default_rng(rng.randrange(2**32)).integers(
            0, 255, (h, w, 3), dtype=np.uint8))
        time.sleep(0.01)


def real_windows(f: Fuzzer, frames: int) -> None:
    """A synthetic 320x96 drive with its CameraInfo: windows that really run SfM-TTR."""
    from msg_adapters import intrinsics_to_camera_info
    from sfm_ttr_ros.data.synthetic import make_sequence

    seq = make_sequence(seed=f.rng.randrange(1000), domain="A", num_frames=frames, width=320,
                        height=96)
    for rgb in seq.images:
        info = intrinsics_to_camera_info(seq.intrinsics)
        info.header.stamp = f._stamp("next")
        f.pub_info.publish(info)
        f.infos += 1
        f.kinds["drive_info"] = f.kinds.get("drive_info", 0) + 1
        f.rgb("drive", rgb, stamp="duplicate")  # the image takes the CameraInfo's stamp
        time.sleep(0.1)


def invalid_parameter_sets() -> list[tuple[str, object]]:
    nan, inf = float("nan"), float("inf")
    return [
        ("window_size", 1), ("window_size", 0), ("window_size", -3), ("window_size", 10**9),
        ("window_size", 2.5), ("window_size", "ten"), ("window_stride", -1),
        ("window_stride", 100), ("window_stride", 10**9), ("refinement.lr", 0.0),
        ("refinement.lr", -1e-4), ("refinement.lr", nan), ("refinement.lr", inf),
        ("refinement.lr", 1), ("refinement.lr", 2.0), ("refinement.steps", -1),
        ("refinement.steps", 10**12), ("refinement.bn_mode", "banana"),
        ("refinement.bn_mode", ""), ("refinement.weighting", "all"),
        ("refinement.frozen_encoder_levels", 9), ("refinement.frozen_encoder_levels", -1),
        ("sfm.max_image_size", 1),
        ("sfm.max_image_size", -7), ("sfm.init_min_tri_angle", 0.0),
        ("sfm.init_min_tri_angle", -1.0), ("sfm.max_num_features", 0), ("sfm.num_threads", 0),
        ("sfm.overlap", 0), ("sfm.first_octave", -2), ("sfm.mapping_attempts", 0),
        ("alignment.tau", 0.0),
        ("alignment.tau", -1.0), ("alignment.tau", float("nan")),
        ("min_supervision_points", 0), ("fallback_intrinsics", "-1 1 0 0"),
        ("fallback_intrinsics", "nan 1 0 0"), ("fallback_intrinsics", "700 0 1 1"),
        ("fallback_intrinsics", "700 700 -5 1"), ("fallback_intrinsics", "700 700 1 inf"),
        ("fallback_intrinsics", 700.0), ("outputs", "depth,everything"),
        ("check.holdout_fraction", 0.2), ("fx", "700"), ("camera_info_use_projection", "maybe"),
        ("camera_info_use_projection", 3), ("model_type", "mobilenet"), ("device", "cuda:7"),
        ("qos_depth", 5), ("image_transport", "compressed"), ("max_pending", 5),
        ("diagnostics_period_s", 0.1), ("min_keyframe_motion", 300.0),
        ("idle_flush_s", -1.0), ("overload_pending", -1), ("seed", -1),
        ("no_such_parameter", 1), ("refinement.lr", "1e-4"), ("publish_points", "yes"),
    ]


def run(args: argparse.Namespace) -> dict:
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ["ROS_DOMAIN_ID"] = str(args.domain_id or random.SystemRandom().randint(101, 230))
    import rclpy

    from sfm_ttr_ros.tools.process import close_client_and_node

    log_dir = Path(args.log_dir or tempfile.mkdtemp(prefix="fuzz_node_"))
    log_dir.mkdir(parents=True, exist_ok=True)
    log_path = log_dir / "refiner.log"
    accounting_path = log_dir / "accounting.json"  # the node's own, written as it stops
    cmd = [args.exe, ACCOUNTING_ARG, str(accounting_path), "--ros-args", "--params-file",
           args.params_file]
    cmd += node_arguments([*LIGHT, *(args.set or [])])
    t0 = time.monotonic()
    with open(log_path, "w") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=log_dir,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
    rclpy.init()
    f = None
    report: dict = {"command": " ".join(cmd), "log": str(log_path)}
    rss = []
    try:
        f = Fuzzer(args.messages, args.seed)
        deadline = time.monotonic() + 120
        while (f.pub_image.get_subscription_count() < 1
               or not f.params.wait_for_services(timeout_sec=0.5)):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the node did not come up (exit {proc.poll()}); see "
                                   f"{log_path}")
            time.sleep(0.2)
        report["start_s"] = time.monotonic() - t0

        def sample() -> float:
            rss.append((time.monotonic() - t0, rss_mib(proc.pid)))
            return rss[-1][1]

        rss_first = _send_all(f, args, sample)
        report["send_s"] = time.monotonic() - t0
        _drain(f, proc, args.drain_timeout, sample)
        alive = proc.poll() is None
        d = f.last_diag()
        report.update(_checks(f, d, alive, rss, rss_first, log_path))
    finally:
        close_client_and_node(f, proc, timeout=30)
        report["exit_code"] = proc.returncode
        report["seconds"] = time.monotonic() - t0
    text = log_path.read_text(errors="replace")
    report["tracebacks"] = text.count("Traceback")
    report["checks"]["no_traceback"] = report["tracebacks"] == 0
    report["checks"]["clean_exit"] = report["exit_code"] == 0
    report.update(_final_checks(read_accounting(accounting_path), report["checks"]))
    report["ok"] = all(report["checks"].values())
    return report


def _send_all(f: Fuzzer, args: argparse.Namespace, sample) -> float:
    """The script: frames before any CameraInfo, invalid parameter sets, hostile images and
    CameraInfos, real windows, a burst; ``sample()`` the node's RSS between the parts. Returns
    the RSS (MiB) after the first part."""
    import numpy as np

    npr = np.random.default_rng(args.seed)
    # 1. before any CameraInfo: frames smaller than kitti.yaml's fallback principal point
    for w, h in [(416, 128), (100, 50), (160, 48), (1242, 100), (300, 375)] * 2:
        f.rgb("fallback_pp_outside", npr.integers(0, 255, (h, w, 3), dtype=np.uint8))
        time.sleep(0.02)
    f.set_param("fallback_intrinsics", "721.5377 721.5377 5000 172.854", True)
    for _ in range(3):
        f.rgb("live_cx_5000", npr.integers(0, 255, (375, 1242, 3), dtype=np.uint8))
        time.sleep(0.02)
    f.set_param("fallback_intrinsics", "721.5377 721.5377 609.5593 172.854", True)
    rss_first = sample()
    # 2. invalid parameter sets (and two valid ones)
    for name, value in invalid_parameter_sets():
        f.set_param(name, value, False)
    f.set_param("refinement.steps", 3, True)
    f.set_param("window_stride", 2, True)
    sample()
    _send_hostile(f, args.messages, npr, sample)
    return rss_first


def _send_hostile(f: Fuzzer, n: int, npr, sample) -> None:
    """3. hostile images, CameraInfos, real windows, a burst (``n`` messages in all)."""
    import numpy as np

    budget = max(0, n - f.sent)
    n_burst = max(10, budget * 15 // 100)
    n_infos = max(10, budget * 12 // 100)
    n_drive = 16
    n_hostile = max(0, budget - n_burst - 2 * n_infos - 2 * n_drive)
    for chunk in range(4):
        hostile_images(f, n_hostile // 4 + (n_hostile % 4 if chunk == 3 else 0))
        sample()
        camera_infos(f, n_infos // 4 + (n_infos % 4 if chunk == 3 else 0))
        sample()
    f.wait_drained(60.0)  # the windows below get a queue of their own
    real_windows(f, n_drive)
    f.wait_drained(120.0)
    sample()
    burst = npr.integers(0, 255, (48, 160, 3), dtype=np.uint8)
    for i in range(n_burst):  # far above max_pending (40), no pause
        f.rgb("burst", np.roll(burst, i, axis=1))
    sample()


def _drain(f: Fuzzer, proc: subprocess.Popen, timeout: float, sample) -> None:
    """4. drain: everything received and nothing pending, then one more status."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        d = f.last_diag()
        if (d.get("frames_pending") == "0"
                and int(d.get("frames_received", -1)) == f.images
                and f.refined_back >= int(d.get("frames_refined", 0))
                + int(d.get("frames_unrefined", 0)) - int(d.get("frames_live_only", 0))):
            break
        time.sleep(0.5)
        sample()
    time.sleep(2.0)
    sample()


def _checks(f: Fuzzer, d: dict[str, str], alive: bool, rss, rss_first, log_path) -> dict:
    def num(key: str) -> int:
        return int(d.get(key, 0))

    dropped_valid = num("frames_dropped") - num("dropped.bad_image")
    peak = max(r for _, r in rss if not math.isnan(r)) if rss else float("nan")
    final = rss[-1][1] if rss else float("nan")
    refused = [p for p in f.param_sets if not p["expected_ok"]]
    accepted = [p for p in f.param_sets if p["expected_ok"]]
    checks = {
        "alive": alive,
        "diagnostics_seen": bool(d),
        "every_image_received": num("frames_received") == f.images,
        "accounting_adds_up": num("frames_received") == num("frames_refined")
        + num("frames_unrefined") + num("frames_dropped") + num("frames_pending"),
        "nothing_pending": num("frames_pending") == 0,
        "bad_images_counted": num("dropped.bad_image") == f.bad_images,
        "every_valid_frame_back_or_counted":
            f.valid_images == f.refined_back + dropped_valid + num("frames_live_only")
            and f.refined_back == num("frames_refined") + num("frames_unrefined")
            - num("frames_live_only"),
        "bad_camera_infos_counted": num("rejected_camera_info") == f.bad_infos,
        "no_fault": num("faults") == 0,
        "memory_bounded": final <= 2 * rss_first + 200,
        "invalid_parameters_refused_with_reasons": all(
            p["ok"] is False and p["reason"] for p in refused),
        "valid_parameters_accepted": all(p["ok"] for p in accepted),
    }
    return {
        "checks": checks,
        "messages_sent": f.sent, "images": f.images, "bad_images": f.bad_images,
        "valid_images": f.valid_images, "camera_infos": f.infos, "bad_camera_infos": f.bad_infos,
        "depth_refined_back": f.refined_back, "depth_live_back": f.live_back,
        "parameter_sets": len(f.param_sets), "parameter_sets_refused": sum(
            p["ok"] is False for p in f.param_sets),
        "kinds": dict(sorted(f.kinds.items())),
        "rss_mib": {"after_first_phase": rss_first, "peak": peak, "final": final},
        "diagnostics": d,
        "refused_examples": [f"{p['name']}={p['value']}: {p['reason']}" for p in refused[:6]],
        "wrong_answers": [p for p in f.param_sets if p["ok"] is not p["expected_ok"]],
        "log": str(log_path),
    }


def _final_checks(final: dict | None, checks: dict) -> dict:
    """The node's final accounting (``--accounting``, ros/accounting.py), as it stopped: no
    fault contained in the whole run (any place, the worker's included: a fault the last
    /diagnostics did not see yet counts too) and no frame pending, held or in the worker's
    hands; ``checks`` gets both."""
    final = final or {}
    faults = {k: v for k, v in final.items() if k.startswith("faults.") and v}
    checks["final_accounting_written"] = bool(final)
    checks["no_fault_in_the_run"] = bool(final) and final.get("faults") == 0
    checks["nothing_pending_at_the_end"] = bool(final) and final.get("frames_pending") == 0
    return {"final_accounting": final, "faults_by_place": faults}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--messages", type=int, default=1000,
                    help="messages to send (images + CameraInfos; default 1000)")
    ap.add_argument("--exe", default=str(Path(sys.executable).parent / "refiner"),
                    help="the installed refiner (default: the one next to this Python)")
    ap.add_argument("--params-file", default=str(REPO / "params" / "kitti.yaml"))
    ap.add_argument("--set", dest="set", action="append", metavar="NAME=VALUE",
                    help="extra node parameter (after the light overrides)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--domain-id", type=int, default=0, help="ROS_DOMAIN_ID (0 = random)")
    ap.add_argument("--drain-timeout", type=float, default=300.0)
    ap.add_argument("--log-dir", default=None, help="where the node's log goes (default tmp)")
    ap.add_argument("--json", default=None, help="write the report here")
    args = ap.parse_args(argv)
    if args.messages < 100:
        ap.error("--messages must be >= 100")
    report = run(args)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2, default=str))
    c = report["checks"]
    print(f"fuzz_node: {report.get('messages_sent')} messages ({report.get('images')} images: "
          f"{report.get('bad_images')} bad, {report.get('valid_images')} valid; "
          f"{report.get('camera_infos')} CameraInfos, {report.get('bad_camera_infos')} bad), "
          f"{report.get('parameter_sets')} parameter sets "
          f"({report.get('parameter_sets_refused')} refused) in {report['seconds']:.0f} s")
    print(f"  back on ~/depth_refined: {report.get('depth_refined_back')}, live ~/depth: "
          f"{report.get('depth_live_back')}; RSS MiB {report.get('rss_mib')}")
    print(f"  exit code {report['exit_code']}, tracebacks {report['tracebacks']}; log "
          f"{report['log']}")
    for name, ok in c.items():
        print(f"  [{'ok' if ok else 'FAIL'}] {name}")
    if report.get("wrong_answers"):
        print(f"  parameter answers not as expected: {report['wrong_answers']}")
    print("PASS" if report["ok"] else "FAIL")
    return 0 if report["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
