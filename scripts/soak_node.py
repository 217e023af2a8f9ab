#!/usr/bin/env python3
"""Soak the INSTALLED refiner: a looped generated KITTI-size drive at 10 Hz for
``--minutes`` (30 for the figures in BENCHMARKS.md "Soak") through the node started with
``params/kitti.yaml``, as an outside rclpy client through DDS.

Sampled: the node process's RSS (every ``--rss-period`` s, /proc); per frame, the latency from
publishing the image to receiving its ``~/depth/image`` (live; taken by a listener process of its
own, as a controller would be, unless ``--one-client``) and its ``~/depth_refined/image`` (window)
message; with the RSS, the node's own live latency from /diagnostics (arrival in the node to
published) and the machine's CPU steal, which tell a late depth made in the node from one late in
DDS.
Checks at the end (the issue's criteria; for runs shorter than 30 minutes the
"first / last 5 minutes" are the first / last sixth of the run):

* every frame accounted: /diagnostics ``frames_received`` = frames sent, ``received = refined +
  unrefined + dropped`` and nothing pending after the drain, every frame published on
  ``~/depth_refined/image`` or counted dropped or live-only (``frames_live_only``);
* memory: the peak RSS after the first 5 minutes <= 1.10 x the peak in them (RSS is a
  sawtooth: the allocator gives a window's freed pages back, ros/allocator.py);
* latency: the p95 of ``~/depth_refined/image`` latency over the last 5 minutes within 20 % of the
  first 5 minutes' (and the same reported for the live ``~/depth/image``).

Writes ``soak.json`` (samples, figures, checks) and ``soak.png`` (RSS and latency over time,
drawn with OpenCV) into ``--out``. Exit 0 when every check passes.

    .venv/bin/python scripts/soak_node.py --minutes 30 --out soak_30min   # the full soak
    .venv/bin/python scripts/soak_node.py --minutes 2 --out /tmp/soak     # a short proof run
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shlex
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
#: Seconds per bucket of the report's ``rss_mib.max_per_30s``.
RSS_BUCKET_S = 30.0
sys.path.insert(0, str(REPO))

from sfm_ttr_ros.tools.demo import node_arguments  # noqa: E402
from sfm_ttr_ros.tools.process import rss_mib  # noqa: E402

KITTI_W, KITTI_H = 1242, 375


def cpu_times() -> tuple[float, float]:
    """(steal, total) jiffies of the whole machine (/proc/stat): time the hypervisor gave
    another guest, which no process here can account for."""
    f = [float(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    return (f[7] if len(f) > 7 else 0.0), sum(f[:8])


#: Decimals kept in the report's samples (0.1 ms, 0.0001 MiB): the figures need no more.
SAMPLE_DECIMALS = 4


def rounded(samples: list) -> list:
    """Each sample (a tuple of numbers) with :data:`SAMPLE_DECIMALS` decimals, one line each."""
    return [[round(x, SAMPLE_DECIMALS) if isinstance(x, float) else x for x in row]
            for row in samples]


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def rss_maxima(rss: list[tuple[float, float]], bucket_s: float) -> list[float]:
    """The RSS's maximum in each ``bucket_s`` seconds of the run ((t, MiB) samples): whether
    it keeps growing or has reached its level (docs/decisions.md, "Memory": the peak after frame 100
    is set by the first windows; after them the maxima stay within a few per cent)."""
    out: dict[int, float] = {}
    for t, v in rss:
        k = int(t // bucket_s)
        out[k] = max(out.get(k, v), v)
    return [out[k] for k in sorted(out)]


def draw_plot(path: Path, rss: list[tuple[float, float]], live: list[tuple[float, float]],
              refined: list[tuple[float, float]], title: str,
              node_p95: list[tuple[float, float]] = ()) -> None:
    """Two panels (RSS MiB; latency s of ~/depth/image and ~/depth_refined/image at the client,
    and the node's own live p95 from /diagnostics) over minutes, OpenCV."""
    import cv2

    w, h, m = 1200, 800, 70
    img = np.full((h, w, 3), 255, np.uint8)
    cv2.putText(img, title, (m, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 0, 0), 2)
    t_max = max([t for t, _ in rss + live + refined] + [1.0]) / 60.0
    panels = [("RSS (MiB)", [(rss, (200, 0, 0))], 60, 380),
              ("latency (s): live ~/depth blue, ~/depth_refined red, live p95 in the node green",
               [(live, (255, 120, 0)), (refined, (0, 0, 220)), (list(node_p95), (0, 160, 0))],
               440, 760)]
    for name, series, top, bottom in panels:
        values = [v for s, _ in series for _, v in s if np.isfinite(v)]
        lo, hi = (min(values), max(values)) if values else (0.0, 1.0)
        lo = 0.0 if name.startswith("latency") else lo * 0.95
        hi = hi * 1.05 if hi > lo else lo + 1.0
        cv2.rectangle(img, (m, top), (w - 20, bottom), (0, 0, 0), 1)
        cv2.putText(img, name, (m + 5, top + 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1)
        for frac in (0.0, 0.5, 1.0):
            y = int(bottom - frac * (bottom - top))
            cv2.putText(img, f"{lo + frac * (hi - lo):.1f}", (5, y + 5),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
        for frac in (0.0, 0.25, 0.5, 0.75, 1.0):
            x = int(m + frac * (w - 20 - m))
            cv2.putText(img, f"{frac * t_max:.1f} min", (x - 20, bottom + 18),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
        for samples, colour in series:
            kept = [(t, v) for t, v in samples if np.isfinite(v)]
            pts = [(int(m + (t / 60.0) / t_max * (w - 20 - m)),
                    int(bottom - (v - lo) / (hi - lo) * (bottom - top))) for t, v in kept]
            for i in range(1, len(pts)):  # no line across a gap (frames dropped in between)
                if kept[i][0] - kept[i - 1][0] <= 5.0:
                    cv2.line(img, pts[i - 1], pts[i], colour, 1)
            for p in pts if len(pts) < 400 else []:
                cv2.circle(img, p, 2, colour, -1)
    cv2.imwrite(str(path), img)


def ready_file(live_file: str | Path) -> Path:
    """The file the listener creates once it has matched the node's ``~/depth/image``."""
    return Path(f"{live_file}.ready")


def listen_live(out_path: str, best_effort: bool = False) -> int:
    """A second client process that only takes ``~/depth/image`` (what a controller would run) and
    writes ``[[stamp_ns, received monotonic s], ...]`` to ``out_path`` on SIGINT / SIGTERM.

    One process taking both outputs measures its own queue, not the node: a window releases
    up to ``max_pending`` depth images on ``~/depth_refined/image`` at once (~190 MB at
    1242x375), and the live images arriving behind them in the same client wait until they are
    taken."""
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    from msg_adapters.stamp import stamp_to_ns
    from sfm_ttr_ros.ros import names

    got: list[tuple[int, float]] = []
    rclpy.init()
    node = Node("soak_live_listener")
    qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
    if best_effort:  # sensor-data QoS, as a controller takes a camera-rate stream
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5,
                         reliability=ReliabilityPolicy.BEST_EFFORT)
    # metres on ~/depth/image, the network's units on its relative twin (REP 118)
    sub, _ = [node.create_subscription(Image, topic, lambda m: got.append(
        (stamp_to_ns(m.header.stamp), time.monotonic())), qos)
        for topic in (names.DEPTH_TOPIC_RESOLVED, names.DEPTH_RELATIVE_TOPIC_RESOLVED)]
    ready = ready_file(out_path)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.1)
            if not ready.exists() and sub.get_publisher_count() >= 1:
                ready.touch()  # matched the node's ~/depth: the soak may start
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    Path(out_path).write_text(json.dumps(got))
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


class Client:
    """Publishes the drive, records output latencies and the last diagnostics."""

    def __init__(self, live: bool = True):
        import rclpy  # noqa: F401
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, Image

        from msg_adapters import diagnostic_values
        from msg_adapters.stamp import stamp_to_ns
        from sfm_ttr_ros.ros import names

        self.names, self.diagnostic_values, self.stamp_to_ns = names, diagnostic_values, \
            stamp_to_ns
        self.node = Node("soak_player")
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                         reliability=ReliabilityPolicy.RELIABLE)
        self.pub_image = self.node.create_publisher(Image, names.IMAGE_TOPIC, qos)
        self.pub_info = self.node.create_publisher(CameraInfo, names.CAMERA_INFO_TOPIC, qos)
        # The client keeps every depth it is sent (KEEP_ALL): a sample lost here would be
        # blamed on the node.
        qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
        self.sent_at: dict[int, float] = {}
        self.live: list[tuple[float, float]] = []
        self.refined: list[tuple[float, float]] = []
        self.diag: dict[str, str] = {}
        self.t0 = time.monotonic()
        self._lock = threading.Lock()
        # each output on its metric topic and its relative twin (REP 118)
        outputs = [(names.DEPTH_REFINED_TOPIC_RESOLVED, self.refined)]
        if live:  # else a listener process of its own takes ~/depth (listen_live)
            outputs.append((names.DEPTH_TOPIC_RESOLVED, self.live))
        for topic, sink in outputs:
            for t in (topic, names.relative_twin_of(topic)):
                self.node.create_subscription(
                    Image, t, lambda m, sink=sink: self._on_depth(m, sink), qos)
        self.node.create_subscription(DiagnosticArray, names.DIAGNOSTICS_TOPIC, self._on_diag,
                                      10)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def _on_depth(self, msg, sink: list) -> None:
        now = time.monotonic()
        with self._lock:
            self._record(sink, self.stamp_to_ns(msg.header.stamp), now)

    def add_live(self, received: list) -> None:
        """The listener process's ``[stamp_ns, received]`` pairs, recorded as ``_on_depth``
        records its own."""
        with self._lock:
            for ns, at in received:
                self._record(self.live, int(ns), at)
            self.live.sort()

    def _record(self, sink: list, stamp_ns: int, received: float) -> None:
        """(sent - t0, latency) of the frame stamped ``stamp_ns``, if this client sent it."""
        sent = self.sent_at.get(stamp_ns)
        if sent is not None:
            sink.append((sent - self.t0, received - sent))

    def _on_diag(self, msg) -> None:
        # the node's statuses (stream, scale, live, worker), each key in one: merged
        if any(s.hardware_id == self.names.NODE_FQN for s in msg.status):
            v = self.diagnostic_values(msg, hardware_id=self.names.NODE_FQN)
            with self._lock:
                self.diag = v

    def publish(self, rgb: np.ndarray, intr, stamp_ns: int) -> None:
        from msg_adapters import intrinsics_to_camera_info, make_header, numpy_to_image

        header = make_header(stamp_ns, "camera_color_left")
        self.pub_info.publish(intrinsics_to_camera_info(intr, header))
        msg = numpy_to_image(rgb, "rgb8", header)
        with self._lock:
            self.sent_at[stamp_ns] = time.monotonic()
        self.pub_image.publish(msg)


def run(args: argparse.Namespace) -> dict:
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ["ROS_DOMAIN_ID"] = str(args.domain_id or random.SystemRandom().randint(101, 230))
    import rclpy

    from sfm_ttr_ros.data.synthetic import make_sequence
    from sfm_ttr_ros.tools.process import close_client_and_node

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(f"soak: rendering a {args.drive_frames}-frame {KITTI_W}x{KITTI_H} drive", flush=True)
    seq = make_sequence(seed=args.seed, domain="A", num_frames=args.drive_frames, width=KITTI_W,
                        height=KITTI_H)
    cmd, proc, log_path = _start_node(args, out)
    if not args.clients_default_dds:  # the clients as a camera driver following the README
        from sfm_ttr_ros.ros import dds
        print(f"soak: clients' {dds.apply_profile()}", flush=True)
    listener = None
    live_file = out / "live_received.json"
    if args.split_live:
        live_file.unlink(missing_ok=True)
        ready_file(live_file).unlink(missing_ok=True)
        listener = subprocess.Popen(
            [sys.executable, __file__, "--listen-live", str(live_file)]
            + (["--live-best-effort"] if args.live_best_effort else []), env=os.environ.copy())
    rclpy.init(args=[sys.argv[0]])  # the soak's own flags (-p name:=value) are not ROS arguments
    c = None
    rss: list[tuple[float, float]] = []
    node_live: list[tuple] = []  # (t, node p95, node max, publish max, live skipped, steal)
    sent = 0
    try:
        c = Client(live=not args.split_live)
        deadline = time.monotonic() + 120
        while c.pub_image.get_subscription_count() < 1 or (
                listener is not None and not ready_file(live_file).exists()):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the node did not come up; see {log_path}")
            time.sleep(0.2)
        c.t0 = t0 = time.monotonic()
        print(f"soak: {args.minutes:g} min at {args.rate:g} Hz into {' '.join(cmd)}", flush=True)
        sent = _feed(args, c, proc, seq, rss, node_live)
        # drain
        drain_end = time.monotonic() + args.drain_timeout
        while time.monotonic() < drain_end and proc.poll() is None:
            d = c.diag
            if d.get("frames_pending") == "0" and int(d.get("frames_received", -1)) == sent:
                break
            time.sleep(0.5)
            rss.append((time.monotonic() - t0, rss_mib(proc.pid)))
        time.sleep(2.0)
        alive = proc.poll() is None
        d = dict(c.diag)
        if listener is not None:
            listener.send_signal(signal.SIGINT)
            listener.wait(30)
            c.add_live(json.loads(live_file.read_text()) if live_file.exists() else [])
        live, refined = list(c.live), list(c.refined)
    finally:
        if listener is not None and listener.poll() is None:
            listener.kill()
        close_client_and_node(c, proc, timeout=30)
    return _report(args, out, cmd, sent, alive, proc.returncode, d, rss, live, refined,
                   log_path, node_live)


def _start_node(args: argparse.Namespace, out: Path) -> tuple[list[str], subprocess.Popen, Path]:
    """(the node's command, its process, its log): started in the output folder (the command's
    paths made absolute first)."""
    exe = [str(Path(t).absolute()) if Path(t).exists() else t for t in shlex.split(args.exe)]
    cmd = [*exe, "--ros-args", "--params-file", args.params_file]
    cmd += node_arguments(args.set or [])
    log_path = out / "refiner.log"
    with open(log_path, "w") as log:
        node_env = dict(kv.split("=", 1) for kv in args.node_env or [])
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=out,
                                env={**os.environ, "PYTHONUNBUFFERED": "1", **node_env})
    return cmd, proc, log_path


def _feed(args: argparse.Namespace, c, proc: subprocess.Popen, seq, rss: list, node_live: list
          ) -> int:
    """The looped drive at ``--rate`` for ``--minutes`` (or until the node ends), the node's RSS
    and live figures sampled every ``--rss-period`` s; the frames sent."""
    t0 = c.t0
    cpu = cpu_times()
    duration = args.minutes * 60.0
    period = 1.0 / args.rate
    next_rss = 0.0
    stamp0 = 1_700_000_000 * 10**9
    sent = 0
    while True:
        now = time.monotonic() - t0
        if now >= duration or proc.poll() is not None:
            return sent
        if now >= next_rss:
            rss.append((now, rss_mib(proc.pid)))
            next_rss += args.rss_period
            node_live.append(node_sample(now, c.diag, cpu))
            cpu = cpu_times()
        loop, i = divmod(sent, len(seq.images))
        rgb = seq.images[i]
        if loop:  # a new pixel digest per loop: no prediction is reused across loops
            rgb = rgb.copy()
            rgb[0, 0, 0] = loop % 256
        c.publish(rgb, seq.intrinsics, stamp0 + sent * int(period * 1e9))
        sent += 1
        if sent % int(60 * args.rate) == 0:
            d = c.diag
            print(f"  {now / 60:.1f} min: {sent} sent, RSS {rss[-1][1]:.0f} MiB, "
                  f"{d.get('frames_refined')} refined, {d.get('frames_unrefined')} unrefined, "
                  f"{d.get('frames_dropped')} dropped, {d.get('frames_pending')} pending",
                  flush=True)
        time.sleep(max(0.0, t0 + sent * period - time.monotonic()))


def node_sample(now: float, diag: dict, cpu_before: tuple[float, float]) -> tuple:
    """The node's own live figures (/diagnostics) and the machine's steal share since the last
    sample: with the client's latencies they tell a late frame made in the node from one late on
    the way through DDS or taken by the hypervisor."""
    steal, total = cpu_times()
    share = (steal - cpu_before[0]) / max(total - cpu_before[1], 1.0)

    def num(key):
        try:
            return float(diag.get(key, "nan"))
        except ValueError:
            return float("nan")
    return (now, num("live.latency_p95_s"), num("live.latency_max_s"),
            num("live.publish_max_s"), num("live.skipped"), share)


def _report(args, out, cmd, sent, alive, code, d, rss, live, refined, log_path,
            node_live) -> dict:
    duration = args.minutes * 60.0
    warm = args.warm_s or min(300.0, duration / 6.0)  # "the first 5 minutes" (a sixth of a
    # shorter run); --warm-s 10 = the memory target's "after frame 100" at 10 Hz

    def num(key):
        return int(d.get(key, 0))

    # "peak RSS growth after the first 5 minutes": the peak after them against the peak in them.
    # Since the allocator gives a window's freed pages back (ros/allocator.py) RSS is a
    # sawtooth (the window's working set, then back), so the value AT minute 5 is a point
    # anywhere on it.
    rss_at_warm = next((v for t, v in rss if t >= warm), float("nan"))
    peak_warm = max((v for t, v in rss if t < warm), default=float("nan"))
    peak_after = max((v for t, v in rss if t >= warm), default=float("nan"))
    first = [lat for t, lat in refined if t < warm]
    last = [lat for t, lat in refined if t >= duration - warm]
    live_first = [lat for t, lat in live if t < warm]
    live_last = [lat for t, lat in live if t >= duration - warm]
    p95 = {"refined_first": percentile(first, 95), "refined_last": percentile(last, 95),
           "live_first": percentile(live_first, 95), "live_last": percentile(live_last, 95)}
    dropped = num("frames_dropped")
    checks = {
        "alive": alive,
        "every_frame_received": num("frames_received") == sent,
        "accounting_adds_up": num("frames_received") == num("frames_refined")
        + num("frames_unrefined") + dropped + num("frames_pending"),
        "nothing_pending": num("frames_pending") == 0,
        # live-only frames: unrefined, already on ~/depth, not sent again (republish_unrefined)
        "every_frame_back_or_counted": len(refined) + dropped + num("frames_live_only") == sent,
        "rss_growth_le_10pct": peak_after <= 1.10 * peak_warm,
        "latency_p95_within_20pct": abs(p95["refined_last"] - p95["refined_first"])
        <= 0.20 * p95["refined_first"],
        "no_traceback": "Traceback" not in log_path.read_text(errors="replace"),
        "clean_exit": code == 0,
    }
    report = {
        "command": " ".join(cmd), "node_env": args.node_env or [], "minutes": args.minutes,
        "rate_hz": args.rate,
        "frames_sent": sent, "depth_refined_back": len(refined), "depth_live_back": len(live),
        "warm_up_s": warm, "rss_mib": {"at_warm_up": rss_at_warm, "peak_in_warm_up": peak_warm,
                                       "peak_after_warm_up": peak_after,
                                       "final": rss[-1][1] if rss else None,
                                       "max_per_30s": rss_maxima(rss, RSS_BUCKET_S)},
        "latency_p95_s": p95,
        "latency_median_s": {"refined": percentile([lat for _, lat in refined], 50),
                             "live": percentile([lat for _, lat in live], 50)},
        "diagnostics": d, "checks": checks, "ok": all(checks.values()), "exit_code": code,
        "node_live": _node_live_summary(node_live),
        "samples": {k: rounded(v) for k, v in (("rss", rss), ("live", live),
                                               ("refined", refined), ("node_live", node_live))},
        "log": str(log_path),
    }
    (out / "soak.json").write_text(json.dumps(report, indent=1, default=str))
    draw_plot(out / "soak.png", rss, live, refined,
              f"refiner soak: {args.minutes:g} min at {args.rate:g} Hz, params/kitti.yaml, "
              f"{KITTI_W}x{KITTI_H}", [(x[0], x[1]) for x in node_live])
    return report


def _node_live_summary(samples: list[tuple]) -> dict:
    """Over the run: the largest node-side live p95 / max / publish time seen in a sample, the
    machine's mean and largest steal share."""
    if not samples:
        return {}
    a = np.asarray([x[1:] for x in samples], dtype=float)
    return {"node_latency_p95_max_s": float(np.nanmax(a[:, 0])),
            "node_latency_max_s": float(np.nanmax(a[:, 1])),
            "publish_max_s": float(np.nanmax(a[:, 2])),
            "steal_mean": float(np.nanmean(a[:, 4])), "steal_max": float(np.nanmax(a[:, 4]))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=30.0)
    ap.add_argument("--rate", type=float, default=10.0, help="frames per second")
    ap.add_argument("--out", default="soak_out", help="folder for soak.json, soak.png, the log")
    ap.add_argument("--exe", default=str(Path(sys.executable).parent / "refiner"),
                    help="the node's command (split like a shell line)")
    ap.add_argument("--params-file", default=str(REPO / "params" / "kitti.yaml"))
    ap.add_argument("--set", dest="set", action="append", metavar="NAME=VALUE",
                    help="a node parameter over --params-file, as in sfm-ttr (repeatable)")
    ap.add_argument("--drive-frames", type=int, default=30, help="length of the looped drive")
    ap.add_argument("--rss-period", type=float, default=2.0)
    ap.add_argument("--drain-timeout", type=float, default=600.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--domain-id", type=int, default=0)
    ap.add_argument("--one-client", dest="split_live", action="store_false",
                    help="take ~/depth in the same client process as ~/depth_refined (default: "
                         "a listener process of its own, as a controller would be)")
    ap.add_argument("--warm-s", type=float, default=0.0,
                    help="the warm-up the RSS and latency checks start after (default: 5 min, "
                         "a sixth of a shorter run)")
    ap.add_argument("--clients-default-dds", action="store_true",
                    help="the sending client and the listener keep Fast DDS's defaults (else "
                         "they take the node's large-image profile, as the README advises a "
                         "camera driver to)")
    ap.add_argument("--node-env", action="append", metavar="NAME=VALUE",
                    help="an environment variable for the node's process only")
    ap.add_argument("--live-best-effort", action="store_true",
                    help="the ~/depth listener subscribes BEST_EFFORT (sensor-data QoS): a "
                         "lost sample is lost, none holds the later ones back")
    ap.add_argument("--listen-live", metavar="FILE", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.listen_live:
        return listen_live(args.listen_live, args.live_best_effort)
    r = run(args)
    print(f"soak: {r['frames_sent']} frames in {r['minutes']:g} min; back on ~/depth_refined "
          f"{r['depth_refined_back']}, live {r['depth_live_back']}; RSS MiB {r['rss_mib']}; "
          f"latency p95 s {r['latency_p95_s']}; median {r['latency_median_s']}; in the node "
          f"{r['node_live']}")
    d = r["diagnostics"]
    print("  " + ", ".join(f"{k} {d.get(k)}" for k in (
        "frames_received", "frames_refined", "frames_unrefined", "frames_dropped",
        "frames_pending", "windows_ok", "windows_failed", "windows_skipped_overload")))
    for name, ok in r["checks"].items():
        print(f"  [{'ok' if ok else 'FAIL'}] {name}")
    print(f"  {Path(args.out) / 'soak.json'}, {Path(args.out) / 'soak.png'}")
    print("PASS" if r["ok"] else "FAIL")
    return 0 if r["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
