"""Names of the ``refiner`` node, its topics and its diagnostics statuses, defined once.

Pure constants (no rclpy): the node, the launch file's test, the demo, the bag tools and the
benchmarks read them from here. Input topics are relative (remap them with ``-r image:=...``);
the outputs are private (``~/``) and resolve under the node's name: ``/refiner/depth/image``
with the default name in the root namespace.

Each depth image follows image_transport's camera-publisher convention: ``<base>/image`` with a
sensor_msgs/CameraInfo on ``<base>/camera_info`` beside it, with the same header (stamp and
frame_id), so that depth_image_proc's CameraSubscriber (exact-stamp pairing) and RViz's
DepthCloud take them as they are. The live and the windowed depth each have their own
``camera_info``: the windowed copy of a frame arrives seconds after the live one.
"""

from __future__ import annotations

from sfm_ttr_ros.core.stream.status import TASKS

PACKAGE = "sfm_ttr_ros"
NODE_NAME = "refiner"

# subscriptions (relative: remappable)
IMAGE_TOPIC = "image"
CAMERA_INFO_TOPIC = "camera_info"
ODOMETRY_TOPIC = "odom"  # nav_msgs/Odometry: the distance travelled (metric.source odometry)
COMPRESSED_SUFFIX = "/compressed"  # image_transport: <image>/compressed carries CompressedImage


def compressed_topic(image_topic: str) -> str:
    """The CompressedImage topic of an image topic (image_transport's naming)."""
    return image_topic.rstrip("/") + COMPRESSED_SUFFIX


def camera_info_beside(image_topic: str) -> str:
    """The CameraInfo topic of a resolved image topic (image_transport's camera subscriber:
    the image topic's namespace + ``/camera_info``; ``/cam/image_raw`` -> ``/cam/camera_info``)."""
    parent = image_topic.rstrip("/").rsplit("/", 1)[0]
    return parent + "/" + CAMERA_INFO_TOPIC


# publications: image_transport's camera publisher, <base>/image + <base>/camera_info
IMAGE_SUFFIX = "/image"
CAMERA_INFO_SUFFIX = "/camera_info"
DEPTH_BASE = "~/depth"  # live: every frame, the newest served weights
DEPTH_TOPIC = DEPTH_BASE + IMAGE_SUFFIX
DEPTH_INFO_TOPIC = DEPTH_BASE + CAMERA_INFO_SUFFIX
DEPTH_COLORED_BASE = "~/depth_colored"  # live, colourised
DEPTH_COLORED_TOPIC = DEPTH_COLORED_BASE + IMAGE_SUFFIX
DEPTH_COLORED_INFO_TOPIC = DEPTH_COLORED_BASE + CAMERA_INFO_SUFFIX
DEPTH_REFINED_BASE = "~/depth_refined"  # each frame again once its window is done
DEPTH_REFINED_TOPIC = DEPTH_REFINED_BASE + IMAGE_SUFFIX
DEPTH_REFINED_INFO_TOPIC = DEPTH_REFINED_BASE + CAMERA_INFO_SUFFIX
CLOUD_TOPIC = "~/cloud"  # the live depth back-projected (outputs: cloud)
POINTS_TOPIC = "~/points"  # the windows' sparse SfM clouds
ODOM_OUTPUT_TOPIC = "~/odom"  # nav_msgs/Odometry: the camera's path in metres (outputs: odom)
ODOM_RELATIVE_TOPIC = "~/odom_relative"  # the same in SfM units, while no metres are known
DIAGNOSTICS_TOPIC = "/diagnostics"

# REP 118: 32FC1 depth is metres (REP 105: so are odom's poses). Depth, clouds, points and the
# camera's path not (yet) in metres go out on a relative twin of their topic (relative_depth:
# publish) or not at all (drop): ros/units.py, topic_now.
DEPTH_RELATIVE_BASE = "~/depth_relative"
DEPTH_RELATIVE_TOPIC = DEPTH_RELATIVE_BASE + IMAGE_SUFFIX
DEPTH_RELATIVE_INFO_TOPIC = DEPTH_RELATIVE_BASE + CAMERA_INFO_SUFFIX
DEPTH_REFINED_RELATIVE_BASE = "~/depth_refined_relative"
DEPTH_REFINED_RELATIVE_TOPIC = DEPTH_REFINED_RELATIVE_BASE + IMAGE_SUFFIX
DEPTH_REFINED_RELATIVE_INFO_TOPIC = DEPTH_REFINED_RELATIVE_BASE + CAMERA_INFO_SUFFIX
CLOUD_RELATIVE_TOPIC = "~/cloud_relative"
POINTS_RELATIVE_TOPIC = "~/points_relative"
#: metric topic -> its relative twin (the outputs in the depth's units): every output that has
#: units (``~/depth_colored`` has none)
RELATIVE_TWIN = {
    DEPTH_TOPIC: DEPTH_RELATIVE_TOPIC, DEPTH_INFO_TOPIC: DEPTH_RELATIVE_INFO_TOPIC,
    DEPTH_REFINED_TOPIC: DEPTH_REFINED_RELATIVE_TOPIC,
    DEPTH_REFINED_INFO_TOPIC: DEPTH_REFINED_RELATIVE_INFO_TOPIC,
    CLOUD_TOPIC: CLOUD_RELATIVE_TOPIC, POINTS_TOPIC: POINTS_RELATIVE_TOPIC,
    ODOM_OUTPUT_TOPIC: ODOM_RELATIVE_TOPIC,
}
#: latched (transient local, depth 1) diagnostic_msgs/DiagnosticStatus: the depth's scale now
DEPTH_SCALE_TOPIC = "~/depth_scale"
COMPRESSED_DEPTH_SUFFIX = "/compressedDepth"  # image_transport: <image>/compressedDepth


def compressed_depth_topic(image_topic: str) -> str:
    """The compressedDepth topic of a depth image topic (image_transport's naming)."""
    return image_topic.rstrip("/") + COMPRESSED_DEPTH_SUFFIX


#: the depth image topics (each may have a compressedDepth twin)
DEPTH_IMAGE_TOPICS = (DEPTH_TOPIC, DEPTH_REFINED_TOPIC, DEPTH_RELATIVE_TOPIC,
                      DEPTH_REFINED_RELATIVE_TOPIC)
RELATIVE_TWIN.update({compressed_depth_topic(metric): compressed_depth_topic(relative)
                      for metric, relative in ((DEPTH_TOPIC, DEPTH_RELATIVE_TOPIC),
                                               (DEPTH_REFINED_TOPIC,
                                                DEPTH_REFINED_RELATIVE_TOPIC))})


def resolve(topic: str, node_name: str = NODE_NAME, namespace: str = "/") -> str:
    """The absolute name of ``topic`` for a node ``node_name`` in ``namespace`` (ROS 2 rules:
    ``~/x`` -> ``<namespace>/<node>/x``, ``x`` -> ``<namespace>/x``, ``/x`` unchanged)."""
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    if topic.startswith("/"):
        return topic
    if topic.startswith("~/"):
        return f"{ns}/{node_name}/{topic[2:]}"
    if topic == "~":
        return f"{ns}/{node_name}"
    return f"{ns}/{topic}"


def status_name(node_name: str, task: str) -> str:
    """A DiagnosticStatus name on /diagnostics as diagnostic_updater gives it: ``<node name>:
    <task>`` (``refiner: stream``), the node's name without its namespace (``get_name()``);
    the hardware_id, the node's fully qualified name, tells apart two nodes of one name in
    different namespaces."""
    return f"{node_name}: {task}"


def relative_twin_of(topic: str) -> str | None:
    """The relative twin of a metric output topic, resolved or not (``/cam1/refiner/depth/image``
    -> ``/cam1/refiner/depth_relative/image``); None for any other topic."""
    for metric, relative in RELATIVE_TWIN.items():
        if topic == metric or (topic.startswith("/") and topic.endswith(metric[1:])):
            return topic[:len(topic) - len(metric) + 1] + relative[1:]
    return None


NODE_FQN = resolve("~")  # "/refiner": the diagnostics' hardware_id
#: task -> the default node's status name on /diagnostics ("stream" -> "refiner: stream")
DIAG_NAMES = {task: status_name(NODE_NAME, task) for task in TASKS}
DEPTH_TOPIC_RESOLVED = resolve(DEPTH_TOPIC)  # "/refiner/depth/image"
DEPTH_INFO_TOPIC_RESOLVED = resolve(DEPTH_INFO_TOPIC)  # "/refiner/depth/camera_info"
DEPTH_COLORED_TOPIC_RESOLVED = resolve(DEPTH_COLORED_TOPIC)
DEPTH_COLORED_INFO_TOPIC_RESOLVED = resolve(DEPTH_COLORED_INFO_TOPIC)
DEPTH_REFINED_TOPIC_RESOLVED = resolve(DEPTH_REFINED_TOPIC)  # "/refiner/depth_refined/image"
DEPTH_REFINED_INFO_TOPIC_RESOLVED = resolve(DEPTH_REFINED_INFO_TOPIC)
CLOUD_TOPIC_RESOLVED = resolve(CLOUD_TOPIC)  # "/refiner/cloud"
POINTS_TOPIC_RESOLVED = resolve(POINTS_TOPIC)
DEPTH_RELATIVE_TOPIC_RESOLVED = resolve(DEPTH_RELATIVE_TOPIC)  # "/refiner/depth_relative/image"
DEPTH_REFINED_RELATIVE_TOPIC_RESOLVED = resolve(DEPTH_REFINED_RELATIVE_TOPIC)
DEPTH_SCALE_TOPIC_RESOLVED = resolve(DEPTH_SCALE_TOPIC)  # "/refiner/depth_scale"
ODOM_OUTPUT_TOPIC_RESOLVED = resolve(ODOM_OUTPUT_TOPIC)  # "/refiner/odom"
ODOM_RELATIVE_TOPIC_RESOLVED = resolve(ODOM_RELATIVE_TOPIC)
