"""The ``refiner`` node's publishers: every output topic (docs/node.md, "Topics"), each depth
image's CameraInfo beside it, and ``/diagnostics``.

:class:`OutputPublishers` creates them (KEEP_LAST ``qos_depth``, reliable; /diagnostics depth
10), publishes the ``{topic: message}`` dicts :mod:`sfm_ttr_ros.ros.outputs` builds, in their
order, and one diagnostics status at a time.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from functools import partial

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image, PointCloud2

from sfm_ttr_ros.ros import names, outputs

DIAGNOSTICS_QOS_DEPTH = 10
IMAGE_TOPICS = (names.DEPTH_TOPIC, names.DEPTH_COLORED_TOPIC, names.DEPTH_REFINED_TOPIC)
CLOUD_TOPICS = (names.POINTS_TOPIC, names.CLOUD_TOPIC)
CAMERA_INFO_TOPICS = (names.DEPTH_INFO_TOPIC, names.DEPTH_COLORED_INFO_TOPIC,
                      names.DEPTH_REFINED_INFO_TOPIC)


class OutputPublishers:
    """One publisher per output topic of ``node`` (``by_topic``) and ``diagnostics``; an
    incompatible QoS on any of them calls ``on_incompatible_qos(topic, event)``."""

    def __init__(self, node, qos_depth: int,
                 on_incompatible_qos: Callable[[str, object], None]) -> None:
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=qos_depth,
                         reliability=ReliabilityPolicy.RELIABLE)

        def pub(msg_type, topic, depth_qos=qos):
            return node.create_publisher(
                msg_type, topic, depth_qos, event_callbacks=PublisherEventCallbacks(
                    incompatible_qos=partial(on_incompatible_qos, topic)))

        self.by_topic = {topic: pub(Image, topic) for topic in IMAGE_TOPICS}
        self.by_topic.update({topic: pub(PointCloud2, topic) for topic in CLOUD_TOPICS})
        self.diagnostics = pub(DiagnosticArray, names.DIAGNOSTICS_TOPIC, DIAGNOSTICS_QOS_DEPTH)
        self.by_topic.update({topic: pub(CameraInfo, topic) for topic in CAMERA_INFO_TOPICS})
        self._diag_lock = threading.Lock()  # one status published at a time, in order

    def publish(self, messages: dict[str, object]) -> None:
        """Each message on its topic, in the order given."""
        for topic, msg in messages.items():
            self.by_topic[topic].publish(msg)

    def publish_status(self, status: Callable[[], object], stamp: Callable[[], object],
                       hardware_id: str, stopping: Callable[[], bool]) -> None:
        """``status()`` on /diagnostics, stamped ``stamp()``; a publication that fails once
        ``stopping()`` (the context shut down under it) is let go."""
        with self._diag_lock:
            msg = outputs.diagnostics_message(status(), stamp(), hardware_id)
            try:
                self.diagnostics.publish(msg)
            except Exception as exc:  # context shut down under us
                if not stopping():
                    raise
                del exc
