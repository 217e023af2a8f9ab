"""The ``refiner`` ROS 2 node: SfM-TTR on a live image stream (thin glue over the core).

Threads: the executor (main thread) runs the subscription callbacks, the parameter services and
the diagnostics timer; callbacks only convert the message (``msg_adapters``) and hand the frame
to :class:`~sfm_ttr_ros.core.stream.refiner.StreamRefiner`: its live server thread answers
``~/depth`` at once, its worker thread runs the windows (SfM, model, refinement) and publishes their
outputs, so the executor never blocks on heavy work.

Topics (names remappable): subscribes ``image`` (sensor_msgs/Image: rgb8, bgr8, mono8, rgba8,
bgra8, mono16, ...; with ``image_transport: compressed`` sensor_msgs/CompressedImage JPEG / PNG
on ``<image>/compressed`` instead) and ``camera_info``; publishes, each depth image with a
CameraInfo of the same header beside it (image_transport's camera publisher: ``<base>/image``
+ ``<base>/camera_info``), ``~/depth/image`` (32FC1, NaN = invalid, the input image's header:
EVERY frame at once, predicted by the serving copy of the network with the newest refined
weights), ``~/depth_colored/image`` (bgr8, the same), ``~/cloud`` (on request: the live depth
back-projected, PointCloud2 x, y, z, rgb), ``~/depth_refined/image`` (32FC1: every frame again
once its window is done, refined or unrefined with a reason; a frame no window refined that the
live output already carried is not predicted and sent again unless ``republish_unrefined``:
counted in ``frames_live_only``), ``~/points`` (PointCloud2 x, y, z, reprojection_error in the
optical frame of the window's newest registered image, with that image's header; units = the
depth's units) and ``/diagnostics``. Threads: the live server (core/stream/live.py) predicts
and publishes the live outputs; the worker (core/stream/refiner.py, at a lower OS priority)
runs the windows.

CameraInfo beside a depth image: the one received for its frame (exact stamp, else the latest),
republished with the image's header; for a frame on the fallback intrinsics one built from them.
The live output looks it up when it publishes (it needs no intrinsics to predict): before any
CameraInfo or fallback its depth goes out without one, counted (``live.without_camera_info``)
and logged, and ``~/cloud`` is not published for it.

Topic and node names: :mod:`sfm_ttr_ros.ros.names`; the messages: :mod:`sfm_ttr_ros.ros.outputs`.

Intrinsics (:class:`~sfm_ttr_ros.ros.camera.IntrinsicsResolver`): the CameraInfo with the
image's stamp, else the latest one; without any CameraInfo the fallback parameters fx, fy (cx,
cy; 0 = image centre); with neither, frames are held (bounded by ``max_pending``, oldest dropped
and counted) with a throttled warning, and processed once intrinsics are known. Diagnostics:
:class:`~sfm_ttr_ros.core.stream.diagnostics.StreamDiagnostics`.

Containment: no single message, parameter or fault can end the process. Every callback the
executor runs (subscriptions, QoS events, the timer, the parameter check) and the worker's loop
and publications are wrapped (:func:`contained`): an exception no check foresaw is counted
(``faults.<place>`` on /diagnostics, WARN status), logged once per ``WARN_PERIOD_S`` per place
with its type, message and where it was raised, and the node goes on; a frame it concerned is
still accounted for (``dropped.bad_image`` when its message could not be read). A parameter
change whose check raises is refused with the reason.

Exit codes: 0 after a normal shutdown; 1 when the node cannot START (bad parameters, a missing
or corrupt model / weights file, a pycolmap or torch older than the floors of
:mod:`sfm_ttr_ros.requirements`: one ``cannot start: ...`` line, before spinning); 2 for a
fault of the run itself that escaped the containment (``run-time fault: ...``; none is known).

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

import functools
import os
import re
import signal
import sys
import threading
import traceback
from functools import partial
from pathlib import Path

import rclpy
import torch
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2

from msg_adapters import camera_info_to_intrinsics, compressed_to_rgb8, image_to_rgb8
from msg_adapters.odometry import odometry_to_position
from msg_adapters.stamp import stamp_to_ns, stamp_to_seconds
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Frame
from sfm_ttr_ros.core.models.base import DepthModel
from sfm_ttr_ros.core.models.registry import build_model
from sfm_ttr_ros.core.outcomes import Dropped, Unrefined
from sfm_ttr_ros.core.params.node import LIVE_OUTPUTS
from sfm_ttr_ros.core.pipeline import SfmTTR
from sfm_ttr_ros.core.stream.diagnostics import StreamDiagnostics
from sfm_ttr_ros.core.stream.live import LiveOutput
from sfm_ttr_ros.core.stream.refiner import StreamRefiner
from sfm_ttr_ros.core.stream.throttle import WARN_PERIOD_S, Throttle
from sfm_ttr_ros.core.stream.windows import FrameOutput, WindowStats
from sfm_ttr_ros.requirements import check_sfm_dependencies
from sfm_ttr_ros.ros import allocator, dds, names, outputs
from sfm_ttr_ros.ros import params as node_params
from sfm_ttr_ros.ros.camera import (
    NO_INTRINSICS,
    CameraSource,
    FallbackIntrinsics,
    IntrinsicsResolver,
    Resolved,
)

STOP_TIMEOUT_S = 3.0  # how long shutdown waits for the worker to finish its current step
EXIT_START_UP = 1  # the node could not start (parameters, model, weights)
EXIT_RUN_TIME = 2  # a fault escaped the containment while running


def where(exc: BaseException) -> str:
    """``file:line in function`` where ``exc`` was raised (its innermost frame), for a one-line
    log without a traceback."""
    frames = traceback.extract_tb(exc.__traceback__)
    if not frames:
        return "?"
    f = frames[-1]
    return f"{Path(f.filename).name}:{f.lineno} in {f.name}"


def contained(place: str):
    """Decorator of a :class:`RefinerNode` callback: an exception is counted as a fault of
    ``place`` and logged (throttled) instead of reaching the executor or the worker."""
    def wrap(method):
        @functools.wraps(method)
        def call(self, *args):
            try:
                return method(self, *args)
            except Exception as exc:
                self.fault(place, exc)
                return None
        return call
    return wrap


class RefinerNode(Node):
    """The refiner node. ``model`` (tests, embedding) replaces the one the parameters describe;
    other keyword arguments go to :class:`rclpy.node.Node` (context, parameter_overrides,
    cli_args, namespace).

    ``intrinsics`` (:class:`~sfm_ttr_ros.ros.camera.IntrinsicsResolver`) decides each frame's
    intrinsics and holds the frames that have none; ``diagnostics``
    (:class:`~sfm_ttr_ros.core.stream.diagnostics.StreamDiagnostics`) counts and builds the status;
    :mod:`sfm_ttr_ros.ros.outputs` builds the messages."""

    def __init__(self, *, model: DepthModel | None = None, node_name: str = names.NODE_NAME,
                 **kwargs):
        super().__init__(node_name, **kwargs)
        try:
            self._setup(model)
        except BaseException:
            super().destroy_node()  # no half-built node left in the graph
            raise

    def _setup(self, model: DepthModel | None) -> None:
        check_sfm_dependencies()  # a pycolmap too old for SfM: "cannot start", not bad windows
        node_params.declare(self)
        values = node_params.current_values(self)
        reason = node_params.validate(values)
        if reason:
            raise InputError(f"invalid parameters: {reason}")
        settings = node_params.build_settings(values)
        for warning in settings.warnings:
            self.get_logger().warning(warning)
        # every setting, rebuilt once per parameter change (not per frame or window); the
        # stream and the window read theirs from it, the node its own (self.settings)
        self._all = settings
        self.settings = settings.node
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._parameters_set)

        if self.settings.torch_num_threads > 0:
            torch.set_num_threads(int(self.settings.torch_num_threads))
        if model is None:
            model = build_model(settings.model)
        if self.settings.load_weights_path:
            self._load_encoder(model, self.settings.load_weights_path)
        self.ttr = SfmTTR(model, settings.ttr)
        self.online = StreamRefiner(
            self.ttr, settings.stream,
            config_provider=lambda: self._all.ttr,
            settings_provider=lambda: self._all.stream,
            on_live=self._publish_live, on_refined=self._publish_output,
            on_window=self._on_window, on_fault=self.fault, logger=self.get_logger())
        self.stream = self.online.stream
        self.intrinsics = IntrinsicsResolver(self._fallback_intrinsics,
                                             max_held=int(settings.stream.max_pending))
        self.diagnostics = StreamDiagnostics(self.stream, held=lambda: self.intrinsics.held,
                                             live=self.online.counters_live)
        self._diag_lock = threading.Lock()  # one status published at a time, in order
        self._closed = False
        self._stop = threading.Event()
        self._throttle = Throttle()  # of warn_every, per key

        node = self.settings
        reliability = (ReliabilityPolicy.BEST_EFFORT if node.qos_reliability == "best_effort"
                       else ReliabilityPolicy.RELIABLE)
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(node.qos_depth),
                         reliability=reliability)
        overrides = QoSOverridingOptions.with_default_policies()
        image_input = (Image, names.IMAGE_TOPIC, self._on_image)
        if node.image_transport == "compressed":  # image_transport: <resolved image>/compressed
            image_input = (CompressedImage, names.compressed_topic(
                self.resolve_topic_name(names.IMAGE_TOPIC)), self._on_compressed_image)
        self.image_topic = self.resolve_topic_name(image_input[1])
        self._create_publishers(int(node.qos_depth))
        self.create_timer(float(node.diagnostics_period_s), self._on_timer)

        self.online.start()  # warm-up paid: only now subscribe, so no frame waits for it
        for msg_type, topic, callback in (image_input, (CameraInfo, names.CAMERA_INFO_TOPIC,
                                                        self._on_camera_info),
                                          (Odometry, names.ODOMETRY_TOPIC, self._on_odometry)):
            self.create_subscription(
                msg_type, topic, callback, qos, qos_overriding_options=overrides,
                event_callbacks=SubscriptionEventCallbacks(
                    incompatible_qos=partial(self._on_incompatible_qos, topic)))
        self.get_logger().info(
            f"refiner ready: model {type(model).__name__} (input {model.input_size}), window "
            f"{values['window_size']}/{values['window_stride']}, refinement "
            f"{values['refinement.steps']} steps, weight_policy "
            f"{values['weight_policy']}, input {self.image_topic} ({node.image_transport}), "
            f"QoS {node.qos_reliability} depth {node.qos_depth}")

    def _create_publishers(self, qos_depth: int) -> None:
        """Every output's publisher (KEEP_LAST ``qos_depth``, reliable; /diagnostics depth 10),
        each image's CameraInfo beside it; ``_publishers_by_topic`` maps the outputs' topics."""
        out_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=qos_depth,
                             reliability=ReliabilityPolicy.RELIABLE)

        def pub(msg_type, topic, depth_qos=out_qos):
            return self.create_publisher(
                msg_type, topic, depth_qos, event_callbacks=PublisherEventCallbacks(
                    incompatible_qos=partial(self._on_incompatible_qos, topic)))

        self.pub_depth = pub(Image, names.DEPTH_TOPIC)
        self.pub_colored = pub(Image, names.DEPTH_COLORED_TOPIC)
        self.pub_refined = pub(Image, names.DEPTH_REFINED_TOPIC)
        self.pub_points = pub(PointCloud2, names.POINTS_TOPIC)
        self.pub_cloud = pub(PointCloud2, names.CLOUD_TOPIC)
        self.pub_diag = pub(DiagnosticArray, names.DIAGNOSTICS_TOPIC, 10)
        self._publishers_by_topic = {
            names.DEPTH_TOPIC: self.pub_depth, names.DEPTH_COLORED_TOPIC: self.pub_colored,
            names.DEPTH_REFINED_TOPIC: self.pub_refined, names.POINTS_TOPIC: self.pub_points,
            names.CLOUD_TOPIC: self.pub_cloud,
            **{topic: pub(CameraInfo, topic) for topic in (
                names.DEPTH_INFO_TOPIC, names.DEPTH_COLORED_INFO_TOPIC,
                names.DEPTH_REFINED_INFO_TOPIC)}}

    # -- parameters ------------------------------------------------------------------------------
    def _values(self) -> dict:
        return node_params.current_values(self)

    def _param(self, name: str):
        return self.get_parameter(name).value

    def _fallback_intrinsics(self) -> FallbackIntrinsics:
        k = self.settings.fallback
        return FallbackIntrinsics(*k) if k is not None else FallbackIntrinsics()

    def _publishes(self, output: str) -> bool:
        return output in self.settings.published

    def _parameters_set(self, params) -> None:
        """After a change: every setting again (and the legacy names' warnings)."""
        try:
            settings = node_params.build_settings(self._values())
        except Exception as exc:  # validated before it was set: unexpected
            self.fault("parameters", exc)
            return
        self._all, self.settings = settings, settings.node
        for warning in settings.warnings:
            self.warn_every(f"legacy:{warning}", warning)

    def _validate_parameters(self, params) -> SetParametersResult:
        """The on-set check: never raises (an exception would reach the parameter service);
        anything unexpected refuses the change with the reason and counts a fault."""
        try:
            values = self._values()
            values.update({p.name: p.value for p in params})
            reason = node_params.validate(values)
            if not reason:
                self.ttr.check_config(node_params.build_ttr_config(values))
        except InputError as exc:  # e.g. frozen encoder levels on a model without stages
            reason = str(exc)
        except Exception as exc:  # a value no check foresaw: refuse it, with the reason
            reason = f"{type(exc).__name__}: {exc}"
            self.fault("parameters", exc)
        if reason:
            self.warn_every("parameters", f"parameter change refused: {reason}")
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

    # -- faults and throttled logs -------------------------------------------------------------
    def fault(self, place: str, exc: BaseException) -> None:
        """Count and log (throttled per place) an exception contained at ``place``."""
        n = self.diagnostics.fault(place)
        self.warn_every(f"fault:{place}", f"{place}: contained {type(exc).__name__}: {exc} (at "
                        f"{where(exc)}; {n} so far); the node goes on", error=True)

    def warn_every(self, key: str, message: str, *, error: bool = False) -> None:
        """Log ``message`` at most once per ``WARN_PERIOD_S`` per ``key``."""
        if not self._throttle.due(key):
            return
        # two call sites: rclpy refuses one call site logging at two severities
        try:
            if error:
                self.get_logger().error(message)
            else:
                self.get_logger().warning(message)
        except Exception:  # noqa: S110 - a log that cannot be written must not become a fault
            pass

    # -- callbacks (executor thread: convert and hand over only) -------------------------------
    @contained("image_callback")
    def _on_image(self, msg: Image) -> None:
        self._take_image(msg, image_to_rgb8)

    @contained("image_callback")
    def _on_compressed_image(self, msg: CompressedImage) -> None:
        self._take_image(msg, compressed_to_rgb8)

    def _take_image(self, msg, decode) -> None:
        """Decode an image message into a frame and hand it to the intrinsics rule; a message
        that cannot be read (any exception: it is the message that is bad) is dropped and
        counted as ``bad_image``."""
        try:
            rgb = decode(msg)
            stamp_ns = stamp_to_ns(msg.header.stamp)
            frame = Frame(index=self.stream.counters()["received"] + self.intrinsics.held,
                          image=rgb, stamp=stamp_to_seconds(msg.header.stamp),
                          header=msg.header)
        except Exception as exc:
            detail = str(exc) if isinstance(exc, InputError) else f"{type(exc).__name__}: {exc}"
            self.stream.reject(Dropped.BAD_IMAGE, f"image rejected: {detail}")
            return
        if not self.settings.published.isdisjoint(LIVE_OUTPUTS):
            self.online.submit_live(frame)  # live depth needs no intrinsics
        self._hand_over(self.intrinsics.add_frame(frame, stamp_ns))
        if self.intrinsics.held:
            self.warn_every(
                "held", f"{self.intrinsics.held} frame(s) held: no intrinsics yet - waiting for "
                f"a CameraInfo on {self.resolve_topic_name(names.CAMERA_INFO_TOPIC)} or set the "
                "fallback_intrinsics")

    @contained("camera_info_callback")
    def _on_camera_info(self, msg: CameraInfo) -> None:
        try:
            intr = camera_info_to_intrinsics(msg, self.settings.use_projection)
            stamp_ns = stamp_to_ns(msg.header.stamp)
        except Exception as exc:  # it is the message that is bad
            self.diagnostics.camera_info_rejected()
            detail = str(exc) if isinstance(exc, InputError) else f"{type(exc).__name__}: {exc}"
            self.warn_every("camera_info", f"CameraInfo rejected: {detail}")
            return
        self._hand_over(self.intrinsics.add_intrinsics(intr, stamp_ns, msg))

    @contained("odometry_callback")
    def _on_odometry(self, msg: Odometry) -> None:
        """A position for the metric scale (``metric.source: odometry``); one that cannot be
        read, is out of order or not finite is counted (``metric.odometry_rejected``)."""
        try:
            stamp, position = odometry_to_position(msg)
        except Exception as exc:  # it is the message that is bad
            self.ttr.odometry.rejected += 1
            self.warn_every("odometry", f"Odometry rejected: {exc}")
            return
        if not self.ttr.odometry.add(stamp, position):
            self.warn_every("odometry", "Odometry rejected: its stamp is not after the last "
                            "one's, or its position is not finite")

    def _hand_over(self, resolved: Resolved) -> None:
        """Queue the frames that have intrinsics; count the held frames pushed out."""
        for frame, intr in resolved.ready:
            if frame.size != (intr.width, intr.height):
                source = ("the CameraInfo" if self.intrinsics.latest is not None else
                          "fallback_intrinsics (principal point outside the frame)")
                self.warn_every(
                    "mismatch", f"intrinsics for {intr.width}x{intr.height} from {source} on a "
                    f"{frame.size[0]}x{frame.size[1]} frame: published unrefined "
                    "(intrinsics_mismatch)")
            self.stream.submit(frame, intr)
        for frame in resolved.dropped:
            self.stream.reject(NO_INTRINSICS, "no intrinsics (no CameraInfo, "
                               f"fallback_intrinsics unset): held frame dropped (max_pending="
                               f"{self.intrinsics.max_held})", frame)

    @contained("qos_event")
    def _on_incompatible_qos(self, what: str, event) -> None:
        self.diagnostics.qos_event(what)
        policy = getattr(event, "last_policy_kind", "?")
        self.get_logger().warning(
            f"incompatible QoS on {what} (policy {policy}, {event.total_count} so far): "
            "check the other side's reliability/durability (qos_reliability parameter)",
            throttle_duration_sec=WARN_PERIOD_S)

    @contained("timer")
    def _on_timer(self) -> None:
        self._hand_over(self.intrinsics.release())  # the fallback may have been set meanwhile
        self.publish_diagnostics()

    # -- outputs (live thread, worker thread) --------------------------------------------------
    def _publish_live(self, out: LiveOutput) -> None:
        """The live server's sink: ~/depth, ~/depth_colored, ~/cloud (those asked for), with the
        CameraInfo of the frame's camera as known NOW (it may arrive after the image). An
        exception here is counted by the live server (``live.skipped.publish_error``) and
        logged, throttled."""
        if self._stop.is_set():
            return
        s = self.settings
        camera = self.intrinsics.camera_for(out.frame.size, _stamp_ns(out.frame))
        if camera is None:
            self._camera_info_missing("live", out.frame)
        self._publish(outputs.live_messages(out, s.published, camera,
                                            cloud_stride=s.cloud_stride,
                                            cloud_max_range=s.cloud_max_range))

    @contained("publish")
    def _publish_output(self, out: FrameOutput) -> None:
        if self._stop.is_set():
            return
        if self._publishes("depth_refined") and not out.live_only:
            camera = self._refined_camera(out.frame)
            if camera is None:
                self._camera_info_missing("refined", out.frame)
            self._publish(outputs.frame_messages(out, camera))
        self.diagnostics.output_published(out.refined, out.reason_key)

    def _refined_camera(self, frame: Frame) -> CameraSource | None:
        """The camera of a frame out of its window: the CameraInfo its intrinsics were read
        from; for a frame that had the fallback's, a CameraInfo received since (the camera's own
        description: the stream takes the first one in place of the fallback too), else the
        fallback it had."""
        given = frame.camera if isinstance(frame.camera, CameraSource) else None
        if given is not None and not given.fallback:
            return given
        now = self.intrinsics.camera_for(frame.size, _stamp_ns(frame))
        if now is not None and (given is None or not now.fallback):
            return now
        return given

    def _camera_info_missing(self, output: str, frame: Frame) -> None:
        n = self.diagnostics.camera_info_missing(output)
        self.warn_every(f"no_camera_info:{output}", (
            f"{output} depth of frame {frame.name} published without CameraInfo ({n} so far): "
            f"no intrinsics yet - waiting for a CameraInfo on "
            f"{self.resolve_topic_name(names.CAMERA_INFO_TOPIC)} or set fallback_intrinsics"))

    @contained("publish")
    def _on_window(self, stats: WindowStats) -> None:
        if self._stop.is_set():
            return
        if stats.reason_key == Unrefined.ROLLED_BACK:
            self.warn_every("rolled_back", f"window {stats.index}: {stats.reason}")
        self._publish(outputs.window_messages(stats, points=self._publishes("points")))
        self.publish_diagnostics()

    def _publish(self, messages: dict[str, object]) -> None:
        for topic, msg in messages.items():
            self._publishers_by_topic[topic].publish(msg)

    # -- diagnostics ---------------------------------------------------------------------------
    def diagnostics_values(self) -> dict[str, object]:
        """The key/values of the next /diagnostics status (README "Diagnostics")."""
        return self.diagnostics.values()

    def publish_diagnostics(self) -> None:
        if self._stop.is_set() or not self._publishes("diagnostics"):
            return
        with self._diag_lock:
            msg = outputs.diagnostics_message(self.diagnostics.status(), self.get_clock().now(),
                                              self.get_fully_qualified_name())
            try:
                self.pub_diag.publish(msg)
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
        self.online.stop(timeout)
        if self.online.worker_alive:
            self.get_logger().warning(
                f"worker did not stop within {timeout:g} s (busy in an uninterruptible network "
                "call); not waiting for it")
        v = self.diagnostics.values()
        self.get_logger().info(
            f"stopped: {v['frames_received']} received, {v['frames_refined']} refined, "
            f"{v['frames_unrefined']} unrefined, {v['frames_dropped']} dropped, "
            f"{v['frames_pending']} pending not published (no flush on shutdown)"
            + _live_summary(v))
        if self.online.worker_alive:
            return  # the model and the SfM workspace are still in use: leave them alone
        try:
            path = self._param("save_weights_path")
        except Exception as exc:  # the node's parameters are gone (destroyed): nothing to save
            path = ""
            self.fault("shutdown", exc)
        if path:
            try:
                Path(path).parent.mkdir(parents=True, exist_ok=True)
                torch.save(self.ttr.model.encoder.state_dict(), path)
                self.get_logger().info(f"refined encoder saved to {path}")
            except Exception as exc:  # unwritable path, full disk: logged, the exit stays clean
                self.get_logger().error(f"cannot save the encoder to {path}: "
                                        f"{type(exc).__name__}: {exc}")
        try:
            self.ttr.close()
        except Exception as exc:
            self.fault("shutdown", exc)

    @property
    def worker_alive(self) -> bool:
        return self.online.worker_alive

    def destroy_node(self) -> None:
        self.stop_worker()
        super().destroy_node()


def main(args=None) -> int:
    """Entry point of ``ros2 run sfm_ttr_ros refiner``."""
    malloc_note = allocator.preload()  # mimalloc unless SFM_TTR_MALLOC says: ros/allocator.py
    dds_note = dds.apply_profile()  # before rclpy.init: Fast DDS reads it when it starts
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
    log = get_logger(names.NODE_NAME)
    log.info(dds_note)
    log.info(malloc_note)
    try:
        try:
            node = RefinerNode()
        except (InputError, ParameterException) as exc:  # bad parameters / model: one line
            log.fatal(f"cannot start: {type(exc).__name__}: {exc}")
            code = EXIT_START_UP
        except (KeyboardInterrupt, ExternalShutdownException):
            raise
        except Exception as exc:  # any other start-up failure: still one line, no traceback
            log.fatal(f"cannot start: {type(exc).__name__}: {exc} (at {where(exc)})")
            code = EXIT_START_UP
        if node is not None:
            executor = SingleThreadedExecutor()
            executor.add_node(node)
            while rclpy.ok():
                executor.spin_once(timeout_sec=0.2)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as exc:  # escaped the callbacks' containment: a run-time fault
        log.fatal(f"run-time fault: {type(exc).__name__}: {exc} (at {where(exc)}); stopping")
        code = EXIT_RUN_TIME
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


def _stamp_ns(frame: Frame) -> int | None:
    """The frame's header stamp in nanoseconds (None without a header)."""
    header = frame.header
    return None if header is None else stamp_to_ns(header.stamp)


#: The live part of the shutdown line, as :func:`_live_summary` writes it (read by the demo).
LIVE_SUMMARY_RE = re.compile(r"live ~/depth: (\d+) received, (\d+) published, (\d+) skipped")


def _live_summary(v: dict) -> str:
    """The live output's accounting for the shutdown line ("" when ~/depth is off); parsed
    back by :data:`LIVE_SUMMARY_RE`."""
    if "live.received" not in v:
        return ""
    why = ", ".join(f"{k[len('live.skipped.'):]} {n}" for k, n in v.items()
                    if k.startswith("live.skipped.") and n)
    return (f"; live ~/depth: {v['live.received']} received, {v['live.published']} published, "
            f"{v['live.skipped']} skipped" + (f" ({why})" if why else ""))


if __name__ == "__main__":
    sys.exit(main())
