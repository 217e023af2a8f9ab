"""Which message classes the builders of msg_adapters instantiate, and the std_msgs/Header.

rclpy's generated classes (``sensor_msgs.msg.Image``, ...) and the classes of a `rosbags
<https://gitlab.com/ternaris/rosbags>`_ type store (the bag tools, which run without ROS) have
the same fields and serialize to the same CDR bytes, but hold array fields differently: rclpy
wants ``array.array('B')`` for uint8[] (assigning numpy is 100-200 ms per KITTI image, the
setter checks element by element) and Python lists for float64[]; rosbags wants numpy arrays.
A :class:`MessageClasses` carries the classes and those two conversions, so that one builder
(:func:`msg_adapters.image.numpy_to_image`, :func:`msg_adapters.camera_info.camera_info_msg`,
:func:`make_header`) fills the fields for both. Nothing here imports ROS at module level.
"""

from __future__ import annotations

import array
import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from msg_adapters.stamp import NS_PER_S
from sfm_ttr_ros.core.errors import InputError


@dataclass(frozen=True)
class MessageClasses:
    """The classes of the messages the builders make, and how array fields are held."""

    time: type  # builtin_interfaces/msg/Time
    header: type  # std_msgs/msg/Header
    image: type  # sensor_msgs/msg/Image
    camera_info: type  # sensor_msgs/msg/CameraInfo
    region_of_interest: type  # sensor_msgs/msg/RegionOfInterest
    bytes_field: Callable[[np.ndarray], Any]  # contiguous uint8 array -> a uint8[] value
    doubles_field: Callable[[np.ndarray], Any]  # float64 array -> a float64[] / float64[N] value
    compressed_image: type | None = None  # sensor_msgs/msg/CompressedImage


@functools.cache
def rclpy_classes() -> MessageClasses:
    """The classes of the ROS 2 message packages (what rclpy publishes and subscribes)."""
    from builtin_interfaces.msg import Time
    from sensor_msgs.msg import CameraInfo, CompressedImage, Image, RegionOfInterest
    from std_msgs.msg import Header

    return MessageClasses(
        time=Time, header=Header, image=Image, camera_info=CameraInfo,
        region_of_interest=RegionOfInterest,
        bytes_field=lambda a: array.array("B", a.tobytes()),
        doubles_field=lambda a: np.asarray(a, np.float64).ravel().tolist(),
        compressed_image=CompressedImage,
    )


def typestore_classes(store) -> MessageClasses:
    """The classes of a rosbags type store (``rosbags.typesys.get_typestore(...)``)."""
    types = store.types
    return MessageClasses(
        time=types["builtin_interfaces/msg/Time"], header=types["std_msgs/msg/Header"],
        image=types["sensor_msgs/msg/Image"], camera_info=types["sensor_msgs/msg/CameraInfo"],
        region_of_interest=types["sensor_msgs/msg/RegionOfInterest"],
        bytes_field=lambda a: np.ascontiguousarray(a).view(np.uint8).reshape(-1),
        doubles_field=lambda a: np.asarray(a, np.float64).reshape(-1),
        compressed_image=types["sensor_msgs/msg/CompressedImage"],
    )


def make_header(stamp_ns: int, frame_id: str, classes: MessageClasses | None = None):
    """A std_msgs/Header stamped ``stamp_ns`` (integer nanoseconds, >= 0) in ``frame_id``;
    rclpy's class unless ``classes`` says otherwise."""
    ns = int(stamp_ns)
    if ns < 0:
        raise InputError(f"negative stamp {ns} ns cannot be a ROS time")
    c = classes or rclpy_classes()
    return c.header(stamp=c.time(sec=ns // NS_PER_S, nanosec=ns % NS_PER_S),
                    frame_id=str(frame_id))


def empty_header(classes: MessageClasses | None = None):
    """A Header with a zero stamp and no frame id (the default of an unset header)."""
    return make_header(0, "", classes)
