"""The ``refiner`` ROS 2 node: SfM-TTR on a live image stream, glue over the core
(docs/node.md holds the node in full: topics, outputs, intrinsics, diagnostics, QoS, faults,
shutdown).

Threads: the executor (main thread) runs the subscription callbacks, the parameter services and
the diagnostics timer; callbacks only convert the message (``msg_adapters``) and hand the frame
to :class:`~sfm_ttr_ros.core.stream.refiner.StreamRefiner`: its live server thread answers
``~/depth`` at once, its worker thread (at a lower OS priority) runs the windows (SfM, model,
refinement) and publishes their outputs, so the executor never blocks on heavy work.

The node's jobs, each in a module of its own: the settings from the parameters
(:mod:`~sfm_ttr_ros.ros.live_settings`), the inputs and their QoS
(:mod:`~sfm_ttr_ros.ros.subscriptions`), each frame's intrinsics and camera
(:mod:`~sfm_ttr_ros.ros.camera`), the messages (:mod:`~sfm_ttr_ros.ros.outputs`) and their
publishers (:mod:`~sfm_ttr_ros.ros.publishers`), fault containment
(:mod:`~sfm_ttr_ros.ros.containment`), the encoder file
(:mod:`~sfm_ttr_ros.ros.encoder_file`) and the final accounting
(:mod:`~sfm_ttr_ros.ros.accounting`); topic and node names: :mod:`~sfm_ttr_ros.ros.names`.

Exit codes: 0 after a normal shutdown; 1 when the node cannot START (bad parameters, a missing
or corrupt model / weights file, a pycolmap or torch older than the floors of
:mod:`sfm_ttr_ros.requirements`: one ``cannot start: ...`` line, before spinning); 2 for a
fault of the run itself that escaped the containment (``run-time fault: ...``; none is known).

Shutdown (SIGINT / SIGTERM / external shutdown): the worker is cancelled (``SfmTTR.cancel``) and
joined, the accounting logged (and written with ``--accounting FILE``), the refined encoder
saved when ``save_weights_path`` is set, then the executor is shut down, the node destroyed and
rclpy shut down: exit code 0. Pending frames are NOT flushed on shutdown (it must be fast). A
network forward pass cannot be interrupted: when the worker is still inside one after
``STOP_TIMEOUT_S``, the process leaves with ``os._exit`` once ROS is shut down (a thread in
torch C++ code at interpreter finalisation would abort it), without saving the weights.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from functools import partial

import rclpy
import torch
from nav_msgs.msg import Odometry
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from msg_adapters import (
    UncalibratedCameraInfo,
    compressed_to_rgb8,
    image_to_rgb8,
)
from msg_adapters.odometry import odometry_to_position
from msg_adapters.stamp import stamp_to_ns, stamp_to_seconds
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Frame
from sfm_ttr_ros.core.models.base import DepthModel
from sfm_ttr_ros.core.models.registry import build_model
from sfm_ttr_ros.core.outcomes import Dropped, Unrefined
from sfm_ttr_ros.core.params.node import LIVE_OUTPUTS
from sfm_ttr_ros.core.params.sections import unapplied_files
from sfm_ttr_ros.core.pipeline import SfmTTR
from sfm_ttr_ros.core.stream.diagnostics import StreamDiagnostics, scale_level
from sfm_ttr_ros.core.stream.health import Health
from sfm_ttr_ros.core.stream.live import LiveOutput
from sfm_ttr_ros.core.stream.refiner import StreamRefiner
from sfm_ttr_ros.core.stream.window_runner import FrameOutput, WindowStats
from sfm_ttr_ros.requirements import check_sfm_dependencies
from sfm_ttr_ros.ros import accounting, allocator, camera, dds, names, outputs, subscriptions
from sfm_ttr_ros.ros.camera import NO_INTRINSICS, FallbackIntrinsics, IntrinsicsResolver, Resolved
from sfm_ttr_ros.ros.camera_path_output import CameraPathOutput
from sfm_ttr_ros.ros.containment import ThrottledLog, contained, fault_message, where
from sfm_ttr_ros.ros.encoder_file import load_encoder, save_encoder
from sfm_ttr_ros.ros.live_settings import LiveSettings
from sfm_ttr_ros.ros.metric_watch import warn_if_stale
from sfm_ttr_ros.ros.publishers import OutputPublishers, output_refused
from sfm_ttr_ros.ros.units import ScaleState, describe_depth

STOP_TIMEOUT_S = 3.0  # how long shutdown waits for the worker to finish its current step
EXIT_START_UP = 1  # the node could not start (parameters, model, weights)
EXIT_RUN_TIME = 2  # a fault escaped the containment while running


class RefinerNode(Node):
    """The refiner node. ``model`` (tests, embedding) replaces the one the parameters describe;
    other keyword arguments go to :class:`rclpy.node.Node` (context, parameter_overrides,
    cli_args, namespace).

    ``live_settings`` holds every setting, current with the parameters; ``intrinsics``
    (:class:`~sfm_ttr_ros.ros.camera.IntrinsicsResolver`) decides each frame's intrinsics and
    holds the frames that have none; ``diagnostics``
    (:class:`~sfm_ttr_ros.core.stream.diagnostics.StreamDiagnostics`) counts and builds the
    status; ``pubs`` (:class:`~sfm_ttr_ros.ros.publishers.OutputPublishers`) publishes what
    :mod:`sfm_ttr_ros.ros.outputs` builds. ``final_accounting`` is the diagnostics' values once
    stopped (None before)."""

    def __init__(self, *, model: DepthModel | None = None, node_name: str = names.NODE_NAME,
                 **kwargs):
        super().__init__(node_name, **kwargs)
        warn_unapplied_params_files(self, kwargs.get("cli_args") or ())
        try:
            self._setup(model)
        except BaseException:
            super().destroy_node()  # no half-built node left in the graph
            raise

    def _setup(self, model: DepthModel | None) -> None:
        check_sfm_dependencies()  # a pycolmap too old for SfM: "cannot start", not bad windows
        self._log = ThrottledLog(self.get_logger())  # of warn_every, per key
        self.live_settings = LiveSettings(
            self, check_config=lambda config: self.ttr.check_config(config), fault=self.fault,
            warn_every=self.warn_every)
        settings, node = self.live_settings.all, self.settings
        if node.torch_num_threads > 0:
            torch.set_num_threads(int(node.torch_num_threads))
        if model is None:
            model = build_model(settings.model)
        if node.load_weights_path:
            load_encoder(model, node.load_weights_path)
        self.ttr = SfmTTR(model, settings.ttr)
        self.online = StreamRefiner(
            self.ttr, settings.stream,
            config_provider=lambda: self.live_settings.all.ttr,
            settings_provider=lambda: self.live_settings.all.stream,
            on_live=self._publish_live, on_refined=self._publish_output,
            on_window=self._on_window, on_fault=self.fault, logger=self.get_logger())
        self.stream = self.online.stream
        self.intrinsics = IntrinsicsResolver(
            lambda: FallbackIntrinsics(*(self.settings.fallback or ())),
            max_held=int(settings.stream.max_pending),
            assumed_hfov_deg=lambda: self.settings.assumed_hfov_deg,
            assumed_focal=self.ttr.focal.focal_for)
        self.diagnostics = StreamDiagnostics(
            self.stream, held=lambda: self.intrinsics.held, live=self.online.counters_live,
            scale=lambda s: (scale_level(s), self._describe_depth(s, self.settings.relative_depth)))
        self.diagnostics.intrinsics_values = lambda: camera.intrinsics_values(
            self.intrinsics, self.ttr.focal)
        self.cameras = camera.CameraInfoReader(self.get_logger(),
                                               self.diagnostics.camera_info_rejected)
        self.final_accounting: dict | None = None
        self._closed = False
        self._stop = threading.Event()

        image_input = subscriptions.image_input(self, node, self._on_image,
                                                self._on_compressed_image)
        self.image_topic = self.resolve_topic_name(image_input.topic)
        self.camera_info_topic = self.resolve_topic_name(subscriptions.camera_info_topic(self))
        self.pubs = OutputPublishers(self, int(node.qos_depth),
                                     partial(output_refused, self))
        self.scale = ScaleState(self.pubs.depth_scale.publish, self.get_fully_qualified_name(),
                                self.get_logger(), self._describe_depth)
        self._report_scale()
        self.camera_path = CameraPathOutput(self, node, int(node.qos_depth))  # ~/odom
        self.create_timer(float(node.diagnostics_period_s), self._on_timer)

        self.online.start()  # warm-up paid: only now subscribe, so no frame waits for it
        self.health = self.diagnostics.health = Health(  # ERROR, STALE, rates: from now on
            lambda: self.online.worker_alive,
            lambda: self.settings.diagnostics_stale_after_s, self.image_topic)
        subscriptions.subscribe(
            self, [image_input, *subscriptions.camera_and_odometry(
                self._on_camera_info, self._on_odometry, subscriptions.camera_info_topic(self))],
            subscriptions.input_qos(node), partial(subscriptions.input_refused, self))
        self.get_logger().info(_ready_line(self, model))

    @property
    def settings(self):
        """The node's own settings (:class:`~sfm_ttr_ros.core.params.node.NodeSettings`), as
        the parameters are now."""
        return self.live_settings.all.node

    def _publishes(self, output: str) -> bool:
        return output in self.settings.published

    # -- faults and throttled logs -------------------------------------------------------------
    def fault(self, place: str, exc: BaseException) -> None:
        """Count and log (throttled per place) an exception contained at ``place``."""
        n = self.diagnostics.fault(place)
        self._log.error_every(f"fault:{place}", fault_message(place, exc, n))

    def warn_every(self, key: str, message: str) -> None:
        """Log the warning ``message`` at most once per ``WARN_PERIOD_S`` per ``key``."""
        self._log.warn_every(key, message)

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
        self.health.image_received()
        try:
            rgb = decode(msg)
            stamp_ns = stamp_to_ns(msg.header.stamp)
            frame = Frame(index=self.stream.counters()["received"] + self.intrinsics.held,
                          image=rgb, stamp=stamp_to_seconds(msg.header.stamp),
                          header=msg.header)
        except Exception as exc:
            self.stream.reject(Dropped.BAD_IMAGE, f"image rejected: {_detail(exc)}")
            return
        frame = self.intrinsics.rectified(frame, stamp_ns)  # once, for live and the window
        if not self.settings.published.isdisjoint(LIVE_OUTPUTS):
            self.online.submit_live(frame)  # live depth needs no intrinsics
        self._hand_over(self.intrinsics.add_frame(frame, stamp_ns))
        if self.intrinsics.held:
            self.warn_every(
                "held", f"{self.intrinsics.held} frame(s) held: no intrinsics yet - waiting for "
                f"a CameraInfo on {self.camera_info_topic} or set the "
                "fallback_intrinsics")

    @contained("camera_info_callback")
    def _on_camera_info(self, msg: CameraInfo) -> None:
        try:
            source = self.cameras.read(msg, self.settings.use_projection)  # None: refused
            stamp_ns = stamp_to_ns(msg.header.stamp)
        except UncalibratedCameraInfo as exc:  # K all zero: intrinsics assumed (ros/camera.py)
            self.warn_every("uncalibrated", camera.uncalibrated_note(exc, self.settings))
            self._hand_over(self.intrinsics.camera_uncalibrated())
            return
        except Exception as exc:  # it is the message that is bad
            self.diagnostics.camera_info_rejected()
            self.warn_every("camera_info", f"CameraInfo rejected: {_detail(exc)}")
            return
        if source is not None:
            self._hand_over(self.intrinsics.add_camera(source, stamp_ns))

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
                            "one's (more than 1 s back restarts the track), or its position "
                            "is not finite")

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

    @contained("timer")
    def _on_timer(self) -> None:
        self._hand_over(self.intrinsics.release())  # the fallback may have been set meanwhile
        for frame in self.intrinsics.expire(self.live_settings.all.stream.idle_flush_s):
            self.stream.submit(frame, None)  # no intrinsics came: published unrefined
        self._report_scale()
        self.publish_diagnostics()
        warn_if_stale(self.ttr, self.warn_every)  # the metric scale's source stopped

    def _report_scale(self) -> None:
        """~/depth_scale (latched) and the log of where the depth goes, on a change (units)."""
        self.scale.update(self.ttr.metric_status(), self.settings.relative_depth)

    def _describe_depth(self, status, relative: str) -> str:
        return describe_depth(status, relative, self.resolve_topic_name, self.settings.published)

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
        self.pubs.publish(outputs.live_messages(out, s.published, camera,
                                                cloud_stride=s.cloud_stride,
                                                cloud_max_range=s.cloud_max_range,
                                                **outputs.unit_options(s)))
        self.health.published("depth")

    @contained("publish")
    def _publish_output(self, out: FrameOutput) -> None:
        if self._stop.is_set():
            return
        if self._publishes("depth_refined") and not out.live_only:
            camera = self.intrinsics.window_camera(out.frame, _stamp_ns(out.frame))
            if camera is None:
                self._camera_info_missing("refined", out.frame)
            self.pubs.publish(outputs.frame_messages(out, camera,
                                                     **outputs.unit_options(self.settings)))
            self.health.published("depth_refined")
        self.diagnostics.output_published(out.refined, out.reason_key)

    def _camera_info_missing(self, output: str, frame: Frame) -> None:
        n = self.diagnostics.camera_info_missing(output)
        self.warn_every(f"no_camera_info:{output}", (
            f"{output} depth of frame {frame.name} published without CameraInfo ({n} so far): "
            f"no intrinsics yet - waiting for a CameraInfo on "
            f"{self.camera_info_topic} or set fallback_intrinsics"))

    @contained("publish")
    def _on_window(self, stats: WindowStats) -> None:
        if self._stop.is_set():
            return
        if stats.reason_key == Unrefined.ROLLED_BACK:
            self.warn_every("rolled_back", f"window {stats.index}: {stats.reason}")
        self.pubs.publish(outputs.window_messages(
            stats, points=self._publishes("points"), metric=self.ttr.metres_per_unit is not None,
            relative=self.settings.relative_depth))
        self._report_scale()
        if self._publishes("odom"):
            self.camera_path.window(stats, relative=self.settings.relative_depth)
        self.publish_diagnostics()

    def diagnostics_values(self) -> dict[str, object]:
        """The key/values of the next /diagnostics status (docs/node.md "Diagnostics")."""
        return self.diagnostics.values()

    def publish_diagnostics(self) -> None:
        if self._stop.is_set() or not self._publishes("diagnostics"):
            return
        self.pubs.publish_statuses(self.diagnostics.statuses, self.get_clock().now,
                                   self.get_name(), self.get_fully_qualified_name(),
                                   self._stop.is_set)

    # -- shutdown ------------------------------------------------------------------------------
    def stop_worker(self, timeout: float = 5.0) -> None:
        """Cancel the running window, join the worker, keep and log the final accounting, save
        the weights (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        self.online.stop(timeout)
        if self.online.worker_alive:
            self.get_logger().warning(
                f"worker did not stop within {timeout:g} s (busy in an uninterruptible network "
                "call); not waiting for it")
        self.final_accounting = self.diagnostics.values()
        self.get_logger().info(accounting.stopped_line(self.final_accounting))
        if self.online.worker_alive:
            return  # the model and the SfM workspace are still in use: leave them alone
        try:
            path = self.get_parameter("save_weights_path").value
        except Exception as exc:  # the node's parameters are gone (destroyed): nothing to save
            path = ""
            self.fault("shutdown", exc)
        if path:
            save_encoder(self.ttr.model, path, self.get_logger())
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
    """Entry point of ``ros2 run sfm_ttr_ros refiner [--accounting FILE]``."""
    malloc_note = allocator.preload()  # mimalloc unless SFM_TTR_MALLOC says: ros/allocator.py
    dds_note = dds.apply_profile()  # before rclpy.init: Fast DDS reads it when it starts
    argv = sys.argv if args is None else args
    accounting_file = accounting.accounting_path(argv)
    # Our own signal handling: SIGINT/SIGTERM raise KeyboardInterrupt in the main thread, so the
    # worker is stopped BEFORE the context goes down (the executor spins with a timeout).
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)

    def _interrupt(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGINT, _interrupt)
    signal.signal(signal.SIGTERM, _interrupt)
    log = get_logger(names.NODE_NAME)
    log.info(dds_note)
    log.info(malloc_note)
    node, executor, code = None, None, 0
    try:
        node, code = _start(log, argv)
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
        stuck = _stop(node, executor, accounting_file, log)
    if stuck:
        # A thread inside torch / pycolmap C++ code at interpreter finalisation aborts the
        # process (exit 134): leave at once instead, everything ROS is already shut down.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


def warn_unapplied_params_files(node: Node, args) -> None:
    """A WARNING for each ``--params-file`` among the ROS arguments ``args`` that has no section
    for this node's full name (rcl then starts it at the defaults and says nothing; e.g. a
    ``refiner:`` section under ``-r __ns:=/cam1``)."""
    for message in unapplied_files(args, node.get_fully_qualified_name()):
        node.get_logger().warning(message)


def _start(log, argv) -> tuple[RefinerNode | None, int]:
    """The node (``argv``: the process's arguments, whose parameter files it checks), or None
    and :data:`EXIT_START_UP` with one ``cannot start`` line."""
    try:
        node = RefinerNode()
        warn_unapplied_params_files(node, argv)
        return node, 0
    except (InputError, ParameterException) as exc:  # bad parameters / model: one line
        log.fatal(f"cannot start: {type(exc).__name__}: {exc}")
    except (KeyboardInterrupt, ExternalShutdownException):
        raise
    except Exception as exc:  # any other start-up failure: still one line, no traceback
        log.fatal(f"cannot start: {type(exc).__name__}: {exc} (at {where(exc)})")
    return None, EXIT_START_UP


def _stop(node: RefinerNode | None, executor, accounting_file, log) -> bool:
    """Stop the worker, write the accounting (``--accounting``), shut the executor, the node
    and rclpy down; True when the worker is stuck in a network call."""
    if node is not None:
        node.stop_worker(timeout=STOP_TIMEOUT_S)
        if accounting_file is not None and node.final_accounting is not None:
            try:
                accounting.write_accounting(accounting_file, node.final_accounting)
            except OSError as exc:  # logged: the exit stays clean
                log.error(f"cannot write the accounting to {accounting_file}: {exc}")
    stuck = node is not None and node.worker_alive
    if executor is not None:
        executor.shutdown(timeout_sec=1.0)
    if node is not None:
        node.destroy_node()
    rclpy.try_shutdown()
    return stuck


def _ready_line(node: RefinerNode, model: DepthModel) -> str:
    """The line logged once the node is ready."""
    values, settings = node.live_settings.start_values, node.settings
    return (f"refiner ready: model {type(model).__name__} (input {model.input_size}), window "
            f"{values['window_size']}/{values['window_stride']}, refinement "
            f"{values['refinement.steps']} steps, weight_policy {values['weight_policy']}, "
            f"input {node.image_topic} ({settings.image_transport}) with "
            f"{node.camera_info_topic}, QoS {settings.qos_reliability} depth "
            f"{settings.qos_depth}")


def _detail(exc: Exception) -> str:
    """An exception as a rejection's reason: an InputError's message, else type and message."""
    return str(exc) if isinstance(exc, InputError) else f"{type(exc).__name__}: {exc}"


def _stamp_ns(frame: Frame) -> int | None:
    """The frame's header stamp in nanoseconds (None without a header)."""
    header = frame.header
    return None if header is None else stamp_to_ns(header.stamp)


if __name__ == "__main__":
    sys.exit(main())
