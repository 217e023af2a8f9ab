"""The name a frame's image has in COLMAP: in the workspace's image folder, the database, the
map cache and every reconstruction (batch and streaming alike), one rule both ways."""

from __future__ import annotations

IMAGE_SUFFIX = ".png"  # the workspace writes each frame as a PNG image for extraction


def image_name(frame_name: str) -> str:
    """The COLMAP image name of the frame ``frame_name`` (``<name>.png``)."""
    return f"{frame_name}{IMAGE_SUFFIX}"


def frame_name(image_name: str) -> str:
    """The frame name of the COLMAP image ``image_name`` (:func:`image_name` undone)."""
    return image_name.removesuffix(IMAGE_SUFFIX)
