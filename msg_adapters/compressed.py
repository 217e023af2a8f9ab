"""sensor_msgs/CompressedImage <-> numpy: JPEG / PNG through OpenCV, the image_transport
``compressed`` convention (ros-perception/image_transport_plugins, compressed_image_transport).

``format`` is ``"<encoding>; <jpeg|png> compressed <order>"`` (e.g. ``"rgb8; jpeg compressed
bgr8"``): the image's own encoding, the codec, and the channel order of the pixels that were
compressed. OpenCV decodes a colour image into the order it was given when encoding, so the
decoded array is BGR for ``compressed bgr8`` (what compressed_image_transport writes for colour
images), RGB for ``compressed rgb8``, and BGR for an old bare ``"jpeg"`` / ``"png"`` format
(OpenCV's own order) - as compressed_subscriber.cpp reverts it. Mono images decode as one
channel; 16-bit PNGs are reduced to 8 bits by ``>> 8`` like mono16 Images; alpha is dropped.

Refused with :class:`CompressedImageError` (an :class:`~sfm_ttr_ros.core.frames.InputError`):
empty data, data that is neither JPEG nor PNG, ``compressedDepth`` (a depth map, not an
image), a declared size of zero or above :data:`MAX_PIXELS` (read from the PNG / JPEG header
BEFORE decoding, so a small message cannot make the decoder allocate gigabytes), and data
OpenCV cannot decode.
"""

from __future__ import annotations

import cv2
import numpy as np

from msg_adapters.classes import MessageClasses, empty_header, rclpy_classes
from sfm_ttr_ros.core.errors import InputError

MAX_PIXELS = 64 * 1024 * 1024  # declared width x height above this: refused before decoding
JPEG_QUALITY = 95  # compressed_image_transport's (ROS 2) default jpeg_quality
PNG_LEVEL = 3  # its default png_level
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


class CompressedImageError(InputError):
    """A sensor_msgs/CompressedImage that cannot be decoded into an image."""


def _png_size(b: bytes) -> tuple[int, int] | None:
    if len(b) < 24 or b[12:16] != b"IHDR":
        return None
    return int.from_bytes(b[16:20], "big"), int.from_bytes(b[20:24], "big")


def _jpeg_size(b: bytes) -> tuple[int, int] | None:
    """(width, height) of the first start-of-frame segment, walking the JPEG markers."""
    i, n = 2, len(b)
    while i + 4 <= n:
        if b[i] != 0xFF:
            return None
        marker = b[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0x01, 0xD8) or 0xD0 <= marker <= 0xD7:  # no length field
            i += 2
            continue
        if marker in _JPEG_SOF:
            if i + 9 > n:
                return None
            return int.from_bytes(b[i + 7:i + 9], "big"), int.from_bytes(b[i + 5:i + 7], "big")
        i += 2 + int.from_bytes(b[i + 2:i + 4], "big")
    return None


def declared_size(data: bytes) -> tuple[str, int, int]:
    """(codec, width, height) as the JPEG / PNG header declares them; CompressedImageError for
    anything else."""
    if data[:8] == _PNG_MAGIC:
        codec, size = "png", _png_size(data)
    elif data[:2] == b"\xff\xd8":
        codec, size = "jpeg", _jpeg_size(data)
    else:
        raise CompressedImageError(f"compressed data is neither JPEG nor PNG (starts with "
                                   f"{data[:8].hex() or 'nothing'})")
    if size is None:
        raise CompressedImageError(f"truncated or corrupt {codec} header: no image size")
    return codec, size[0], size[1]


def compressed_order(fmt: str) -> str:
    """The channel order (``"rgb"`` or ``"bgr"``) OpenCV's decoder returns for ``format``."""
    _, sep, tail = str(fmt).partition(";")
    return "rgb" if sep and "compressed rgb" in tail.lower() else "bgr"


def compressed_to_rgb8(msg) -> np.ndarray:
    """Decode a CompressedImage (JPEG / PNG) into H x W x 3 uint8 RGB (module docstring)."""
    fmt = str(msg.format)
    if "compresseddepth" in fmt.lower():
        raise CompressedImageError(f"format {fmt!r} is a compressed depth map, not an image")
    data = bytes(msg.data)
    if not data:
        raise CompressedImageError("CompressedImage has no data")
    codec, w, h = declared_size(data)
    if w <= 0 or h <= 0 or w * h > MAX_PIXELS:
        raise CompressedImageError(f"{codec} declares a {w}x{h} image: zero or above the "
                                   f"{MAX_PIXELS} pixels accepted")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise CompressedImageError(f"undecodable {codec} data ({len(data)} bytes, format "
                                   f"{fmt!r})")
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise CompressedImageError(f"{codec} decoded to {img.dtype}, not 8 or 16 bits")
    if img.ndim == 2 or img.shape[2] == 1:
        return np.repeat(img.reshape(img.shape[0], img.shape[1], 1), 3, axis=2)
    if img.shape[2] not in (3, 4):
        raise CompressedImageError(f"{codec} decoded to {img.shape[2]} channels")
    rgb = img[:, :, :3] if compressed_order(fmt) == "rgb" else img[:, :, 2::-1]
    return np.ascontiguousarray(rgb)


def rgb8_to_compressed(rgb: np.ndarray, codec: str = "jpeg", header=None, *,
                       classes: MessageClasses | None = None,
                       quality: int = JPEG_QUALITY):
    """An H x W x 3 uint8 RGB image as a CompressedImage the way compressed_image_transport
    writes a colour image: pixels compressed in BGR order, format ``"rgb8; <codec> compressed
    bgr8"``. ``codec``: ``"jpeg"`` (``quality`` 1-100) or ``"png"``. ``classes`` as in
    :func:`msg_adapters.image.numpy_to_image` (rclpy's by default, a rosbags type store's for
    bags)."""
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8 or 0 in a.shape:
        raise CompressedImageError(f"need a non-empty H x W x 3 uint8 RGB array, got "
                                   f"{a.shape} {a.dtype}")
    if codec == "jpeg":
        ok, buf = cv2.imencode(".jpg", a[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    elif codec == "png":
        ok, buf = cv2.imencode(".png", a[:, :, ::-1], [cv2.IMWRITE_PNG_COMPRESSION, PNG_LEVEL])
    else:
        raise CompressedImageError(f"codec must be jpeg or png, got {codec!r}")
    if not ok:
        raise CompressedImageError(f"OpenCV could not encode the image as {codec}")
    c = classes or rclpy_classes()
    if c.compressed_image is None:
        raise CompressedImageError("these message classes have no CompressedImage")
    return c.compressed_image(header=empty_header(c) if header is None else header,
                              format=f"rgb8; {codec} compressed bgr8",
                              data=c.bytes_field(np.ascontiguousarray(buf).reshape(-1)))
