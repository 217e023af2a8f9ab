"""The ``refiner`` node's publishers: every output topic (docs/node.md, "Topics"), each depth
image's CameraInfo beside it, the relative twins of the metric outputs, the compressedDepth of
each depth image, the latched ``~/depth_scale`` and ``/diagnostics``.

:class:`OutputPublishers` creates them (KEEP_LAST ``qos_depth``, reliable; /diagnostics depth
10; ``~/depth_scale`` transient local, depth 1), each output's QoS overridable at start-up by
ROS's ``qos_overrides.<topic>.publisher.<policy>`` parameters (rclpy's
``QoSOverridingOptions``, as the inputs', :mod:`sfm_ttr_ros.ros.subscriptions`), publishes the
``{topic: message}`` dicts :mod:`sfm_ttr_ros.ros.outputs` builds, in their order, and one
diagnostics array (the node's statuses) at a time.
"""

from __future__ import annotations

import copy
import threading
from collections.abc import Callable
from functools import partial

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2

from sfm_ttr_ros.core.stream.throttle import WARN_PERIOD_S
from sfm_ttr_ros.ros import names, outputs

DIAGNOSTICS_QOS_DEPTH = 10
IMAGE_TOPICS = (names.DEPTH_TOPIC, names.DEPTH_COLORED_TOPIC, names.DEPTH_REFINED_TOPIC,
                names.DEPTH_RELATIVE_TOPIC, names.DEPTH_REFINED_RELATIVE_TOPIC)
CLOUD_TOPICS = (names.POINTS_TOPIC, names.CLOUD_TOPIC, names.POINTS_RELATIVE_TOPIC,
                names.CLOUD_RELATIVE_TOPIC)
CAMERA_INFO_TOPICS = (names.DEPTH_INFO_TOPIC, names.DEPTH_COLORED_INFO_TOPIC,
                      names.DEPTH_REFINED_INFO_TOPIC, names.DEPTH_RELATIVE_INFO_TOPIC,
                      names.DEPTH_REFINED_RELATIVE_INFO_TOPIC)
#: ~/depth_scale: a late subscriber still gets the last state (transient local, depth 1)
LATCHED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)


def output_qos(qos_depth: int) -> QoSProfile:
    """The outputs' QoS: KEEP_LAST ``qos_depth``, reliable (overridable per topic)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=qos_depth,
                      reliability=ReliabilityPolicy.RELIABLE)


def output_publisher(node, msg_type, topic: str, qos: QoSProfile | int,
                     on_incompatible_qos: Callable[[str, object], None] | None = None,
                     overridable: bool = True):
    """A publisher of ``node`` on ``topic``: ``qos_overrides`` apply when ``overridable``,
    each on a profile of its own (rclpy writes a topic's overrides into the one given); an
    incompatible QoS calls ``on_incompatible_qos(topic, event)``."""
    profile = copy.copy(qos) if isinstance(qos, QoSProfile) else qos
    events = (PublisherEventCallbacks(incompatible_qos=partial(on_incompatible_qos, topic))
              if on_incompatible_qos is not None else None)
    return node.create_publisher(
        msg_type, topic, profile, event_callbacks=events,
        qos_overriding_options=(QoSOverridingOptions.with_default_policies() if overridable
                                else None))


def output_refused(node, topic: str, event) -> None:
    """An output of ``node`` (the refiner) refused a subscriber: counted (``qos_incompatible``)
    and a WARN, throttled; an exception here is a fault of ``qos_event``."""
    try:
        node.diagnostics.qos_event(topic)
        node.get_logger().warning(
            f"incompatible QoS on {topic} (policy {getattr(event, 'last_policy_kind', '?')}, "
            f"{event.total_count} so far): check the other side's reliability/durability "
            "(qos_overrides of this output)", throttle_duration_sec=WARN_PERIOD_S)
    except Exception as exc:  # noqa: BLE001 - contained like every callback of the node
        node.fault("qos_event", exc)


class OutputPublishers:
    """One publisher per output topic of ``node`` (``by_topic``), ``depth_scale`` and
    ``diagnostics``; an incompatible QoS on any of them calls ``on_incompatible_qos(topic,
    event)``."""

    def __init__(self, node, qos_depth: int,
                 on_incompatible_qos: Callable[[str, object], None]) -> None:
        qos = output_qos(qos_depth)

        def pub(msg_type, topic, depth_qos=qos, overridable=True):
            return output_publisher(node, msg_type, topic, depth_qos, on_incompatible_qos,
                                    overridable)

        self.by_topic = {topic: pub(Image, topic) for topic in IMAGE_TOPICS}
        # image_transport's naming: <the depth image topic, resolved and remapped>/compressedDepth
        self.by_topic.update({names.compressed_depth_topic(image): pub(
            CompressedImage, names.compressed_depth_topic(node.resolve_topic_name(image)))
            for image in names.DEPTH_IMAGE_TOPICS})
        self.by_topic.update({topic: pub(PointCloud2, topic) for topic in CLOUD_TOPICS})
        self.diagnostics = pub(DiagnosticArray, names.DIAGNOSTICS_TOPIC, DIAGNOSTICS_QOS_DEPTH,
                               overridable=False)
        self.by_topic.update({topic: pub(CameraInfo, topic) for topic in CAMERA_INFO_TOPICS})
        self.depth_scale = pub(DiagnosticStatus, names.DEPTH_SCALE_TOPIC, LATCHED_QOS)
        self._diag_lock = threading.Lock()  # one status published at a time, in order

    def publish(self, messages: dict[str, object]) -> None:
        """Each message on its topic, in the order given."""
        for topic, msg in messages.items():
            self.by_topic[topic].publish(msg)

    def publish_statuses(self, statuses: Callable[[], list], stamp: Callable[[], object],
                         node_name: str, hardware_id: str, stopping: Callable[[], bool]) -> None:
        """``statuses()`` in one array on /diagnostics, stamped ``stamp()``, named after
        ``node_name`` (:func:`~sfm_ttr_ros.ros.outputs.diagnostics_message`); a publication
        that fails once ``stopping()`` (the context shut down under it) is let go."""
        with self._diag_lock:
            msg = outputs.diagnostics_message(statuses(), stamp(), node_name, hardware_id)
            try:
                self.diagnostics.publish(msg)
            except Exception as exc:  # context shut down under us
                if not stopping():
                    raise
                del exc
