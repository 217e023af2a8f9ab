"""The camera's path on ``~/odom`` (nav_msgs/Odometry) and, when asked, on TF.

:class:`OdomOutput` keeps the stream's :class:`~sfm_ttr_ros.core.camera_path.CameraPath`: after
each window (the worker thread) its registered frames are chained onto the path and the frames
new to it go out on ``~/odom``, in stamp order, each with its image's stamp, in
``odom.frame_id`` (REP 105's ``odom``, default "odom") with ``child_frame_id`` the image's
frame (``odom.child_frame_id``, or the image header's frame_id when empty) and the pose's
covariance from the reconstruction (core/camera_path.py says what it is); with
``odom.publish_tf`` the same pose as the transform ``odom`` -> the camera's frame on ``/tf``.
Metres when the first window's metric scale is known (core/metric): ``~/odom``; otherwise the
path is in the first reconstruction's SfM units and goes out on ``~/odom_relative`` instead
(REP 105 frames are in metres; the depth outputs' units contract, docs/node.md), never on
``~/odom`` (``units`` in :meth:`OdomOutput.summary`). The twist is not estimated (zero). Both
publishers' QoS can be overridden at start-up (``qos_overrides.<topic>.publisher.*``).

TF needs tf2_msgs, which these PyPI installs lack: ``odom.publish_tf`` true without it stops
the start with a clear error (:func:`msg_adapters.odometry.tf_message_class`).
"""

from __future__ import annotations

import threading
from collections import OrderedDict

from nav_msgs.msg import Odometry

from msg_adapters.odometry import odometry_msg, tf_message_class, transform_msg
from msg_adapters.stamp import stamp_to_ns
from sfm_ttr_ros.core.camera_path import CameraPath, PathPose, result_poses
from sfm_ttr_ros.core.frames import Frame
from sfm_ttr_ros.core.params.node import NodeSettings
from sfm_ttr_ros.core.stream.records import WindowStats
from sfm_ttr_ros.ros import names
from sfm_ttr_ros.ros.publishers import output_publisher, output_qos

TF_TOPIC = "/tf"
TF_QOS_DEPTH = 100
#: The frames remembered for the windows to come (their stamps and frame ids): far more than a
#: window holds, bounded for a long run.
MAX_FRAMES = 1000
DEFAULT_CHILD_FRAME = "camera"  # when neither the parameter nor the image names one


class OdomOutput:
    """``~/odom`` (and ``/tf``) of ``node`` from the windows' camera poses (module docstring)."""

    def __init__(self, node, settings: NodeSettings, qos_depth: int) -> None:
        self.frame_id = settings.odom_frame_id
        self.child_frame_id = settings.odom_child_frame_id
        self.tf = None
        if settings.odom_publish_tf:
            self.tf = node.create_publisher(tf_message_class(), TF_TOPIC, TF_QOS_DEPTH)
        self.publishers = {units: output_publisher(node, Odometry, topic, output_qos(qos_depth))
                           for units, topic in (("m", names.ODOM_OUTPUT_TOPIC),
                                                ("sfm", names.ODOM_RELATIVE_TOPIC))}
        self.path = CameraPath()
        self.published = 0
        self._frames: OrderedDict[str, tuple[int, str]] = OrderedDict()
        self._lock = threading.Lock()  # frames are seen on the worker and the live thread

    def frame_seen(self, frame: Frame) -> None:
        """Remember a frame's stamp (ns) and frame id for the window that registers it."""
        header = frame.header
        stamp_ns = (round(frame.stamp * 1e9) if header is None
                    else stamp_to_ns(header.stamp))
        frame_id = "" if header is None else str(header.frame_id)
        with self._lock:
            self._frames[frame.name] = (stamp_ns, frame_id)
            self._frames.move_to_end(frame.name)
            while len(self._frames) > MAX_FRAMES:
                self._frames.popitem(last=False)

    def window(self, stats: WindowStats, metres_per_unit: float | None,
               publish: bool, relative: str = "publish") -> list[PathPose]:
        """Chain the window onto the path; its new poses on ``~/odom`` (and ``/tf``) when
        ``publish``; a path not in metres on ``~/odom_relative``, or nowhere under
        ``relative`` drop (the depth outputs' rule, ``relative_depth``)."""
        with self._lock:
            known = dict(self._frames)
        poses = result_poses(stats.result, {n: known[n][0] * 1e-9 for n in known},
                             metres_per_unit)
        added = [] if poses is None else self.path.add(poses)
        if publish and (self.path.units == "m" or relative != "drop"):
            for pose in added:
                self._publish(pose, *known[pose.name])
        return added

    def _publish(self, pose: PathPose, stamp_ns: int, image_frame_id: str) -> None:
        child = self.child_frame_id or image_frame_id or DEFAULT_CHILD_FRAME
        self.publishers[self.path.units].publish(odometry_msg(stamp_ns, self.frame_id, child,
                                            pose.odom_from_camera,
                                            covariance=pose.covariance()))
        if self.tf is not None:
            self.tf.publish(self.tf.msg_type(transforms=[transform_msg(
                stamp_ns, self.frame_id, child, pose.odom_from_camera)]))
        self.published += 1

    def summary(self) -> dict[str, object]:
        """The path's units, poses, chaining and breaks, and the messages published."""
        return {**self.path.summary(), "published": self.published}
