"""The units of the ``refiner`` node's outputs on the wire (docs/node.md, "Units").

REP 118: a 32FC1 depth image is metres (REP 105: so is ``odom``). Every output topic that has a
relative twin (:data:`~sfm_ttr_ros.ros.names.RELATIVE_TWIN`: the depth images, their
CameraInfos, the clouds, the camera's path) carries metres only; what is not (yet) in metres
(metric state ``not_metric`` or ``waiting``:
:class:`~sfm_ttr_ros.core.metric.scale.MetricStatus`) goes out on that twin (``relative_depth:
publish``) or not at all (``drop``; ``~/depth_scale`` says which): :func:`topic_now`, the one
rule, and :func:`route` of a publication's messages by it.
A frame is in metres when the outputs' factor was known as it was made: in states ``metric``,
``confirming`` (one window's estimate, not yet confirmed by a second) and ``stale`` (its source
stopped; the last factor holds), each of the last two with a WARN on ``~/depth_scale``.

``~/depth_scale`` (:class:`ScaleState`) states the scale now: a latched (transient local,
depth 1) diagnostic_msgs/DiagnosticStatus, published at start and at every change of source,
state, factor or the relative policy, so that a subscriber that comes late still reads it.
Why DiagnosticStatus: it is in common_interfaces (no package of ours to build on the
consumer's side), ``ros2 topic echo`` shows it as it is, and its key/values hold the source and
state (strings) beside the factor (a number), which a std_msgs/Float64 could not; its level
says whether the depth topics carry metres (OK) or not (WARN).

:func:`describe_depth` says it for a person, with the resolved topic names: the node logs it at
start-up and at every change (INFO in metres, WARN not), and it is the message of the node's
``scale`` status on /diagnostics.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Collection, Mapping

from msg_adapters import make_diagnostic_status
from sfm_ttr_ros.core.metric.scale import MetricStatus
from sfm_ttr_ros.core.stream.diagnostics import scale_level
from sfm_ttr_ros.ros import names

SCALE_STATUS_NAME = "depth scale"  # the DiagnosticStatus name (after the node's full name)


def topic_now(topic: str, metric: bool, relative: str) -> str | None:
    """Where an output built for the metric ``topic`` goes: ``topic`` itself when ``metric``
    or when it has no relative twin (``~/depth_colored``: colours, no unit); else its twin
    (``relative`` ``"publish"``) or nowhere (None, ``"drop"``)."""
    twin = names.RELATIVE_TWIN.get(topic)
    if metric or twin is None:
        return topic
    return twin if relative == "publish" else None


def route(messages: Mapping[str, object], metric: bool, relative: str) -> dict[str, object]:
    """``messages`` built on the metric topics, as they go out (:func:`topic_now`)."""
    out: dict[str, object] = {}
    for topic, msg in messages.items():
        now = topic_now(topic, metric, relative)
        if now is not None:
            out[now] = msg
    return out


def depth_topic_now(metres_per_unit: float | None, relative: str) -> str:
    """Where the live depth goes with the outputs' factor ``metres_per_unit`` (None: not in
    metres; :func:`topic_now`): the metric topic, its relative twin, or ``"dropped"``."""
    return topic_now(names.DEPTH_TOPIC, metres_per_unit is not None, relative) or "dropped"


def scale_status_message(status: MetricStatus, relative: str, hardware_id: str):
    """The ``~/depth_scale`` DiagnosticStatus of ``status``: key/values ``source``, ``state``,
    ``reason``, ``factor`` (metres per network unit, ``nan`` when not metric) and
    ``depth_topic`` (where the live depth goes now). The depth is in metres whenever a factor
    is known (as :func:`route` decides per frame); the level is OK in state ``metric``, WARN
    otherwise: not in metres, or in metres not yet confirmed by a second window
    (``confirming``) or whose source stopped (``stale``: the last factor still applies)."""
    metres = status.metres_per_unit is not None
    message = (f"depth in metres (REP 118), state {status.state}" if metres else
               f"depth not in metres ({status.state}): relative topics"
               if relative == "publish" else
               f"depth not in metres ({status.state}): not published")
    values = {"source": status.source, "state": status.state,
              "reason": status.reason,
              "factor": float("nan") if not metres else status.metres_per_unit,
              "depth_topic": depth_topic_now(status.metres_per_unit, relative)}
    return make_diagnostic_status(f"{hardware_id} {SCALE_STATUS_NAME}", hardware_id,
                                  scale_level(status), message, values)


#: output (``outputs`` parameter) -> its metric depth image topic
DEPTH_OUTPUTS = {"depth": names.DEPTH_TOPIC, "depth_refined": names.DEPTH_REFINED_TOPIC}


def describe_depth(status: MetricStatus, relative: str, resolve: Callable[[str], str],
                   published: Collection[str] = ("depth",)) -> str:
    """Which topic carries the depth now and why, with the names ``resolve`` gives the metric
    depth topics of the ``published`` outputs (``~/depth/image``, ``~/depth_refined/image``),
    e.g. ``depth on /refiner/depth_relative/image (relative: metric.source none; set
    metric.source to camera_height, odometry or fixed to get metres on
    /refiner/depth/image)``."""
    topics = [topic for output, topic in DEPTH_OUTPUTS.items() if output in published]
    metres = status.metres_per_unit is not None
    metric = ", ".join(resolve(t) for t in topics) or "the depth topics"
    reason = f": {status.reason}" if status.reason else ""
    if metres:
        return (f"depth in metres on {metric} (metric.source {status.source}, {status.state}"
                f"{reason}; {status.metres_per_unit:.4g} m per network unit)")
    if status.source == "none":
        why = ("relative: metric.source none; set metric.source to camera_height, odometry or "
               f"fixed to get metres on {metric}")
    else:
        why = (f"relative: metric.source {status.source} has no scale yet{reason}; metres on "
               f"{metric} once a window's scale is accepted")
    now = [resolve(t) for t in (topic_now(t, False, relative) for t in topics) if t]
    if not now:
        return f"depth not published ({why}; relative_depth {relative})"
    return f"depth on {', '.join(now)} ({why})"


class ScaleState:
    """Publishes ``~/depth_scale`` through ``publish(msg)`` whenever (source, state, factor,
    relative policy) differs from the last one published (``changes`` counts them). With a
    ``logger`` and ``describe(status, relative)`` (:func:`describe_depth`), also logs where the
    depth goes at the first update and whenever the source, state or relative policy changes:
    INFO when the depth is in metres, WARN when not. Thread-safe (the worker and the executor
    both report)."""

    def __init__(self, publish: Callable[[object], None], hardware_id: str, logger=None,
                 describe: Callable[[MetricStatus, str], str] | None = None) -> None:
        self._publish = publish
        self._hardware_id = hardware_id
        self._logger, self._describe = logger, describe
        self._last: tuple | None = None
        self._logged: tuple | None = None
        self._lock = threading.Lock()
        self.changes = 0

    def update(self, status: MetricStatus, relative: str) -> bool:
        """Publish ``status`` when it differs from the last published; True when it did."""
        key = (status.source, status.state, status.metres_per_unit, relative)
        with self._lock:
            self._log(status, relative)
            if key == self._last:
                return False
            self._publish(scale_status_message(status, relative, self._hardware_id))
            self._last = key
            self.changes += 1
            return True

    def _log(self, status: MetricStatus, relative: str) -> None:
        key = (status.source, status.state, relative)
        if self._logger is None or self._describe is None or key == self._logged:
            return
        self._logged = key
        line = self._describe(status, relative)
        if status.metres_per_unit is not None:
            self._logger.info(line)
        else:
            self._logger.warning(line)
