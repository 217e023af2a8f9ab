"""The ``refiner`` node's inputs: the image (raw, or image_transport's ``<image>/compressed``),
``camera_info`` and ``odom``, on one QoS (docs/node.md, "QoS").

The CameraInfo comes from beside the image, as image_transport's camera subscriber takes it
(:func:`camera_info_topic`): ``-r image:=/cam/image_raw`` brings ``/cam/camera_info``; a remap
of ``camera_info`` itself still wins.

The QoS is KEEP_LAST ``qos_depth`` with ``qos_reliability``: reliable by default, so a
publisher with ROS's default QoS repairs what the transport loses (docs/decisions.md, "A ROS
citizen on any camera": a best-effort reader lost 26 of 30 real-size frames at 10 Hz);
best_effort takes best-effort publishers too. ``--ros-args`` QoS overrides may change it
(``QoSOverridingOptions``); an incompatible QoS on an input calls the node's handler with the
topic, and :func:`incompatible_input_message` says how to fix it.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from functools import partial
from typing import NamedTuple

from nav_msgs.msg import Odometry
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from sfm_ttr_ros.core.params.node import NodeSettings
from sfm_ttr_ros.core.stream.throttle import WARN_PERIOD_S
from sfm_ttr_ros.ros import names


class Input(NamedTuple):
    """One subscription: its message type, topic and callback."""

    msg_type: type
    topic: str
    callback: Callable


def input_qos(settings: NodeSettings) -> QoSProfile:
    """KEEP_LAST ``qos_depth``, best effort or reliable as ``qos_reliability`` says."""
    reliability = (ReliabilityPolicy.BEST_EFFORT if settings.qos_reliability == "best_effort"
                   else ReliabilityPolicy.RELIABLE)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(settings.qos_depth),
                      reliability=reliability)


def image_input(node, settings: NodeSettings, on_image: Callable,
                on_compressed: Callable) -> Input:
    """The image subscription: ``image`` (sensor_msgs/Image), or with ``image_transport:
    compressed`` the CompressedImage on ``<resolved image>/compressed``."""
    if settings.image_transport == "compressed":
        return Input(CompressedImage, names.compressed_topic(
            node.resolve_topic_name(names.IMAGE_TOPIC)), on_compressed)
    return Input(Image, names.IMAGE_TOPIC, on_image)


def subscribe(node, inputs: list[Input], qos: QoSProfile,
              on_incompatible_qos: Callable[[str, object], None]) -> None:
    """Create each input's subscription on ``qos`` (overridable by ``--ros-args``; each on a
    copy: rclpy writes a topic's overrides into the profile it is given)."""
    overrides = QoSOverridingOptions.with_default_policies()
    for msg_type, topic, callback in inputs:
        node.create_subscription(
            msg_type, topic, callback, copy.copy(qos), qos_overriding_options=overrides,
            event_callbacks=SubscriptionEventCallbacks(
                incompatible_qos=partial(on_incompatible_qos, topic)))


def camera_info_topic(node) -> str:
    """The CameraInfo topic: ``camera_info`` as remapped when it was remapped (its resolution
    differs from its plain expansion), else image_transport's rule, the resolved image topic's
    namespace + ``/camera_info`` (``-r image:=/cam/image_raw`` -> ``/cam/camera_info``). The
    relative name itself when that is where it resolves anyway (no remap at all): a remap
    rule applies to the relative name only, so an absolute name is given only when derived."""
    plain = node.resolve_topic_name(names.CAMERA_INFO_TOPIC, only_expand=True)
    remapped = node.resolve_topic_name(names.CAMERA_INFO_TOPIC)
    if remapped != plain:
        return remapped
    beside = names.camera_info_beside(node.resolve_topic_name(names.IMAGE_TOPIC))
    return names.CAMERA_INFO_TOPIC if beside == plain else beside


def input_refused(node, topic: str, event) -> None:
    """An input of ``node`` (the refiner) refused a publisher: counted (``qos_incompatible``)
    and an ERROR naming the fix (:func:`incompatible_input_message`), throttled; an exception
    here is a fault of ``qos_event``."""
    try:
        node.diagnostics.qos_event(topic)
        node.get_logger().error(incompatible_input_message(
            node.resolve_topic_name(topic), getattr(event, "last_policy_kind", "?"),
            event.total_count), throttle_duration_sec=WARN_PERIOD_S)
    except Exception as exc:  # noqa: BLE001 - contained like every callback of the node
        node.fault("qos_event", exc)


def incompatible_input_message(topic: str, policy: object, count: int) -> str:
    """The ERROR of an input that refused a publisher (``topic`` resolved): a best-effort
    driver (REP 2003's sensor-data QoS) against the reliable default, and the two fixes."""
    return (f"incompatible QoS on input {topic} (policy {policy}, {count} so far): its publisher "
            f"does not offer this subscription's QoS - a best-effort (sensor-data) driver "
            f"needs `-p qos_overrides.{topic}.subscription.reliability:=best_effort` (or "
            f"`-p qos_reliability:=best_effort` for every input); until then no message of it "
            f"arrives")


def camera_and_odometry(on_camera_info: Callable, on_odometry: Callable,
                        camera_info: str = names.CAMERA_INFO_TOPIC) -> list[Input]:
    """The CameraInfo (on ``camera_info``: :func:`camera_info_topic`) and ``odom``
    subscriptions."""
    return [Input(CameraInfo, camera_info, on_camera_info),
            Input(Odometry, names.ODOMETRY_TOPIC, on_odometry)]
