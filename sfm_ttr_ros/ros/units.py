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
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping

from msg_adapters import make_diagnostic_array
from sfm_ttr_ros.core.metric.scale import MetricStatus
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
    array = make_diagnostic_array(None, f"{hardware_id} {SCALE_STATUS_NAME}", hardware_id,
                                  "ok" if status.state == "metric" else "warn", message, values)
    return array.status[0]


class ScaleState:
    """Publishes ``~/depth_scale`` through ``publish(msg)`` whenever (source, state, factor,
    relative policy) differs from the last one published (``changes`` counts them).
    Thread-safe (the worker and the executor both report)."""

    def __init__(self, publish: Callable[[object], None], hardware_id: str) -> None:
        self._publish = publish
        self._hardware_id = hardware_id
        self._last: tuple | None = None
        self._lock = threading.Lock()
        self.changes = 0

    def update(self, status: MetricStatus, relative: str) -> bool:
        """Publish ``status`` when it differs from the last published; True when it did."""
        key = (status.source, status.state, status.metres_per_unit, relative)
        with self._lock:
            if key == self._last:
                return False
            self._publish(scale_status_message(status, relative, self._hardware_id))
            self._last = key
            self.changes += 1
            return True
