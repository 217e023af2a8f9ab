"""The ``refiner`` ROS 2 node: SfM-TTR on a live image stream (thin glue over the core).

Threads: the executor (main thread) runs the subscription callbacks, the parameter services and
the diagnostics timer; callbacks only convert the message (``msg_adapters``) and queue the frame
in :class:`~sfm_ttr_ros.core.stream.StreamProcessor`. One worker thread runs the stream (SfM, model,
refinement) and publishes its outputs, so the executor never blocks on heavy work.

Topics (names remappable): subscribes ``image`` (sensor_msgs/Image: rgb8, bgr8, mono8, rgba8,
bgra8, mono16, ...) and ``camera_info``; publishes ``~/depth`` (32FC1, NaN = invalid, the input
image's header), ``~/depth_colored`` (bgr8), ``~/points`` (PointCloud2 x, y, z,
reprojection_error in the optical frame of the window's newest registered image, with that
image's header; units = the depth's units) and ``/diagnostics``.

Intrinsics: the CameraInfo with the image's stamp, else the latest one; without any CameraInfo
the fallback parameters fx, fy (cx, cy; 0 = image centre); with neither, frames are held
(bounded by ``max_pending``, oldest dropped and counted) with a throttled warning, and processed
once intrinsics are known.

Shutdown (SIGINT / SIGTERM / external shutdown): the worker is cancelled (``SfmTTR.cancel``:
refinement stops at the next step, pycolmap through its cancellation token) and joined, the
refined encoder is saved when ``save_weights_path`` is set, then the executor is shut down, the
node destroyed and rclpy shut down: exit code 0. Pending frames are NOT flushed on shutdown (it
must be fast); their number is logged. A network forward pass cannot be interrupted: when the
worker is still inside one after ``STOP_TIMEOUT_S``, the process leaves with ``os._exit`` once ROS
is shut down (a thread in torch C++ code at interpreter finalisation would abort it), without
saving the weights.
"""

from __future__ import annotations

import collections
import os
import signal
import sys
import threading
import time
from functools import partial
from pathlib import Path

import rclpy
import torch
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import SetParametersResult
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import CameraInfo, Image, PointCloud2

from msg_adapters import (
    camera_info_to_intrinsics,
    depth_to_colored_image,
    depth_to_image,
    image_to_rgb8,
    make_diagnostic_array,
    numpy_to_pointcloud2,
)
from sfm_ttr_ros.core.frames import Frame, InputError, Intrinsics
from sfm_ttr_ros.core.models.base import DepthModel
from sfm_ttr_ros.core.models.registry import build_model
from sfm_ttr_ros.core.pipeline import SfmTTR
from sfm_ttr_ros.core.stream import FrameOutput, StreamProcessor, WindowStats
from sfm_ttr_ros.ros import params as node_params

NODE_NAME = "refiner"
DIAG_NAME = "sfm_ttr_ros: refiner"
WARN_PERIOD_S = 5.0
STOP_TIMEOUT_S = 3.0  # how long shutdown waits for the worker to finish its current step


def _stamp_key(stamp) -> tuple[int, int]:
    return int(stamp.sec), int(stamp.nanosec)


class RefinerNode(Node):
    """The refiner node. ``model`` (tests, embedding) replaces the one the parameters describe;
    other keyword arguments go to :class:`rclpy.node.Node` (context, parameter_overrides,
    cli_args, namespace)."""

    def __init__(self, *, model: DepthModel | None = None, node_name: str = NODE_NAME,
                 **kwargs):
        super().__init__(node_name, **kwargs)
        try:
            self._setup(model)
        except BaseException:
            super().destroy_node()  # no half-built node left in the graph
            raise

    def _setup(self, model: DepthModel | None) -> None:
        node_params.declare(self)
        values = node_params.current_values(self)
        reason = node_params.validate(values)
        if reason:
            raise InputError(f"invalid parameters: {reason}")
        self.add_on_set_parameters_callback(self._validate_parameters)
        nv = node_params.node_values(values)

        if nv["torch_num_threads"] > 0:
            torch.set_num_threads(int(nv["torch_num_threads"]))
        if model is None:
            model = build_model(node_params.build_model_config(values))
        if nv["load_weights_path"]:
            self._load_encoder(model, nv["load_weights_path"])
        self.ttr = SfmTTR(model, node_params.build_ttr_config(values))
        self.stream = StreamProcessor(
            self.ttr, node_params.build_stream_settings(values),
            config_provider=lambda: node_params.build_ttr_config(self._values()),
            settings_provider=lambda: node_params.build_stream_settings(self._values()),
            on_output=self._publish_output, on_window=self._on_window,
            logger=self.get_logger())

        # counters of things that are not frames (frames are counted by the stream)
        self.qos_incompatible = collections.Counter()
        self.rejected_camera_info = 0
        self._cam_latest: Intrinsics | None = None
        self._cam_by_stamp: collections.OrderedDict = collections.OrderedDict()
        self._held: collections.deque[Frame] = collections.deque()
        self._unrefined_since_diag = 0
        self._diag_lock = threading.Lock()
        self._closed = False
        self._stop = threading.Event()

        reliability = (ReliabilityPolicy.BEST_EFFORT if nv["qos_reliability"] == "best_effort"
                       else ReliabilityPolicy.RELIABLE)
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(nv["qos_depth"]),
                         reliability=reliability)
        overrides = QoSOverridingOptions.with_default_policies()
        self.create_subscription(
            Image, "image", self._on_image, qos, qos_overriding_options=overrides,
            event_callbacks=SubscriptionEventCallbacks(
                incompatible_qos=partial(self._on_incompatible_qos, "image")))
        self.create_subscription(
            CameraInfo, "camera_info", self._on_camera_info, qos,
            qos_overriding_options=overrides,
            event_callbacks=SubscriptionEventCallbacks(
                incompatible_qos=partial(self._on_incompatible_qos, "camera_info")))
        out_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(nv["qos_depth"]),
                             reliability=ReliabilityPolicy.RELIABLE)

        def pub(msg_type, topic, depth_qos=out_qos):
            return self.create_publisher(
                msg_type, topic, depth_qos, event_callbacks=PublisherEventCallbacks(
                    incompatible_qos=partial(self._on_incompatible_qos, topic)))

        self.pub_depth = pub(Image, "~/depth")
        self.pub_colored = pub(Image, "~/depth_colored")
        self.pub_points = pub(PointCloud2, "~/points")
        self.pub_diag = pub(DiagnosticArray, "/diagnostics", 10)
        self.create_timer(float(nv["diagnostics_period_s"]), self._on_timer)

        self._worker = threading.Thread(target=self._work, name="refiner-worker", daemon=True)
        self._worker.start()
        self.get_logger().info(
            f"refiner ready: model {type(model).__name__} (input {model.input_size}), window "
            f"{values['window_size']}/{values['window_stride']}, refinement "
            f"{values['refinement.steps']} steps, reset_each_window="
            f"{values['reset_each_window']}, QoS {nv['qos_reliability']} depth {nv['qos_depth']}")

    # -- parameters ------------------------------------------------------------------------------
    def _values(self) -> dict:
        return node_params.current_values(self)

    def _param(self, name: str):
        return self.get_parameter(name).value

    def _validate_parameters(self, params) -> SetParametersResult:
        values = self._values()
        values.update({p.name: p.value for p in params})
        try:
            reason = node_params.validate(values)
            if not reason:
                self.ttr.check_config(node_params.build_ttr_config(values))
        except InputError as exc:  # e.g. frozen encoder levels on a model without stages
            reason = str(exc)
        except Exception as exc:  # a value no check foresaw: refuse it, with the reason
            reason = f"{type(exc).__name__}: {exc}"
        return SetParametersResult(successful=not reason, reason=reason)

    @staticmethod
    def _load_encoder(model: DepthModel, path: str) -> None:
        if not Path(path).is_file():
            raise InputError(f"load_weights_path: file not found: {path}")
        try:
            state = torch.load(path, map_location=model.device, weights_only=True)
            model.encoder.load_state_dict(state)
        except Exception as exc:
            raise InputError(f"load_weights_path: cannot load encoder weights from {path}: "
                             f"{type(exc).__name__}: {exc}") from exc

    # -- callbacks (executor thread: convert and queue only) ---------------------------------
    def _on_image(self, msg: Image) -> None:
        try:
            rgb = image_to_rgb8(msg)
        except InputError as exc:
            self.stream.reject("bad_image", f"image rejected: {exc}")
            return
        stamp = msg.header.stamp
        frame = Frame(index=self.stream.counters()["received"] + len(self._held), image=rgb,
                      stamp=stamp.sec + stamp.nanosec * 1e-9, header=msg.header)
        self._held.append(frame)
        self._release_held()
        max_pending = int(self._param("max_pending"))
        while len(self._held) > max_pending:
            old = self._held.popleft()
            self.stream.reject("no_intrinsics", "no intrinsics (no CameraInfo, fallback fx/fy "
                               f"unset): held frame dropped (max_pending={max_pending})", old)
        if self._held:
            self.get_logger().warning(
                f"{len(self._held)} frame(s) held: no intrinsics yet - waiting for a CameraInfo "
                f"on {self.resolve_topic_name('camera_info')} or set the fallback parameters "
                "fx and fy", throttle_duration_sec=WARN_PERIOD_S)

    def _on_camera_info(self, msg: CameraInfo) -> None:
        try:
            use_p = node_params.parse_use_projection(self._param("camera_info_use_projection"))
            intr = camera_info_to_intrinsics(msg, use_p)
        except InputError as exc:
            self.rejected_camera_info += 1
            self.get_logger().warning(f"CameraInfo rejected: {exc}",
                                      throttle_duration_sec=WARN_PERIOD_S)
            return
        self._cam_latest = intr
        self._cam_by_stamp[_stamp_key(msg.header.stamp)] = intr
        while len(self._cam_by_stamp) > 64:
            self._cam_by_stamp.popitem(last=False)
        self._release_held()

    def _intrinsics_for(self, frame: Frame) -> Intrinsics | None:
        if frame.header is not None:
            intr = self._cam_by_stamp.get(_stamp_key(frame.header.stamp))
            if intr is not None:
                return intr
        if self._cam_latest is not None:
            return self._cam_latest
        fx, fy = float(self._param("fx")), float(self._param("fy"))
        if fx > 0 and fy > 0:
            w, h = frame.size
            cx = float(self._param("cx")) or (w - 1) / 2.0
            cy = float(self._param("cy")) or (h - 1) / 2.0
            return Intrinsics(fx, fy, cx, cy, w, h)
        return None

    def _release_held(self) -> None:
        """Queue the held frames, oldest first, as long as intrinsics are known for them."""
        while self._held:
            intr = self._intrinsics_for(self._held[0])
            if intr is None:
                return
            self.stream.submit(self._held.popleft(), intr)

    def _on_incompatible_qos(self, what: str, event) -> None:
        self.qos_incompatible[what] += 1
        policy = getattr(event, "last_policy_kind", "?")
        self.get_logger().warning(
            f"incompatible QoS on {what} (policy {policy}, {event.total_count} so far): "
            "check the other side's reliability/durability (qos_reliability parameter)",
            throttle_duration_sec=WARN_PERIOD_S)

    def _on_timer(self) -> None:
        self._release_held()  # the fallback intrinsics may have been set meanwhile
        self.publish_diagnostics()

    # -- worker thread -------------------------------------------------------------------------
    def _work(self) -> None:
        while not self._stop.is_set():
            try:
                self.stream.step(timeout=0.1)
            except Exception as exc:  # never let the worker die
                if self._stop.is_set():
                    break
                self.get_logger().error(f"worker: {type(exc).__name__}: {exc}",
                                        throttle_duration_sec=WARN_PERIOD_S)
                time.sleep(0.1)

    def _publish_output(self, out: FrameOutput) -> None:
        if self._stop.is_set():
            return
        header = out.frame.header
        self.pub_depth.publish(depth_to_image(out.depth, header))
        if self._param("publish_colored"):
            self.pub_colored.publish(depth_to_colored_image(out.depth, header))
        if not out.refined:
            with self._diag_lock:
                self._unrefined_since_diag += 1

    def _on_window(self, stats: WindowStats) -> None:
        if self._stop.is_set():
            return
        if (self._param("publish_points") and stats.cloud_frame is not None
                and stats.cloud_xyz.shape[0]):
            self.pub_points.publish(numpy_to_pointcloud2(
                stats.cloud_xyz, stats.cloud_frame.header,
                {"reprojection_error": stats.cloud_error}))
        self.publish_diagnostics()

    # -- diagnostics ---------------------------------------------------------------------------
    def diagnostics_values(self) -> dict[str, object]:
        c = self.stream.counters()
        held = len(self._held)
        v: dict[str, object] = {
            "frames_received": c["received"] + held,
            "frames_refined": c["refined"],
            "frames_unrefined": c["unrefined"],
            "frames_dropped": c["dropped"],
            "frames_pending": c["pending"] + held,
            "frames_held_no_intrinsics": held,
        }
        v.update({f"unrefined.{k}": n for k, n in sorted(c["unrefined_by_reason"].items())})
        v.update({f"dropped.{k}": n for k, n in sorted(c["dropped_by_reason"].items())})
        v.update({
            "rejected_bad_image": c["dropped_by_reason"].get("bad_image", 0),
            "rejected_camera_info": self.rejected_camera_info,
            "non_monotonic_stamps": c["non_monotonic_stamps"],
            "qos_incompatible": sum(self.qos_incompatible.values()),
            "windows_ok": c["windows_ok"],
            "windows_failed": c["windows_failed"],
            "windows_skipped_overload": c["windows_skipped"],
            "windows_disabled": c["windows_disabled"],
        })
        w = self.stream.last_window
        if w is not None:
            v.update({
                "last_window.index": w.index,
                "last_window.frames": len(w.names),
                "last_window.refined": w.refined,
                "last_window.reason": w.reason,
                "last_window.registered_frames": w.registered,
                "last_window.points_3d": w.points,
                "last_window.inlier_ratio": w.inlier_ratio,
                "last_window.scale": w.scale,
                "last_window.loss_before": w.loss_before,
                "last_window.loss_after": w.loss_after,
                "last_window.steps": w.steps,
                "last_window.steps_done": w.steps_done,
            })
            v.update({f"last_window.time.{k}_s": t for k, t in w.timings.items()})
        return v

    def publish_diagnostics(self) -> None:
        if self._stop.is_set() or not self._param("publish_diagnostics"):
            return
        with self._diag_lock:
            v = self.diagnostics_values()
            w = self.stream.last_window
            problems = []
            if self._unrefined_since_diag:
                problems.append(f"{self._unrefined_since_diag} frame(s) passed through unrefined")
            if w is not None and not w.refined:
                problems.append(f"last window not refined: {w.reason}")
            if v["frames_held_no_intrinsics"]:
                problems.append("no intrinsics: frames held")
            if v["qos_incompatible"]:
                problems.append("incompatible QoS")
            self._unrefined_since_diag = 0
            level = "warn" if problems else "ok"
            message = "; ".join(problems) if problems else (
                f"{v['frames_refined']} refined, {v['windows_ok']} window(s) ok")
            try:
                self.pub_diag.publish(make_diagnostic_array(
                    self.get_clock().now(), DIAG_NAME, self.get_fully_qualified_name(), level,
                    message, v))
            except Exception as exc:  # context shut down under us
                if not self._stop.is_set():
                    raise
                del exc

    # -- shutdown ------------------------------------------------------------------------------
    def stop_worker(self, timeout: float = 5.0) -> None:
        """Cancel the running window, join the worker, save the weights (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        self.stream.cancel()
        self._worker.join(timeout)
        if self._worker.is_alive():
            self.get_logger().warning(
                f"worker did not stop within {timeout:g} s (busy in an uninterruptible network "
                "call); not waiting for it")
        c = self.stream.counters()
        pending = c["pending"] + len(self._held)
        self.get_logger().info(
            f"stopped: {c['received'] + len(self._held)} received, {c['refined']} refined, "
            f"{c['unrefined']} unrefined, {c['dropped']} dropped, {pending} pending not "
            "published (no flush on shutdown)")
        if self._worker.is_alive():
            return  # the model and the SfM workspace are still in use: leave them alone
        path = self._param("save_weights_path")
        if path:
            try:
                Path(path).parent.mkdir(parents=True, exist_ok=True)
                torch.save(self.ttr.model.encoder.state_dict(), path)
                self.get_logger().info(f"refined encoder saved to {path}")
            except Exception as exc:
                self.get_logger().error(f"cannot save the encoder to {path}: {exc}")
        self.ttr.close()

    @property
    def worker_alive(self) -> bool:
        return self._worker.is_alive()

    def destroy_node(self) -> None:
        self.stop_worker()
        super().destroy_node()


def main(args=None) -> int:
    """Entry point of ``ros2 run sfm_ttr_ros refiner``."""
    # Our own signal handling: SIGINT/SIGTERM raise KeyboardInterrupt in the main thread, so the
    # worker is stopped BEFORE the context goes down (the executor spins with a timeout).
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)

    def _interrupt(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGINT, _interrupt)
    signal.signal(signal.SIGTERM, _interrupt)
    node = None
    executor = None
    code = 0
    try:
        node = RefinerNode()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while rclpy.ok():
            executor.spin_once(timeout_sec=0.2)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (InputError, ParameterException) as exc:  # bad parameters / model: no traceback
        get_logger(NODE_NAME).fatal(f"cannot start: {type(exc).__name__}: {exc}")
        code = 1
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        if node is not None:
            node.stop_worker(timeout=STOP_TIMEOUT_S)
        stuck = node is not None and node.worker_alive
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    if stuck:
        # A thread inside torch / pycolmap C++ code at interpreter finalisation aborts the
        # process (exit 134): leave at once instead, everything ROS is already shut down.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


if __name__ == "__main__":
    sys.exit(main())
