"""Conversions between ROS 2 messages and the ROS-free core: the only code in the project that
knows ROS message layouts (sensor_msgs Image / CompressedImage / CameraInfo / PointCloud2,
diagnostic_msgs, nav_msgs Odometry).

Importing the package is cheap and needs no ROS: the names are loaded on first use (PEP 562).
Reading (``image_to_numpy``, ``image_to_depth``, ``camera_info_to_intrinsics``,
``stamp_to_ns``) works on any object with the message's fields (rclpy or rosbags messages)
without the ROS message packages; the Image / CameraInfo / Header builders make rclpy messages by
default, or a rosbags type store's with ``classes=typestore_classes(store)`` (the bag tools).
"""

from __future__ import annotations

import importlib

_LOCATIONS = {
    "CameraInfoError": "msg_adapters.camera_info",
    "UncalibratedCameraInfo": "msg_adapters.camera_info",
    "CompressedDepthError": "msg_adapters.compressed_depth",
    "CompressedImageError": "msg_adapters.compressed",
    "ImageConversionError": "msg_adapters.image",
    "MessageClasses": "msg_adapters.classes",
    "ODOMETRY_MSGTYPE": "msg_adapters.odometry",
    "OdometryError": "msg_adapters.odometry",
    "PointCloudError": "msg_adapters.pointcloud",
    "SUPPORTED_ENCODINGS": "msg_adapters.image",
    "camera_info_for": "msg_adapters.camera_info",
    "camera_info_msg": "msg_adapters.camera_info",
    "camera_info_distortion": "msg_adapters.camera_info",
    "rectified_camera_info": "msg_adapters.camera_info",
    "clock_message": "msg_adapters.stamp",
    "compressed_depth_to_depth": "msg_adapters.compressed_depth",
    "compressed_to_rgb8": "msg_adapters.compressed",
    "camera_info_to_intrinsics": "msg_adapters.camera_info",
    "depth_to_colored_image": "msg_adapters.image",
    "depth_to_compressed_depth": "msg_adapters.compressed_depth",
    "depth_to_image": "msg_adapters.image",
    "depth_to_pointcloud2": "msg_adapters.pointcloud",
    "diagnostic_array": "msg_adapters.diagnostics",
    "diagnostic_values": "msg_adapters.diagnostics",
    "format_value": "msg_adapters.diagnostics",
    "image_to_depth": "msg_adapters.image",
    "image_to_numpy": "msg_adapters.image",
    "image_to_rgb8": "msg_adapters.image",
    "intrinsics_to_camera_info": "msg_adapters.camera_info",
    "make_diagnostic_array": "msg_adapters.diagnostics",
    "make_diagnostic_status": "msg_adapters.diagnostics",
    "make_header": "msg_adapters.classes",
    "ns_to_stamp": "msg_adapters.stamp",
    "numpy_to_image": "msg_adapters.image",
    "numpy_to_pointcloud2": "msg_adapters.pointcloud",
    "odometry_msg": "msg_adapters.odometry",
    "odometry_to_pose": "msg_adapters.odometry",
    "odometry_to_position": "msg_adapters.odometry",
    "pack_rgb": "msg_adapters.pointcloud",
    "pointcloud2_to_numpy": "msg_adapters.pointcloud",
    "pointcloud2_to_xyz": "msg_adapters.pointcloud",
    "projection_of": "msg_adapters.camera_info",
    "quaternion_to_rotation": "msg_adapters.odometry",
    "rclpy_classes": "msg_adapters.classes",
    "rgb8_to_compressed": "msg_adapters.compressed",
    "rotation_to_quaternion": "msg_adapters.odometry",
    "scale_camera_info": "msg_adapters.camera_info",
    "stamp_to_ns": "msg_adapters.stamp",
    "stamp_to_seconds": "msg_adapters.stamp",
    "tf_message_class": "msg_adapters.odometry",
    "transform_msg": "msg_adapters.odometry",
    "typestore_classes": "msg_adapters.classes",
    "unpack_rgb": "msg_adapters.pointcloud",
}

__all__ = sorted(_LOCATIONS)


def __getattr__(name: str):
    if name in _LOCATIONS:
        value = getattr(importlib.import_module(_LOCATIONS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'msg_adapters' has no attribute {name!r}")


def __dir__():
    return __all__
