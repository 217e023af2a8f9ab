"""Conversions between ROS 2 messages and the ROS-free core: the only code in the project that
knows ROS message layouts (sensor_msgs Image / CameraInfo / PointCloud2, diagnostic_msgs)."""

from msg_adapters.camera_info import (
    CameraInfoError,
    camera_info_to_intrinsics,
    intrinsics_to_camera_info,
)
from msg_adapters.diagnostics import diagnostic_values, format_value, make_diagnostic_array
from msg_adapters.image import (
    SUPPORTED_ENCODINGS,
    ImageConversionError,
    depth_to_colored_image,
    depth_to_image,
    image_to_numpy,
    image_to_rgb8,
    numpy_to_image,
)
from msg_adapters.pointcloud import (
    PointCloudError,
    numpy_to_pointcloud2,
    pointcloud2_to_numpy,
    pointcloud2_to_xyz,
)

__all__ = [
    "SUPPORTED_ENCODINGS",
    "CameraInfoError",
    "ImageConversionError",
    "PointCloudError",
    "camera_info_to_intrinsics",
    "depth_to_colored_image",
    "depth_to_image",
    "diagnostic_values",
    "format_value",
    "image_to_numpy",
    "image_to_rgb8",
    "intrinsics_to_camera_info",
    "make_diagnostic_array",
    "numpy_to_image",
    "numpy_to_pointcloud2",
    "pointcloud2_to_numpy",
    "pointcloud2_to_xyz",
]
