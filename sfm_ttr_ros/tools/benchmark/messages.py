"""What the node does with messages, timed, for the speed measurement (:mod:`.speed`): each
input frame arrives as the rgb8 Image a camera driver sends and is decoded as the node's
subscription callback decodes it; each output is built as the node builds it
(:mod:`sfm_ttr_ros.ros.outputs`: depth images and their CameraInfo, the window's cloud, the
``/diagnostics`` status) and serialised with ``rclpy.serialization`` (what ``publish`` does
before handing a message to the middleware; no transport)."""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Collection

import numpy as np

from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.params.node import DEFAULT_OUTPUTS
from sfm_ttr_ros.core.pipeline import WindowResult
from sfm_ttr_ros.core.stream.diagnostics import Status, StreamDiagnostics
from sfm_ttr_ros.core.stream.window_runner import FrameOutput, WindowStats

#: The timers of :class:`MessageCost` (seconds each), in the report's order.
CONVERSIONS = ("input_image", "depth_image", "camera_info", "pointcloud", "diagnostics",
               "serialize")


def make_header(stamp: float, frame_id: str = "camera"):
    """A std_msgs Header for a stamp in seconds (as the node's input images carry)."""
    from msg_adapters import make_header as header_from_ns

    return header_from_ns(round(stamp * 1e9), frame_id)


class MessageCost:
    """The node's message work, timed per :data:`CONVERSIONS` key (``t``), with the messages
    sent and their bytes; ``published`` is the node's ``outputs`` parameter."""

    def __init__(self, published: Collection[str] = DEFAULT_OUTPUTS):
        from rclpy.serialization import serialize_message

        from msg_adapters import image_to_rgb8, intrinsics_to_camera_info, numpy_to_image
        from sfm_ttr_ros.ros import outputs
        from sfm_ttr_ros.ros.camera import CameraSource

        self._ser = serialize_message
        self._outputs = outputs
        self._decode, self._encode = image_to_rgb8, numpy_to_image
        self._camera_info, self._camera_source = intrinsics_to_camera_info, CameraSource
        self._cameras: dict[Intrinsics, object] = {}
        self.publish_points = "points" in published
        self.publish_diagnostics = "diagnostics" in published
        self.diagnostics: StreamDiagnostics | None = None
        self.t: dict[str, float] = defaultdict(float)
        self.bytes = 0
        self.messages = 0

    def _timed(self, key: str, fn, *a, **kw):
        t0 = time.perf_counter()
        out = fn(*a, **kw)
        self.t[key] += time.perf_counter() - t0
        return out

    def _send(self, msg) -> None:
        data = self._timed("serialize", self._ser, msg)
        self.bytes += len(data)
        self.messages += 1

    def make_input(self, frame: Frame, intrinsics: Intrinsics):
        """The rgb8 Image message a camera driver would send for ``frame``, with the frame's
        header and camera set as the node sets them (not timed)."""
        if frame.header is None:
            frame.header = make_header(frame.stamp)
        frame.camera = self.camera(intrinsics)
        return self._encode(frame.image, "rgb8", frame.header)

    def camera(self, intr: Intrinsics):
        """What the node's intrinsics resolver sets on a frame (``Frame.camera``): the intrinsics
        with the CameraInfo a camera driver would send (not timed; republishing it beside each
        depth image is)."""
        if intr not in self._cameras:
            self._cameras[intr] = self._camera_source(intr, self._camera_info(intr))
        return self._cameras[intr]

    def receive(self, frame: Frame, msg) -> None:
        """The node's subscription callback: Image -> the frame's RGB array."""
        frame.image = self._timed("input_image", self._decode, msg)

    def output(self, out: FrameOutput) -> None:
        if self.diagnostics is not None:
            self.diagnostics.output_published(out.refined)
        for msg in self._outputs.frame_messages(out, out.frame.camera, timings=self.t).values():
            self._send(msg)

    def window(self, ws: WindowStats) -> None:
        for msg in self._outputs.window_messages(ws, self.publish_points, self.t).values():
            self._send(msg)
        if not self.publish_diagnostics or self.diagnostics is None:
            return
        stamp = ws.cloud_frame.stamp if ws.cloud_frame is not None else time.time()
        self._send(self._outputs.diagnostics_message(self.diagnostics.statuses(), stamp,
                                                     timings=self.t))

    def warm_up(self, shape: tuple[int, int]) -> None:
        """One message of each type (rclpy loads its type support on first use); then the
        timers and counts start from zero."""
        d = np.ones(shape, np.float32)
        f = Frame(index=0, image=np.zeros((*shape, 3), np.uint8))
        msg = self.make_input(f, Intrinsics(1.0, 1.0, 0.0, 0.0, shape[1], shape[0]))
        self.receive(f, msg)
        for m in self._outputs.frame_messages(FrameOutput(f, d, False), f.camera).values():
            self._send(m)
        cloud = WindowStats(index=0, new_frames=1, cloud_frame=f, result=WindowResult(
            [f.name], {}, {}, refined=True, cloud_frame=f.name,
            cloud_xyz=np.zeros((1, 3), np.float32), cloud_error=np.zeros(1, np.float32)))
        for m in self._outputs.window_messages(cloud).values():
            self._send(m)
        self._send(self._outputs.diagnostics_message([Status("ok", "", {"a": 1})], 0.0))
        self.t.clear()
        self.bytes = self.messages = 0
