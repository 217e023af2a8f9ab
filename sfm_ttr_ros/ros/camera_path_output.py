"""The camera's path on ``~/odom`` (nav_msgs/Odometry) and, when asked, on TF.

The path is the stream's (core/stream/path.py): after each window (the worker thread) the poses
it added (:attr:`~sfm_ttr_ros.core.stream.records.WindowStats.path_poses`) go out, in stamp
order, each with its image's stamp, in ``odom.frame_id`` (REP 105's ``odom``, default "odom")
with ``child_frame_id`` the image's frame (``odom.child_frame_id``, or the image header's
frame_id when empty) and the pose's covariance from the reconstruction (core/camera_path.py
says what it is); with ``odom.publish_tf`` the same pose as the transform ``odom`` -> the
camera's frame on ``/tf``. The path is in metres when the stream's depth is: then on
``~/odom``; a pose in SfM units goes where every output not in metres goes
(:func:`~sfm_ttr_ros.ros.units.topic_now`: ``~/odom_relative``, or nowhere under
``relative_depth: drop``), never on ``~/odom``. The twist is not estimated (zero). Both
publishers' QoS can be overridden at start-up (``qos_overrides.<topic>.publisher.*``). This
module only turns poses into messages: "odometry" elsewhere (core/metric/odometry_track.py) is the
incoming track the metric scale reads.

TF needs tf2_msgs, which these PyPI installs lack: ``odom.publish_tf`` true without it stops
the start with a clear error (:func:`msg_adapters.odometry.tf_message_class`).
"""

from __future__ import annotations

from nav_msgs.msg import Odometry

from msg_adapters.odometry import odometry_msg, tf_message_class, transform_msg
from msg_adapters.stamp import stamp_to_ns
from sfm_ttr_ros.core.params.node import NodeSettings
from sfm_ttr_ros.core.stream.records import FramePose, WindowStats
from sfm_ttr_ros.ros import names, units
from sfm_ttr_ros.ros.publishers import output_publisher, output_qos

TF_TOPIC = "/tf"
TF_QOS_DEPTH = 100
DEFAULT_CHILD_FRAME = "camera"  # when neither the parameter nor the image names one


class CameraPathOutput:
    """``~/odom`` (and ``/tf``) of ``node`` from the stream's camera path (module docstring)."""

    def __init__(self, node, settings: NodeSettings, qos_depth: int) -> None:
        self.frame_id = settings.odom_frame_id
        self.child_frame_id = settings.odom_child_frame_id
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
        policy)."""
        for pose in stats.path_poses:
            topic = units.topic_now(names.ODOM_OUTPUT_TOPIC, pose.units == "m", relative)
            if topic is not None:
                self._publish(pose, topic)

    def _publish(self, pose: FramePose, topic: str) -> None:
        header = pose.frame.header
        stamp_ns = (round(pose.frame.stamp * 1e9) if header is None
                    else stamp_to_ns(header.stamp))
        image_frame_id = "" if header is None else str(header.frame_id)
        child = self.child_frame_id or image_frame_id or DEFAULT_CHILD_FRAME
        T = pose.pose.odom_from_camera
        self.publishers[topic].publish(odometry_msg(stamp_ns, self.frame_id, child, T,
                                                    covariance=pose.pose.covariance()))
        if self.tf is not None:
            self.tf.publish(self.tf.msg_type(transforms=[transform_msg(
                stamp_ns, self.frame_id, child, T)]))
        self.published += 1
