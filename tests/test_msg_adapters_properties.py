"""Property tests of msg_adapters: whatever the fields of an Image, a CameraInfo or a
CompressedImage hold, the readers return a well-formed result or raise the documented error
(an InputError subclass), never anything else. Messages are duck-typed (the readers take any
object with the fields), so the fields range over what ROS can carry: uint32 sizes and steps,
any string, any bytes, any float64 (NaN and inf included)."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from msg_adapters.camera_info import CameraInfoError, camera_info_to_intrinsics  # noqa: E402
from msg_adapters.compressed import (  # noqa: E402
    CompressedImageError,
    compressed_to_rgb8,
    rgb8_to_compressed,
)
from msg_adapters.image import (  # noqa: E402
    SUPPORTED_ENCODINGS,
    ImageConversionError,
    image_to_numpy,
    image_to_rgb8,
)
from sfm_ttr_ros.core.frames import Intrinsics  # noqa: E402

SETTINGS = settings(max_examples=150, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow])
U32 = st.integers(0, 2**32 - 1)
SMALL = st.integers(0, 64)
ENCODINGS = st.one_of(st.sampled_from(SUPPORTED_ENCODINGS),
                      st.sampled_from(["RGB8", "Mono8", "yuv422", "32FC3", "bayer_rggb8", ""]),
                      st.text(max_size=12))
FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=64)


def _image(width, height, step, encoding, data, big):
    return SimpleNamespace(width=width, height=height, step=step, encoding=encoding,
                           data=data, is_bigendian=big)


@st.composite
def images(draw):
    """Mostly consistent small images (so that valid ones are common), plus wild fields."""
    w, h = draw(SMALL), draw(SMALL)
    enc = draw(ENCODINGS)
    bpp = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "8UC3": 3, "mono16": 2, "16UC1": 2,
           "32FC1": 4}.get(enc, 1)
    step = draw(st.one_of(st.just(w * bpp), st.integers(0, 300), U32))
    size = draw(st.one_of(st.just(step * h), st.integers(0, 3000)))
    if size > 100_000:
        size = draw(st.integers(0, 3000))
    data = draw(st.binary(min_size=size, max_size=size))
    w = draw(st.one_of(st.just(w), U32))
    h = draw(st.one_of(st.just(h), U32))
    return _image(w, h, step, enc, data, draw(st.integers(0, 255)))


@SETTINGS
@given(images())
def test_any_image_decodes_or_raises_the_documented_error(msg):
    try:
        rgb = image_to_rgb8(msg)
    except ImageConversionError:
        pass
    else:
        assert rgb.dtype == np.uint8 and rgb.shape == (msg.height, msg.width, 3)
        assert rgb.flags.c_contiguous
        assert len(msg.data) == msg.step * msg.height and msg.encoding in SUPPORTED_ENCODINGS
    try:
        a = image_to_numpy(msg)
    except ImageConversionError:
        pass
    else:
        assert a.shape[:2] == (msg.height, msg.width)


@st.composite
def camera_infos(draw):
    def matrix(n):
        return draw(st.one_of(
            st.lists(FLOATS, min_size=n, max_size=n),
            st.lists(st.floats(-2000, 2000), min_size=n, max_size=n),
            st.lists(FLOATS, max_size=14)))
    k = matrix(9)
    if draw(st.booleans()) and len(k) == 9:  # a plausible K now and then
        k = [draw(st.floats(-10, 2000)), 0, draw(st.floats(-10, 700)), 0,
             draw(st.floats(-10, 2000)), draw(st.floats(-10, 400)), 0, 0, 1]
    roi = SimpleNamespace(x_offset=draw(U32), y_offset=draw(U32),
                          width=draw(st.one_of(SMALL, U32)), height=draw(st.one_of(SMALL, U32)),
                          do_rectify=draw(st.booleans()))
    return SimpleNamespace(width=draw(st.one_of(st.integers(0, 1300), U32)),
                           height=draw(st.one_of(st.integers(0, 400), U32)),
                           k=k, p=matrix(12), d=draw(st.lists(FLOATS, max_size=8)),
                           binning_x=draw(st.one_of(st.integers(0, 4), U32)),
                           binning_y=draw(st.one_of(st.integers(0, 4), U32)), roi=roi)


@SETTINGS
@given(camera_infos(), st.sampled_from([None, True, False]))
def test_any_camera_info_gives_valid_intrinsics_or_the_documented_error(msg, use_p):
    try:
        intr = camera_info_to_intrinsics(msg, use_p)
    except CameraInfoError:
        return
    assert isinstance(intr, Intrinsics)
    assert intr.fx > 0 and intr.fy > 0 and intr.width > 0 and intr.height > 0
    assert np.all(np.isfinite([intr.fx, intr.fy, intr.cx, intr.cy]))


def _valid_jpeg_png():
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 255, (12, 20, 3), dtype=np.uint8)
    out = [bytes(rgb8_to_compressed(rgb, c, classes=_NS).data) for c in ("jpeg", "png")]
    ok, grey16 = cv2.imencode(".png", rng.integers(0, 65535, (5, 7), dtype=np.uint16))
    return [*out, grey16.tobytes()]


class _Msg(SimpleNamespace):
    pass


_NS = SimpleNamespace(compressed_image=_Msg, bytes_field=lambda a: a.tobytes(),
                      header=lambda **kw: None, time=lambda **kw: None)
VALID = None


@st.composite
def compressed(draw):
    global VALID
    if VALID is None:
        VALID = _valid_jpeg_png()
    base = draw(st.sampled_from(VALID))
    kind = draw(st.sampled_from(["valid", "truncated", "flipped", "random", "header_only"]))
    if kind == "truncated":
        data = base[:draw(st.integers(0, len(base)))]
    elif kind == "flipped":
        b = bytearray(base)
        for _ in range(draw(st.integers(1, 8))):
            i = draw(st.integers(0, len(b) - 1))
            b[i] = draw(st.integers(0, 255))
        data = bytes(b)
    elif kind == "random":
        data = draw(st.binary(max_size=200))
    elif kind == "header_only":
        data = base[:draw(st.integers(0, 40))] + draw(st.binary(max_size=40))
    else:
        data = base
    fmt = draw(st.one_of(st.sampled_from(["rgb8; jpeg compressed bgr8", "bgr8; png compressed "
                                          "rgb8", "jpeg", "png", "", "16UC1; compressedDepth"]),
                         st.text(max_size=30)))
    return SimpleNamespace(format=fmt, data=data)


@SETTINGS
@given(compressed())
def test_any_compressed_image_decodes_or_raises_the_documented_error(msg):
    try:
        rgb = compressed_to_rgb8(msg)
    except CompressedImageError:
        return
    assert rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3
    assert rgb.flags.c_contiguous and rgb.shape[0] > 0 and rgb.shape[1] > 0


def test_a_compressed_image_declaring_a_huge_size_is_refused_before_decoding():
    png = bytearray(_valid_jpeg_png()[1])
    png[16:20] = (100_000).to_bytes(4, "big")
    png[20:24] = (100_000).to_bytes(4, "big")
    with pytest.raises(CompressedImageError, match="declares a 100000x100000"):
        compressed_to_rgb8(SimpleNamespace(format="png", data=bytes(png)))


def test_the_format_string_sets_the_colour_order():
    rgb = np.zeros((4, 6, 3), np.uint8)
    rgb[..., 0] = 250  # red
    ok, bgr_png = cv2.imencode(".png", rgb[:, :, ::-1])  # compressed bgr8: true colours
    ok, rgb_png = cv2.imencode(".png", rgb)  # compressed rgb8: the RGB bytes as they are
    red = [250, 0, 0]
    for fmt, data in (("rgb8; png compressed bgr8", bgr_png), ("png", bgr_png),
                      ("rgb8; png compressed rgb8", rgb_png)):
        out = compressed_to_rgb8(SimpleNamespace(format=fmt, data=data.tobytes()))
        assert out[0, 0].tolist() == red, fmt
