"""Depth <-> sensor_msgs/CompressedImage in image_transport's ``compressedDepth`` convention, as
compressed_depth_image_transport writes and reads it (ros-perception/image_transport_plugins,
``compressed_depth_image_transport/src/codec.cpp``: ``encodeCompressedDepthImage`` /
``decodeCompressedDepthImage``; the header in ``compression_common.h``).

``format`` is ``"<encoding>; compressedDepth png"``; ``data`` is a 12-byte ``ConfigHeader``
(little-endian ``int32 format`` = ``INV_DEPTH`` (0), then ``float32 depthParam[2]`` = the
quantisation's A and B) followed by a PNG. For a 32FC1 depth (metres) the PNG holds the 16-bit
quantised inverse depth

    q = trunc(A / d + B),   A = z0 (z0 + 1),   B = 1 - A / depth_max

(z0: ``depth_quantization``, default 100; ``depth_max`` the plugin's parameter, default 10 m):
a depth at or beyond ``depth_max``, or NaN, is q = 0, and decodes as NaN; any other depth
decodes as d' = A / (q - B), so 1/d - 1/d' lies in [0, 1/A) (``quantisation_error`` bounds it:
one step of inverse depth). For 16UC1 / mono16 (millimetres) the PNG holds the depth itself, values
above ``depth_max`` x 1000 set to 0.

Where codec.cpp's float-to-uint16 conversion is undefined (q outside 0..65535: a depth nearer
than A / (65535 - B), or <= 0), this writer saturates q to 65535 and writes 0 (none) for
non-positive depth. RVL (``compressedDepth rvl``) is not read: refused with
:class:`CompressedDepthError`, like every malformed message (short data, a header that is not
INV_DEPTH, a PNG that does not decode to one 16-bit channel, a declared size above
:data:`~msg_adapters.compressed.MAX_PIXELS`).
"""

from __future__ import annotations

import struct

import cv2
import numpy as np

from msg_adapters.classes import MessageClasses, empty_header, rclpy_classes
from msg_adapters.compressed import MAX_PIXELS, CompressedImageError, declared_size

DEPTH_MAX = 10.0  # compressed_depth_image_transport's default depth_max (metres)
DEPTH_QUANTIZATION = 100.0  # its default depth_quantization (z0)
PNG_LEVEL = 9  # its default png_level
INV_DEPTH = 0  # compressionFormat: UNDEFINED = -1, INV_DEPTH
_HEADER = struct.Struct("<iff")  # ConfigHeader: format, depthParam[0], depthParam[1]
HEADER_BYTES = _HEADER.size  # 12
_DEPTH_ENCODINGS = ("32FC1", "16UC1", "mono16")


class CompressedDepthError(CompressedImageError):
    """A compressedDepth CompressedImage that cannot be written or read."""


def quantisation(depth_max: float = DEPTH_MAX,
                 depth_quantization: float = DEPTH_QUANTIZATION) -> tuple[float, float]:
    """(A, B) of the inverse-depth quantisation, in float32 as codec.cpp computes them."""
    if not (np.isfinite(depth_max) and depth_max > 0):
        raise CompressedDepthError(f"depth_max must be > 0, got {depth_max}")
    if not (np.isfinite(depth_quantization) and depth_quantization > 0):
        raise CompressedDepthError(f"depth_quantization must be > 0, got {depth_quantization}")
    z0 = np.float32(depth_quantization)
    a = np.float32(z0 * (z0 + np.float32(1.0)))
    return float(a), float(np.float32(np.float32(1.0) - a / np.float32(depth_max)))


def quantisation_error(depth_max: float = DEPTH_MAX,
                       depth_quantization: float = DEPTH_QUANTIZATION) -> float:
    """The largest inverse-depth error (1/m) of a decoded 32FC1 depth: one step, 1 / A."""
    return 1.0 / quantisation(depth_max, depth_quantization)[0]


def _inverse_depth_png(depth: np.ndarray, a: float, b: float, depth_max: float,
                       png_level: int) -> bytes:
    d = depth.astype(np.float32, copy=False)
    valid = np.isfinite(d) & (d > 0) & (d < np.float32(depth_max))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        q = np.float32(a) / d + np.float32(b)
    q = np.where(valid, np.clip(np.trunc(q), 0, 65535), 0).astype(np.uint16)
    ok, buf = cv2.imencode(".png", q, [cv2.IMWRITE_PNG_COMPRESSION, int(png_level)])
    if not ok:
        raise CompressedDepthError("OpenCV could not encode the inverse depth as PNG")
    return buf.tobytes()


def depth_to_compressed_depth(depth: np.ndarray, header=None, *, encoding: str = "32FC1",
                              depth_max: float = DEPTH_MAX,
                              depth_quantization: float = DEPTH_QUANTIZATION,
                              png_level: int = PNG_LEVEL,
                              classes: MessageClasses | None = None):
    """An H x W depth as a ``compressedDepth png`` CompressedImage, as encodeCompressedDepthImage
    writes it: ``encoding`` 32FC1 (``depth`` in metres, float; NaN = none) as quantised inverse
    depth, or 16UC1 / mono16 (``depth`` uint16 millimetres) as it is. ``classes`` as in
    :func:`msg_adapters.image.numpy_to_image`."""
    d = np.asarray(depth)
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[:, :, 0]
    if d.ndim != 2 or 0 in d.shape:
        raise CompressedDepthError(f"depth must be a non-empty H x W array, got {d.shape}")
    a, b = quantisation(depth_max, depth_quantization)
    if encoding == "32FC1":
        if not np.issubdtype(d.dtype, np.floating):
            raise CompressedDepthError(f"32FC1 depth must be floating point, got {d.dtype}")
        png = _inverse_depth_png(d, a, b, depth_max, png_level)
    elif encoding in ("16UC1", "mono16"):
        if d.dtype != np.uint16:
            raise CompressedDepthError(f"{encoding} depth must be uint16, got {d.dtype}")
        raw = np.where(d > np.uint16(min(65535, int(depth_max * 1000.0))), 0, d)
        ok, buf = cv2.imencode(".png", raw.astype(np.uint16),
                               [cv2.IMWRITE_PNG_COMPRESSION, int(png_level)])
        if not ok:
            raise CompressedDepthError("OpenCV could not encode the depth as PNG")
        png = buf.tobytes()
    else:
        raise CompressedDepthError(f"compressedDepth takes 32FC1 or 16UC1 depth, got "
                                   f"{encoding!r}")
    c = classes or rclpy_classes()
    if c.compressed_image is None:
        raise CompressedDepthError("these message classes have no CompressedImage")
    data = np.frombuffer(_HEADER.pack(INV_DEPTH, a, b) + png, np.uint8)
    return c.compressed_image(header=empty_header(c) if header is None else header,
                              format=f"{encoding}; compressedDepth png",
                              data=c.bytes_field(data))


def _encoding_of(fmt: str) -> str:
    """The image encoding of a compressedDepth ``format``; only its PNG codec is read
    (decodeCompressedDepthImage: no ``;`` = an old PNG message)."""
    encoding, sep, tail = fmt.partition(";")
    if sep and "compressedDepth png" not in tail and not (
            "compressedDepth" in tail and "compressedDepth " not in tail):
        raise CompressedDepthError(f"unsupported compressedDepth format {fmt!r} (only png)")
    encoding = encoding.strip()
    if encoding not in _DEPTH_ENCODINGS:
        raise CompressedDepthError(f"compressedDepth of encoding {encoding!r}: not a depth "
                                   f"encoding ({', '.join(_DEPTH_ENCODINGS)})")
    return encoding


def compressed_depth_to_numpy(msg) -> tuple[str, np.ndarray]:
    """(encoding, depth) of a compressedDepth CompressedImage, as decodeCompressedDepthImage
    reads it: 32FC1 -> float32 metres (q = 0 -> NaN, else A / (q - B)); 16UC1 / mono16 -> the
    uint16 millimetres."""
    encoding = _encoding_of(str(msg.format))
    data = bytes(msg.data)
    if len(data) <= HEADER_BYTES:
        raise CompressedDepthError(f"compressedDepth data of {len(data)} bytes: no image after "
                                   f"its {HEADER_BYTES}-byte header")
    fmt, a, b = _HEADER.unpack_from(data)
    if fmt != INV_DEPTH:
        raise CompressedDepthError(f"compressedDepth header format {fmt}, not INV_DEPTH (0)")
    png = data[HEADER_BYTES:]
    try:
        codec, w, h = declared_size(png)
    except CompressedImageError as exc:
        raise CompressedDepthError(f"compressedDepth image: {exc}") from exc
    if codec != "png" or w <= 0 or h <= 0 or w * h > MAX_PIXELS:
        raise CompressedDepthError(f"compressedDepth holds a {w}x{h} {codec}: not a PNG of "
                                   f"1 to {MAX_PIXELS} pixels")
    q = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    if q is None or q.dtype != np.uint16 or q.ndim != 2:
        raise CompressedDepthError("compressedDepth PNG is not one 16-bit channel")
    if encoding != "32FC1":
        return encoding, q
    with np.errstate(divide="ignore"):
        depth = np.float32(a) / (q.astype(np.float32) - np.float32(b))
    depth[q == 0] = np.nan
    return encoding, depth.astype(np.float32, copy=False)


def compressed_depth_to_depth(msg) -> np.ndarray:
    """A compressedDepth CompressedImage as float32 metres (NaN = none), REP 118 like
    :func:`msg_adapters.image.image_to_depth`: 16UC1 millimetres / 1000, 0 -> NaN."""
    encoding, d = compressed_depth_to_numpy(msg)
    if encoding == "32FC1":
        return d
    out = d.astype(np.float32) / 1000.0
    out[d == 0] = np.nan
    return out
