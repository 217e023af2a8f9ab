"""The messages the ``refiner`` node publishes for one stream output (README "Topics").

* per live frame (:func:`live_messages`): ``~/depth``, a 32FC1 depth (NaN = invalid) with the
  input image's header unchanged, and, when asked, ``~/depth_colored`` (bgr8, by inverse depth);
* per frame out of its window (:func:`frame_messages`): ``~/depth_refined`` (32FC1, same header);
* per window (:func:`window_messages`): ``~/points``, the window's sparse SfM cloud (x, y, z,
  reprojection_error) with the header of the image whose optical frame it is in, when the
  window has a cloud;
* ``/diagnostics`` (:func:`diagnostics_message`): one status named
  :data:`~sfm_ttr_ros.ros.names.DIAG_NAME`.

Every message is built by msg_adapters. The node publishes what these return; the speed
benchmark (scripts/benchmark_speed.py) converts through the same functions. ``timings``, when
given, adds the seconds spent building each message under ``depth_image``, ``colored_image``,
``pointcloud`` and ``diagnostics``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, MutableMapping

from msg_adapters import (
    depth_to_colored_image,
    depth_to_image,
    make_diagnostic_array,
    numpy_to_pointcloud2,
)
from sfm_ttr_ros.core.stream.diagnostics import Status
from sfm_ttr_ros.core.stream.live import LiveOutput
from sfm_ttr_ros.core.stream.windows import FrameOutput, WindowStats
from sfm_ttr_ros.ros import names

Timings = MutableMapping[str, float]


def _timed(timings: Timings | None, key: str, build: Callable, *args):
    if timings is None:
        return build(*args)
    t0 = time.perf_counter()
    try:
        return build(*args)
    finally:
        timings[key] = timings.get(key, 0.0) + time.perf_counter() - t0


def live_messages(out: LiveOutput, colored: bool = True,
                  timings: Timings | None = None) -> dict[str, object]:
    """{topic: message} for one live frame: ``~/depth`` and (``colored``) ``~/depth_colored``,
    both with the input image's header."""
    header = out.frame.header
    msgs = {names.DEPTH_TOPIC: _timed(timings, "depth_image", depth_to_image, out.depth, header)}
    if colored:
        msgs[names.DEPTH_COLORED_TOPIC] = _timed(timings, "colored_image",
                                                 depth_to_colored_image, out.depth, header)
    return msgs


def frame_messages(out: FrameOutput, timings: Timings | None = None) -> dict[str, object]:
    """{topic: message} for one frame out of its window: ``~/depth_refined`` with the input
    image's header."""
    return {names.DEPTH_REFINED_TOPIC: _timed(timings, "depth_image", depth_to_image, out.depth,
                                              out.frame.header)}


def window_messages(stats: WindowStats, points: bool = True,
                    timings: Timings | None = None) -> dict[str, object]:
    """{topic: message} for one finished window: ``~/points`` when ``points`` and the window
    has a non-empty cloud (it reached refinement), else nothing."""
    if not points or stats.cloud_frame is None or not stats.cloud_xyz.shape[0]:
        return {}
    cloud = _timed(timings, "pointcloud", numpy_to_pointcloud2, stats.cloud_xyz,
                   stats.cloud_frame.header, {"reprojection_error": stats.cloud_error})
    return {names.POINTS_TOPIC: cloud}


def diagnostics_message(status: Status, stamp, hardware_id: str = names.NODE_FQN,
                        timings: Timings | None = None):
    """The ``/diagnostics`` DiagnosticArray of ``status`` (``stamp``: an rclpy Time, a
    builtin_interfaces Time or seconds; ``hardware_id``: the node's fully qualified name)."""
    return _timed(timings, "diagnostics", make_diagnostic_array, stamp, names.DIAG_NAME,
                  hardware_id, status.level, status.message, status.values)
