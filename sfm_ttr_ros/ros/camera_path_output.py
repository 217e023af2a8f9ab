"""The camera's path on ``~/odom`` (nav_msgs/Odometry) as the robot base's odometry, and,
when asked, on TF.

The path is the stream's (core/stream/path.py): after each window (the worker thread) the poses
it added (:attr:`~sfm_ttr_ros.core.stream.records.WindowStats.path_poses`) go out, in stamp
order, each with its image's stamp (a window late: docs/node.md), as the pose and twist of the
base ``odom.child_frame_id`` (default ``base_link``) in ``odom.frame_id`` (default
``sfm_odom``), the camera mounted on the base by ``odom.camera_mount``: continuous,
gravity-aligned where the ground was measured, with a covariance that grows with the distance
(core/stream/base_odometry.py, one :class:`BaseOdometry` per topic); with ``odom.publish_tf``
the same pose as the transform odom -> base on ``/tf``. The path is in metres when the
stream's depth is: then on ``~/odom``; a pose in SfM units goes where every output not in
metres goes (:func:`~sfm_ttr_ros.ros.units.topic_now`: ``~/odom_relative``, or nowhere under
``relative_depth: drop``), never on ``~/odom``; there the mount's translation (metres) is left
out, its rotation kept. Both publishers' QoS can be overridden at start-up
(``qos_overrides.<topic>.publisher.*``). This module only turns poses into messages:
"odometry" elsewhere (core/metric/odometry_track.py) is the incoming track the metric scale
reads.

TF needs tf2_msgs, which these PyPI installs lack: ``odom.publish_tf`` true without it stops
the start with a clear error (:func:`msg_adapters.odometry.tf_message_class`).
"""

from __future__ import annotations

from nav_msgs.msg import Odometry

from msg_adapters.odometry import odometry_msg, tf_message_class, transform_msg
from msg_adapters.stamp import stamp_to_ns
from sfm_ttr_ros.core.params.node import NodeSettings
from sfm_ttr_ros.core.stream.base_odometry import BaseOdometry, OdometryPose, parse_camera_mount
from sfm_ttr_ros.core.stream.records import FramePose, WindowStats
from sfm_ttr_ros.ros import names, units
from sfm_ttr_ros.ros.publishers import output_publisher, output_qos

TF_TOPIC = "/tf"
TF_QOS_DEPTH = 100


class CameraPathOutput:
    """``~/odom`` (and ``/tf``) of ``node`` from the stream's camera path (module docstring)."""

    def __init__(self, node, settings: NodeSettings, qos_depth: int) -> None:
        self.frame_id = settings.odom_frame_id
        self.child_frame_id = settings.odom_child_frame_id
        mount = parse_camera_mount(settings.odom_camera_mount)
        unscaled = mount.copy()
        unscaled[:3, 3] = 0.0  # SfM units: the mount's metres do not apply
        self.odometry = {"m": BaseOdometry(mount), "sfm": BaseOdometry(unscaled)}
        self.tf = None
        if settings.odom_publish_tf:
            self.tf = node.create_publisher(tf_message_class(), TF_TOPIC, TF_QOS_DEPTH)
        self.publishers = {topic: output_publisher(node, Odometry, topic, output_qos(qos_depth))
                           for topic in (names.ODOM_OUTPUT_TOPIC,
                                         names.RELATIVE_TWIN[names.ODOM_OUTPUT_TOPIC])}
        self.published = 0

    def window(self, stats: WindowStats, relative: str = "publish") -> None:
        """The poses the window added to the path, each on the topic of its units
        (:func:`~sfm_ttr_ros.ros.units.topic_now`, ``relative`` the ``relative_depth``
        policy), as the base's odometry of that topic."""
        for pose in stats.path_poses:
            odometry = self.odometry[pose.units].add(pose.pose)
            topic = units.topic_now(names.ODOM_OUTPUT_TOPIC, pose.units == "m", relative)
            if topic is not None:
                self._publish(pose, odometry, topic)

    def _publish(self, pose: FramePose, odometry: OdometryPose, topic: str) -> None:
        header = pose.frame.header
        stamp_ns = (round(pose.frame.stamp * 1e9) if header is None
                    else stamp_to_ns(header.stamp))
        T = odometry.odom_from_base
        self.publishers[topic].publish(odometry_msg(
            stamp_ns, self.frame_id, self.child_frame_id, T, covariance=odometry.covariance,
            twist=odometry.twist, twist_covariance=odometry.twist_covariance))
        if self.tf is not None:
            self.tf.publish(self.tf.msg_type(transforms=[transform_msg(
                stamp_ns, self.frame_id, self.child_frame_id, T)]))
        self.published += 1
