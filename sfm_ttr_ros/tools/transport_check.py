"""Count what the transport delivers: real-size frames from a plain rclpy publisher into the
refiner with its DEFAULT settings, as a ROS user plugs in a camera.

Starts the refiner (``python -m sfm_ttr_ros.ros.node --accounting FILE``, no parameter file;
``--set`` adds parameters), then, as an outside client on a private ROS_DOMAIN_ID on localhost,
publishes ``--frames`` 1242x375 rgb8 images (KITTI's size; textured noise, a new image each
frame) and their CameraInfo at each ``--rate`` with ``create_publisher(Image, topic, 10)``:
ROS's default QoS (reliable, KEEP_LAST 10), no profile of ours on the client's side. Then the
node is stopped and its final accounting read: ``frames_received`` against the frames
published. Exit 0 when every rate delivered every frame.

    python -m sfm_ttr_ros.tools.transport_check --frames 30 --rate 10 --rate 20
    python -m sfm_ttr_ros.tools.transport_check --set qos_reliability=best_effort
"""

from __future__ import annotations

import argparse
import json
import os
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from sfm_ttr_ros.tools.demo import node_arguments

#: This package's root folder: the node started here is this checkout's.
REPO = Path(__file__).resolve().parents[2]

WIDTH, HEIGHT = 1242, 375
#: KITTI 2011_09_26's rectified left colour camera (P_rect_02): fx, fy, cx, cy.
KITTI_K = (721.5377, 721.5377, 609.5593, 172.854)
START_TIMEOUT_S = 120.0
#: Seconds the node gets after the last frame before it is stopped (its executor takes the
#: messages at once; the accounting counts a frame when its callback ran).
SETTLE_S = 3.0


def make_frames(n: int, seed: int = 0):
    """``n`` distinct 1242x375 rgb8 images (a noise texture shifted a little every frame)."""
    import numpy as np

    base = np.random.default_rng(seed).integers(0, 255, (HEIGHT, WIDTH + 8 * n, 3), np.uint8)
    return [np.ascontiguousarray(base[:, 8 * i:8 * i + WIDTH]) for i in range(n)]


def _messages(node, images, stamp_ns: int):
    """(Image, CameraInfo) with the same header."""
    from sensor_msgs.msg import CameraInfo, Image

    img = Image(height=HEIGHT, width=WIDTH, encoding="rgb8", is_bigendian=0, step=3 * WIDTH)
    img.header.stamp.sec, img.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    img.header.frame_id = "camera"
    img.data = images.tobytes()
    fx, fy, cx, cy = KITTI_K
    info = CameraInfo(height=HEIGHT, width=WIDTH, distortion_model="plumb_bob")
    info.header = img.header
    info.k = [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]
    info.p = [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    return img, info


def publish(images, rate_hz: float, namespace: str = "") -> int:
    """Publish ``images`` at ``rate_hz`` from a plain client (ROS's default QoS, depth 10)
    once the node's image subscription is seen; returns how many were published."""
    import rclpy
    from sensor_msgs.msg import CameraInfo, Image

    node = rclpy.create_node("camera_driver", namespace=namespace or None)
    try:
        pub = node.create_publisher(Image, "image", 10)
        pub_info = node.create_publisher(CameraInfo, "camera_info", 10)
        deadline = time.monotonic() + START_TIMEOUT_S
        while pub.get_subscription_count() < 1 or pub_info.get_subscription_count() < 1:
            if time.monotonic() > deadline:
                raise RuntimeError("the refiner's subscriptions never appeared")
            time.sleep(0.1)
        time.sleep(0.5)  # discovery both ways
        period, t0 = 1.0 / rate_hz, time.monotonic()
        for i, im in enumerate(images):
            img, info = _messages(node, im, 1_000_000_000 + int(i * period * 1e9))
            pub_info.publish(info)
            pub.publish(img)
            time.sleep(max(0.0, t0 + (i + 1) * period - time.monotonic()))
        time.sleep(SETTLE_S)
        return len(images)
    finally:
        node.destroy_node()


def measure(rate_hz: float, n: int, overrides: list[str], log_dir: Path) -> dict:
    """One run: a fresh node, ``n`` frames at ``rate_hz``; published and received."""
    import rclpy

    from sfm_ttr_ros.ros.accounting import ACCOUNTING_ARG, read_accounting
    from sfm_ttr_ros.tools.process import interrupt

    acc = log_dir / f"accounting_{rate_hz:g}hz.json"
    log_path = log_dir / f"refiner_{rate_hz:g}hz.log"
    cmd = [sys.executable, "-m", "sfm_ttr_ros.ros.node", ACCOUNTING_ARG, str(acc),
           "--ros-args", "--log-level", "warn", *node_arguments(overrides)]
    with open(log_path, "w") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=log_dir,
                                env={**os.environ, "PYTHONUNBUFFERED": "1",
                                     "PYTHONPATH": os.pathsep.join(filter(None, (
                                         str(REPO), os.environ.get("PYTHONPATH"))))})
    rclpy.init()
    try:
        published = publish(make_frames(n), rate_hz)
    finally:
        rclpy.try_shutdown()
        code = interrupt(proc, 30.0)
    values = read_accounting(acc) or {}
    return {"rate_hz": rate_hz, "published": published,
            "received": values.get("frames_received"), "exit_code": code,
            "qos_incompatible": {k: v for k, v in values.items() if "qos" in k},
            "log": str(log_path)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--rate", type=float, action="append", help="Hz (repeat; default 10, 20)")
    ap.add_argument("--set", dest="set", action="append", default=[], metavar="NAME=VALUE",
                    help="a node parameter (default: none, the node's defaults)")
    ap.add_argument("--log-dir", default=None)
    ap.add_argument("--json", default=None, help="write the figures here")
    args = ap.parse_args(argv)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.SystemRandom().randint(101, 230)))
    log_dir = Path(args.log_dir or tempfile.mkdtemp(prefix="transport_check_"))
    log_dir.mkdir(parents=True, exist_ok=True)
    runs = [measure(rate, args.frames, args.set, log_dir) for rate in args.rate or [10.0, 20.0]]
    for r in runs:
        print(f"{r['rate_hz']:g} Hz: {r['received']}/{r['published']} received "
              f"(exit {r['exit_code']}; {r['log']})")
    if args.json:
        Path(args.json).write_text(json.dumps(runs, indent=1))
    return 0 if all(r["received"] == r["published"] for r in runs) else 1


if __name__ == "__main__":
    sys.exit(main())
