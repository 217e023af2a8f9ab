"""sensor_msgs/Image <-> numpy, without cv_bridge.

Supported encodings (``sensor_msgs/image_encodings.hpp`` names): rgb8, bgr8, rgba8, bgra8,
mono8, mono16, 8UC1 (read like mono8), 8UC3 (read like bgr8), 16UC1 and 32FC1. Row padding
(``step`` > width x bytes per pixel) and ``is_bigendian`` are honoured when reading; messages
written here are unpadded and little-endian.

Malformed messages are refused the way cv_bridge refuses them (ros-perception/vision_opencv,
``cv_bridge/src/cv_bridge.cpp``): encoding names are matched exactly, case included
(``getCvType`` compares with the ``image_encodings`` constants: ``RGB8`` is an
"Unrecognized image encoding"), and the data must hold exactly ``step x height`` bytes
(``matFromImage``: "Image is wrongly formed: height * step != size"), so truncated AND
over-long data are both errors. Every refusal is an :class:`ImageConversionError`.

The builders make rclpy messages by default, or those of a rosbags type store when given its
:class:`~msg_adapters.classes.MessageClasses` (the bag tools): same fields, same CDR bytes.
Filling ``msg.data``: the builders assign ``array.array('B', arr.tobytes())``, which the
rosidl setter takes as a whole, never a numpy array or memoryview (which it checks element by
element, orders of magnitude slower). Reading goes through ``np.frombuffer`` and always
returns a copy, so the message can be reused or resized afterwards.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from msg_adapters.classes import MessageClasses, empty_header, rclpy_classes
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.visualize import colorize_depth

if TYPE_CHECKING:  # decoding is duck-typed (rclpy and rosbags messages); only encoding needs ROS
    from sensor_msgs.msg import Image
    from std_msgs.msg import Header


class ImageConversionError(InputError):
    """A sensor_msgs/Image that cannot be converted (or an array that cannot be sent)."""


@dataclass(frozen=True)
class _Enc:
    dtype: np.dtype  # element type, native byte order
    channels: int

    @property
    def bytes_per_pixel(self) -> int:
        return self.dtype.itemsize * self.channels


_U8, _U16, _F32 = np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.float32)
ENCODINGS: dict[str, _Enc] = {
    "rgb8": _Enc(_U8, 3),
    "bgr8": _Enc(_U8, 3),
    "rgba8": _Enc(_U8, 4),
    "bgra8": _Enc(_U8, 4),
    "mono8": _Enc(_U8, 1),
    "8UC1": _Enc(_U8, 1),
    "8UC3": _Enc(_U8, 3),
    "mono16": _Enc(_U16, 1),
    "16UC1": _Enc(_U16, 1),
    "32FC1": _Enc(_F32, 1),
}
SUPPORTED_ENCODINGS = tuple(ENCODINGS)


def _encoding(name: str) -> tuple[str, _Enc]:
    """The encoding named exactly ``name`` (case-sensitive, as cv_bridge's getCvType)."""
    enc = ENCODINGS.get(name) if isinstance(name, str) else None
    if enc is None:
        near = [k for k in ENCODINGS if isinstance(name, str) and k.lower() == name.lower()]
        hint = f" (encoding names are case-sensitive: did you mean {near[0]!r}?)" if near else ""
        raise ImageConversionError(
            f"unsupported image encoding {name!r}{hint}; supported: "
            f"{', '.join(SUPPORTED_ENCODINGS)}"
        )
    return name, enc


def image_to_numpy(msg: Image) -> np.ndarray:
    """Decode an Image into H x W (one channel) or H x W x C, in the message's own channel order
    and element type (uint8, uint16 or float32, native byte order). Always a copy."""
    name, enc = _encoding(msg.encoding)
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0:
        raise ImageConversionError(f"{name} image has zero size: width={w}, height={h}")
    row_bytes = w * enc.bytes_per_pixel
    if step < row_bytes:
        raise ImageConversionError(
            f"{name} image step {step} is smaller than width x bytes per pixel = "
            f"{w} x {enc.bytes_per_pixel} = {row_bytes}"
        )
    expected = step * h
    got = len(msg.data)
    if got != expected:
        what = "truncated" if got < expected else "over-long"
        raise ImageConversionError(
            f"{what} {name} image {w}x{h}: expected step x height = {step} x {h} = "
            f"{expected} bytes, got {got}"
        )
    buf = np.frombuffer(msg.data, dtype=np.uint8, count=expected)
    rows = buf.reshape(h, step)[:, :row_bytes]
    src_dtype = enc.dtype.newbyteorder(">" if msg.is_bigendian else "<")
    if step == row_bytes:
        rows = rows.reshape(-1)
    else:
        rows = np.ascontiguousarray(rows)
    out = rows.view(src_dtype).astype(enc.dtype, copy=True)  # copy + native byte order
    shape = (h, w) if enc.channels == 1 else (h, w, enc.channels)
    return out.reshape(shape)


def image_to_rgb8(msg: Image) -> np.ndarray:
    """Decode a colour or mono Image into H x W x 3 uint8 RGB (contiguous).

    rgba8 / bgra8 drop alpha; mono8 / 8UC1 are repeated into 3 channels; mono16 / 16UC1 are
    reduced to 8 bits by ``>> 8`` (a fixed mapping: the same raw value gives the same grey in
    every frame, unlike per-frame max scaling). 32FC1 is not a colour image and is refused.
    """
    name, enc = _encoding(msg.encoding)
    if enc.dtype == _F32:
        raise ImageConversionError(
            f"{name} is not a colour or mono image encoding; cannot convert it to rgb8"
        )
    a = image_to_numpy(msg)
    if name == "rgb8":
        return a
    if name in ("bgr8", "8UC3"):
        return np.ascontiguousarray(a[:, :, ::-1])
    if name == "rgba8":
        return np.ascontiguousarray(a[:, :, :3])
    if name == "bgra8":
        return np.ascontiguousarray(a[:, :, 2::-1])
    if name in ("mono16", "16UC1"):
        a = (a >> 8).astype(np.uint8)
    return np.repeat(a[:, :, None], 3, axis=2)  # mono8 / 8UC1 / reduced mono16


def image_to_depth(msg: Image) -> np.ndarray:
    """Decode a depth Image into float32 metres (NaN / 0 = none), REP 118: ``32FC1`` metres as
    they are; ``16UC1`` / ``mono16`` millimetres, with 0 (no measurement) becoming NaN."""
    name, _ = _encoding(msg.encoding)
    if name not in ("32FC1", "16UC1", "mono16"):
        raise ImageConversionError(
            f"a depth image must be 32FC1 (metres) or 16UC1 (millimetres), got encoding "
            f"{msg.encoding!r}"
        )
    a = image_to_numpy(msg)
    if name == "32FC1":
        return a
    d = a.astype(np.float32) / 1000.0
    d[a == 0] = np.nan
    return d


def numpy_to_image(
    array_: np.ndarray,
    encoding: str,
    header: Header | None = None,
    *,
    classes: MessageClasses | None = None,
) -> Image:
    """Encode an array as an unpadded little-endian Image of ``encoding``.

    The array must be H x W (or H x W x 1) for one-channel encodings and H x W x C otherwise,
    with the encoding's element type: uint8 for the 8-bit encodings, uint16 for mono16/16UC1
    (other integer types are refused rather than wrapped); any floating type for 32FC1 (cast to
    float32; NaN stays NaN). Channel order is taken as given (no swapping). ``classes``: the
    message classes to build (default rclpy's; a rosbags type store's for bags).
    """
    name, enc = _encoding(encoding)
    a = np.asarray(array_)
    if a.ndim == 3 and a.shape[2] == 1 and enc.channels == 1:
        a = a[:, :, 0]
    want_ndim = 2 if enc.channels == 1 else 3
    if a.ndim != want_ndim or (enc.channels > 1 and a.shape[2] != enc.channels):
        want = "H x W" if enc.channels == 1 else f"H x W x {enc.channels}"
        raise ImageConversionError(f"{name} needs an {want} array, got shape {a.shape}")
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise ImageConversionError(f"cannot encode a zero-size image of shape {a.shape}")
    if enc.dtype == _F32:
        if not np.issubdtype(a.dtype, np.floating):
            raise ImageConversionError(f"{name} needs a floating-point array, got {a.dtype}")
    elif a.dtype != enc.dtype:
        raise ImageConversionError(f"{name} needs a {enc.dtype} array, got {a.dtype}")
    le = np.ascontiguousarray(a, dtype=enc.dtype.newbyteorder("<"))
    c = classes or rclpy_classes()
    height, width = int(a.shape[0]), int(a.shape[1])
    return c.image(
        header=empty_header(c) if header is None else header,
        height=height,
        width=width,
        encoding=name,
        is_bigendian=0,
        step=width * enc.bytes_per_pixel,
        data=c.bytes_field(le),
    )


def depth_to_image(
    depth_m: np.ndarray, header: Header | None = None, *, classes: MessageClasses | None = None
) -> Image:
    """A depth map in metres as a REP 118 32FC1 Image: invalid pixels (non-finite or <= 0)
    become NaN. ``classes`` as in :func:`numpy_to_image`."""
    d = np.asarray(depth_m)
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[:, :, 0]
    if d.ndim != 2:
        raise ImageConversionError(f"depth must be an H x W array, got shape {d.shape}")
    if not (np.issubdtype(d.dtype, np.floating) or np.issubdtype(d.dtype, np.integer)):
        raise ImageConversionError(f"depth must be numeric, got {d.dtype}")
    d = d.astype(np.float32, copy=True)
    d[~(np.isfinite(d) & (d > 0))] = np.nan
    return numpy_to_image(d, "32FC1", header, classes=classes)


def depth_to_colored_image(
    depth: np.ndarray,
    header: Header | None = None,
    vmin: float | None = None,
    vmax: float | None = None,
    *,
    classes: MessageClasses | None = None,
) -> Image:
    """A depth map as a bgr8 Image coloured by inverse depth
    (:func:`sfm_ttr_ros.core.visualize.colorize_depth`; invalid pixels black). ``classes`` as in
    :func:`numpy_to_image`."""
    try:
        bgr = colorize_depth(depth, vmin=vmin, vmax=vmax)
    except InputError as exc:
        raise ImageConversionError(str(exc)) from exc
    return numpy_to_image(bgr, "bgr8", header, classes=classes)
