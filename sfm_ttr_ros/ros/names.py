"""Names of the ``refiner`` node, its topics and its diagnostics status, defined once.

Pure constants (no rclpy): the node, the launch file's test, the demo, the bag tools and the
benchmarks read them from here. Input topics are relative (remap them with ``-r image:=...``);
the outputs are private (``~/``) and resolve under the node's name: ``/refiner/depth`` with the
default name in the root namespace.
"""

from __future__ import annotations

PACKAGE = "sfm_ttr_ros"
NODE_NAME = "refiner"
DIAG_NAME = f"{PACKAGE}: {NODE_NAME}"  # the DiagnosticStatus name on /diagnostics

# subscriptions (relative: remappable)
IMAGE_TOPIC = "image"
CAMERA_INFO_TOPIC = "camera_info"
COMPRESSED_SUFFIX = "/compressed"  # image_transport: <image>/compressed carries CompressedImage


def compressed_topic(image_topic: str) -> str:
    """The CompressedImage topic of an image topic (image_transport's naming)."""
    return image_topic.rstrip("/") + COMPRESSED_SUFFIX

# publications
DEPTH_TOPIC = "~/depth"  # live: every frame, the newest served weights
DEPTH_COLORED_TOPIC = "~/depth_colored"  # live, colourised
DEPTH_REFINED_TOPIC = "~/depth_refined"  # each frame again once its window is done
POINTS_TOPIC = "~/points"
DIAGNOSTICS_TOPIC = "/diagnostics"


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


NODE_FQN = resolve("~")  # "/refiner": the diagnostics' hardware_id
DEPTH_TOPIC_RESOLVED = resolve(DEPTH_TOPIC)  # "/refiner/depth"
DEPTH_COLORED_TOPIC_RESOLVED = resolve(DEPTH_COLORED_TOPIC)
DEPTH_REFINED_TOPIC_RESOLVED = resolve(DEPTH_REFINED_TOPIC)  # "/refiner/depth_refined"
POINTS_TOPIC_RESOLVED = resolve(POINTS_TOPIC)
