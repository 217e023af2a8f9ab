"""The messages the ``refiner`` node publishes for one stream output (README "Topics").

Each depth image goes out in image_transport's camera-publisher convention: ``<base>/image``
and, beside it, ``<base>/camera_info`` with the SAME header (stamp and frame_id) and intrinsics
for the image's size (:func:`camera_info_message`: the CameraInfo received for that frame,
republished, or one built from the fallback intrinsics; none when no intrinsics are known yet,
which the node counts).

* per live frame (:func:`live_messages`): ``~/depth/image``, a 32FC1 depth (NaN = invalid) with
  the input image's header unchanged, ``~/depth_colored/image`` (bgr8, by inverse depth) and
  ``~/cloud`` (the depth back-projected with the CameraInfo beside it, x, y, z, rgb), each when
  asked, with their CameraInfos;
* per frame out of its window (:func:`frame_messages`): ``~/depth_refined/image`` (32FC1, same
  header) and its ``camera_info``;
* per window (:func:`window_messages`): ``~/points``, the window's sparse SfM cloud (x, y, z,
  reprojection_error) with the header of the image whose optical frame it is in, when the
  window has a cloud;
* ``/diagnostics`` (:func:`diagnostics_message`): one status per concern (``stream``,
  ``scale``, ``live``, ``worker``), named ``<node name>: <task>`` as diagnostic_updater names
  them (:func:`~sfm_ttr_ros.ros.names.status_name`; the default node's:
  :data:`~sfm_ttr_ros.ros.names.DIAG_NAMES`), hardware_id the node's fully qualified name.

Units (REP 118, :mod:`sfm_ttr_ros.ros.units`): each message is built on its metric topic and
goes out there only when its depth is in metres (the frame's ``metres_per_unit`` is known, or
``metric`` for a window); otherwise on the topic's relative twin (``relative`` ``"publish"``) or
not at all (``"drop"``). With ``compressed`` (a :class:`Compression`), each depth image is also
sent as image_transport's ``<image>/compressedDepth`` (:mod:`msg_adapters.compressed_depth`),
right after it.

Every message is built by msg_adapters. The node publishes what these return, in their order
(each image before its CameraInfo, as image_transport's CameraPublisher); ``sfm-ttr speed``
(tools/benchmark/messages.py) converts through the same functions. ``timings``, when given, adds
the seconds spent building each message under ``depth_image``, ``colored_image``,
``camera_info``, ``cloud``, ``pointcloud``, ``compressed_depth`` and ``diagnostics``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Collection, MutableMapping, Sequence
from typing import NamedTuple

import numpy as np

from msg_adapters import (
    camera_info_for,
    depth_to_colored_image,
    depth_to_image,
    depth_to_pointcloud2,
    diagnostic_array,
    intrinsics_to_camera_info,
    make_diagnostic_status,
    numpy_to_pointcloud2,
)
from msg_adapters.compressed_depth import depth_to_compressed_depth
from sfm_ttr_ros.core.params.node import DEFAULT_OUTPUTS
from sfm_ttr_ros.core.stream.live import LiveOutput
from sfm_ttr_ros.core.stream.status import Status
from sfm_ttr_ros.core.stream.window_runner import FrameOutput, WindowStats
from sfm_ttr_ros.ros import names, units
from sfm_ttr_ros.ros.camera import CameraSource

Timings = MutableMapping[str, float]


class Compression(NamedTuple):
    """The compressedDepth outputs' settings (``compressed_depth.*`` parameters)."""

    depth_max: float = 100.0
    png_level: int = 1


def unit_options(settings) -> dict[str, object]:
    """The units and compression keywords of :func:`live_messages` and :func:`frame_messages`
    under the node's ``settings`` (:class:`~sfm_ttr_ros.core.params.node.NodeSettings`)."""
    compressed = (Compression(settings.compressed_depth_max,
                              settings.compressed_depth_png_level)
                  if "compressed_depth" in settings.published else None)
    return {"relative": settings.relative_depth, "compressed": compressed}


def _compressed(msgs: dict[str, object], topic: str, depth: np.ndarray, header,
                compressed: Compression | None, timings: Timings | None) -> None:
    """Add ``<topic>/compressedDepth`` of ``depth`` to ``msgs`` when ``compressed``."""
    if compressed is not None:
        msgs[names.compressed_depth_topic(topic)] = _timed(
            timings, "compressed_depth", lambda: depth_to_compressed_depth(
                depth, header, depth_max=compressed.depth_max,
                png_level=compressed.png_level))


def _timed(timings: Timings | None, key: str, build: Callable, *args):
    if timings is None:
        return build(*args)
    t0 = time.perf_counter()
    try:
        return build(*args)
    finally:
        timings[key] = timings.get(key, 0.0) + time.perf_counter() - t0


def camera_info_message(camera: CameraSource | None, size: tuple[int, int], header,
                        rectified: bool = False):
    """The CameraInfo beside a ``size`` = (width, height) image with ``header``: the CameraInfo
    ``camera`` was read from, republished (header replaced; scaled when it describes another
    image size; for the depth of a ``rectified`` frame of a distorted camera, that of its
    rectified images: D = 0, their K), or for the fallback intrinsics one built from them (K,
    P = [K | 0], D empty); None when ``camera`` is None (no intrinsics known)."""
    if camera is None:
        return None
    message = camera.message_for(rectified)
    if message is not None:
        return camera_info_for(message, size[0], size[1], header)
    return intrinsics_to_camera_info(camera.intrinsics, header, size=size)


def live_messages(out: LiveOutput, published: Collection[str] = DEFAULT_OUTPUTS,
                  camera: CameraSource | None = None, *, cloud_stride: int = 4,
                  cloud_max_range: float = 0.0, relative: str = "publish",
                  compressed: Compression | None = None,
                  timings: Timings | None = None) -> dict[str, object]:
    """{topic: message} for one live frame, for the outputs in ``published``: ``depth``
    (and its compressedDepth with ``compressed``), ``depth_colored`` (each image with the
    input image's header, and its ``camera_info`` when ``camera`` is known) and ``cloud`` (only
    with ``camera``: the depth back-projected every ``cloud_stride`` pixels, points beyond
    ``cloud_max_range`` left out, with the input image's colours); routed by units (module
    docstring)."""
    header = out.frame.header
    size = (int(out.depth.shape[1]), int(out.depth.shape[0]))
    info = _timed(timings, "camera_info", camera_info_message, camera, size, header,
                  out.frame.rectified)
    msgs: dict[str, object] = {}
    if "depth" in published:
        msgs[names.DEPTH_TOPIC] = _timed(timings, "depth_image", depth_to_image, out.depth,
                                         header)
        _compressed(msgs, names.DEPTH_TOPIC, out.depth, header, compressed, timings)
        if info is not None:
            msgs[names.DEPTH_INFO_TOPIC] = info
    if "depth_colored" in published:
        msgs[names.DEPTH_COLORED_TOPIC] = _timed(timings, "colored_image",
                                                 depth_to_colored_image, out.depth, header)
        if info is not None:
            msgs[names.DEPTH_COLORED_INFO_TOPIC] = info
    if "cloud" in published and info is not None:
        msgs[names.CLOUD_TOPIC] = _timed(timings, "cloud", depth_to_pointcloud2, out.depth,
                                         out.frame.image, info, cloud_stride, cloud_max_range,
                                         header)
    return units.route(msgs, out.metres_per_unit is not None, relative)



def frame_messages(out: FrameOutput, camera: CameraSource | None = None,
                   timings: Timings | None = None, *, relative: str = "publish",
                   compressed: Compression | None = None) -> dict[str, object]:
    """{topic: message} for one frame out of its window: ``~/depth_refined/image`` with the
    input image's header (and its compressedDepth with ``compressed``) and, when ``camera`` is
    known, its ``camera_info``; routed by units (module docstring)."""
    header = out.frame.header
    msgs = {names.DEPTH_REFINED_TOPIC: _timed(timings, "depth_image", depth_to_image, out.depth,
                                              header)}
    _compressed(msgs, names.DEPTH_REFINED_TOPIC, out.depth, header, compressed, timings)
    size = (int(out.depth.shape[1]), int(out.depth.shape[0]))
    info = _timed(timings, "camera_info", camera_info_message, camera, size, header,
                  out.frame.rectified)
    if info is not None:
        msgs[names.DEPTH_REFINED_INFO_TOPIC] = info
    return units.route(msgs, out.metres_per_unit is not None, relative)


def window_messages(stats: WindowStats, points: bool = True,
                    timings: Timings | None = None, *, metric: bool = False,
                    relative: str = "publish") -> dict[str, object]:
    """{topic: message} for one finished window: ``~/points`` when ``points`` and the window
    has a non-empty cloud (it reached refinement), else nothing; on ``~/points`` when
    ``metric`` (the outputs' metric factor is known), else routed by units (module
    docstring)."""
    if not points or stats.cloud_frame is None or not stats.cloud_xyz.shape[0]:
        return {}
    cloud = _timed(timings, "pointcloud", numpy_to_pointcloud2, stats.cloud_xyz,
                   stats.cloud_frame.header, {"reprojection_error": stats.cloud_error})
    return units.route({names.POINTS_TOPIC: cloud}, metric, relative)


def diagnostics_message(statuses: Sequence[Status], stamp, node_name: str = names.NODE_NAME,
                        hardware_id: str = names.NODE_FQN, timings: Timings | None = None):
    """The ``/diagnostics`` DiagnosticArray of ``statuses`` (``stamp``: an rclpy Time, a
    builtin_interfaces Time or seconds), each named ``<node_name>: <task>``
    (:func:`~sfm_ttr_ros.ros.names.status_name`; ``node_name`` without its namespace) with
    ``hardware_id`` the node's fully qualified name."""
    def build():
        return diagnostic_array(stamp, [make_diagnostic_status(
            names.status_name(node_name, s.task), hardware_id, s.level, s.message, s.values)
            for s in statuses])

    return _timed(timings, "diagnostics", build)
