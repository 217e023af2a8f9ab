"""msg_adapters: Image, CameraInfo, PointCloud2 and DiagnosticArray conversions."""

from __future__ import annotations

import array
import time

import numpy as np
import pytest

pytest.importorskip("sensor_msgs", reason="ROS 2 message packages (ros-jazzy-*) not installed")

from builtin_interfaces.msg import Time  # noqa: E402
from diagnostic_msgs.msg import DiagnosticStatus  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from msg_adapters import (  # noqa: E402
    SUPPORTED_ENCODINGS,
    CameraInfoError,
    ImageConversionError,
    PointCloudError,
    camera_info_for,
    camera_info_msg,
    camera_info_to_intrinsics,
    depth_to_colored_image,
    depth_to_image,
    depth_to_pointcloud2,
    diagnostic_values,
    image_to_depth,
    image_to_numpy,
    image_to_rgb8,
    intrinsics_to_camera_info,
    make_diagnostic_array,
    make_header,
    numpy_to_image,
    numpy_to_pointcloud2,
    pointcloud2_to_numpy,
    pointcloud2_to_xyz,
    projection_of,
    scale_camera_info,
    typestore_classes,
    unpack_rgb,
)
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Intrinsics  # noqa: E402

RNG = np.random.default_rng(1234)
# encoding -> (dtype, channels)
LAYOUT = {
    "rgb8": (np.uint8, 3),
    "bgr8": (np.uint8, 3),
    "rgba8": (np.uint8, 4),
    "bgra8": (np.uint8, 4),
    "mono8": (np.uint8, 1),
    "8UC1": (np.uint8, 1),
    "8UC3": (np.uint8, 3),
    "mono16": (np.uint16, 1),
    "16UC1": (np.uint16, 1),
    "32FC1": (np.float32, 1),
}


def _random(encoding: str, h: int = 7, w: int = 5) -> np.ndarray:
    dtype, ch = LAYOUT[encoding]
    shape = (h, w) if ch == 1 else (h, w, ch)
    if dtype == np.float32:
        a = RNG.uniform(0.1, 80.0, size=shape).astype(np.float32)
        a[0, 0] = np.nan
        return a
    return RNG.integers(0, np.iinfo(dtype).max, size=shape, endpoint=True, dtype=dtype)


def _raw_image(a: np.ndarray, encoding: str, step: int, bigendian: bool = False) -> Image:
    """A message built by hand (like a driver would), rows padded to ``step`` with 0xAB."""
    h, w = a.shape[:2]
    be = a.astype(a.dtype.newbyteorder(">" if bigendian else "<"))
    rows = be.reshape(h, -1).view(np.uint8).reshape(h, -1)
    padded = np.full((h, step), 0xAB, np.uint8)
    padded[:, : rows.shape[1]] = rows
    msg = Image(height=h, width=w, encoding=encoding, is_bigendian=int(bigendian), step=step)
    msg.data = array.array("B", padded.tobytes())
    return msg


def _eq(a: np.ndarray, b: np.ndarray) -> None:
    assert a.dtype == b.dtype and a.shape == b.shape
    np.testing.assert_array_equal(a, b)  # NaNs in the same places compare equal


# ---------------------------------------------------------------------------------- Image
def test_supported_encodings_listed():
    assert set(SUPPORTED_ENCODINGS) == set(LAYOUT)


@pytest.mark.parametrize("encoding", sorted(LAYOUT))
def test_image_round_trip(encoding):
    a = _random(encoding)
    hdr = Header(stamp=Time(sec=12, nanosec=34), frame_id="cam")
    msg = numpy_to_image(a, encoding, hdr)
    dtype, ch = LAYOUT[encoding]
    assert msg.encoding == encoding and (msg.height, msg.width) == (7, 5)
    assert msg.step == 5 * ch * np.dtype(dtype).itemsize and msg.is_bigendian == 0
    assert len(msg.data) == msg.step * 7
    assert msg.header.frame_id == "cam" and msg.header.stamp.sec == 12
    _eq(image_to_numpy(msg), a)


@pytest.mark.parametrize("encoding", sorted(LAYOUT))
def test_image_padded_step(encoding):
    a = _random(encoding, h=4, w=5)
    dtype, ch = LAYOUT[encoding]
    row = 5 * ch * np.dtype(dtype).itemsize
    step = row + 3 if np.dtype(dtype).itemsize == 1 else row + 4  # e.g. rgb8: 15 -> step 18
    _eq(image_to_numpy(_raw_image(a, encoding, step)), a)


def test_rgb8_width5_step16():
    a = _random("rgb8", h=3, w=5)
    msg = _raw_image(a, "rgb8", 16)
    assert len(msg.data) == 48
    _eq(image_to_numpy(msg), a)
    _eq(image_to_rgb8(msg), a)


@pytest.mark.parametrize("encoding", ["mono16", "16UC1", "32FC1"])
@pytest.mark.parametrize("step_pad", [0, 6])
def test_image_big_endian(encoding, step_pad):
    a = _random(encoding, h=6, w=9)
    step = 9 * a.dtype.itemsize + step_pad
    msg = _raw_image(a, encoding, step, bigendian=True)
    msg.is_bigendian = 0  # the bytes really are big-endian: ignoring the flag garbles them
    assert not np.array_equal(image_to_numpy(msg), a, equal_nan=True)
    msg.is_bigendian = 1
    out = image_to_numpy(msg)
    assert out.dtype.isnative
    _eq(out, a)


def test_image_to_numpy_returns_a_copy():
    a = _random("rgb8")
    msg = numpy_to_image(a, "rgb8")
    out = image_to_numpy(msg)
    out[:] = 0
    _eq(image_to_numpy(msg), a)
    msg.data.append(1)  # no buffer export left behind: the message can still be resized


def test_image_to_rgb8_all_encodings():
    rgb = _random("rgb8")
    alpha = RNG.integers(0, 256, size=rgb.shape[:2] + (1,), dtype=np.uint8)
    _eq(image_to_rgb8(numpy_to_image(rgb, "rgb8")), rgb)
    _eq(image_to_rgb8(numpy_to_image(rgb[:, :, ::-1], "bgr8")), rgb)
    _eq(image_to_rgb8(numpy_to_image(rgb[:, :, ::-1], "8UC3")), rgb)
    _eq(image_to_rgb8(numpy_to_image(np.concatenate([rgb, alpha], 2), "rgba8")), rgb)
    _eq(image_to_rgb8(numpy_to_image(np.concatenate([rgb[:, :, ::-1], alpha], 2), "bgra8")), rgb)
    g = rgb[:, :, 0]
    for enc in ("mono8", "8UC1"):
        _eq(image_to_rgb8(numpy_to_image(g, enc)), np.repeat(g[:, :, None], 3, 2))
    g16 = np.array([[0, 255, 256, 65535]], dtype=np.uint16)
    for enc in ("mono16", "16UC1"):
        out = image_to_rgb8(numpy_to_image(g16, enc))
        assert out.shape == (1, 4, 3) and out.dtype == np.uint8
        assert out[0, :, 0].tolist() == [0, 0, 1, 255]  # documented: >> 8
    with pytest.raises(ImageConversionError, match="not a colour"):
        image_to_rgb8(numpy_to_image(_random("32FC1"), "32FC1"))


def test_image_errors():
    good = numpy_to_image(_random("rgb8"), "rgb8")
    bad = Image(height=2, width=2, encoding="yuv422", step=4)
    bad.data = array.array("B", bytes(8))
    with pytest.raises(ImageConversionError, match=r"'yuv422'.*supported: .*rgb8.*32FC1"):
        image_to_numpy(bad)
    zero = Image(height=0, width=5, encoding="rgb8", step=15)
    with pytest.raises(ImageConversionError, match="zero size"):
        image_to_numpy(zero)
    short_step = Image(height=7, width=5, encoding="rgb8", step=14, data=good.data)
    with pytest.raises(ImageConversionError, match="step 14 is smaller .* 15"):
        image_to_numpy(short_step)
    trunc = Image(height=7, width=5, encoding="rgb8", step=15)
    trunc.data = array.array("B", bytes(good.data)[:-1])
    with pytest.raises(ImageConversionError, match="expected .* 105 bytes, got 104"):
        image_to_numpy(trunc)
    assert issubclass(ImageConversionError, ValueError)
    assert issubclass(ImageConversionError, InputError)
    with pytest.raises(ImageConversionError, match="H x W x 3"):
        numpy_to_image(np.zeros((4, 4), np.uint8), "rgb8")
    with pytest.raises(ImageConversionError, match="uint16"):
        numpy_to_image(np.zeros((4, 4), np.int32), "mono16")  # no silent wrap-around
    with pytest.raises(ImageConversionError, match="floating"):
        numpy_to_image(np.zeros((4, 4), np.uint16), "32FC1")
    with pytest.raises(ImageConversionError, match="zero-size"):
        numpy_to_image(np.zeros((0, 4), np.uint8), "mono8")
    with pytest.raises(ImageConversionError, match="supported"):
        numpy_to_image(np.zeros((4, 4), np.uint8), "jpeg")


def test_wrong_case_encodings_and_over_long_data_are_refused_as_cv_bridge_does():
    # cv_bridge's getCvType matches encoding names exactly; its matFromImage requires
    # data size == height x step (README "Topics")
    good = numpy_to_image(_random("rgb8"), "rgb8")
    for name in ("RGB8", "MONO8", "Bgr8", "8uc3"):
        wrong = Image(height=good.height, width=good.width, encoding=name, step=good.step,
                      data=good.data)
        with pytest.raises(ImageConversionError, match="case-sensitive"):
            image_to_rgb8(wrong)
    longer = Image(height=good.height, width=good.width, encoding="rgb8", step=good.step)
    longer.data = array.array("B", bytes(good.data) + b"\0")
    with pytest.raises(ImageConversionError, match=r"over-long rgb8 .* 105 bytes, got 106"):
        image_to_numpy(longer)
    # padded rows are still fine: the padding is part of step x height
    padded = Image(height=good.height, width=good.width, encoding="rgb8", step=good.step + 3)
    rows = np.frombuffer(bytes(good.data), np.uint8).reshape(good.height, good.step)
    padded.data = array.array("B", np.pad(rows, ((0, 0), (0, 3))).tobytes())
    np.testing.assert_array_equal(image_to_rgb8(padded), image_to_rgb8(good))



def test_depth_to_image_rep118():
    d = RNG.uniform(1.0, 80.0, size=(6, 8))  # float64 in, float32 out
    invalid = [(0, 0, 0.0), (1, 1, -2.0), (2, 2, np.inf), (3, 3, np.nan), (4, 4, -np.inf)]
    for r, c, v in invalid:
        d[r, c] = v
    hdr = Header(frame_id="camera_color_left")
    msg = depth_to_image(d, hdr)
    assert msg.encoding == "32FC1" and msg.step == 32 and msg.header.frame_id == hdr.frame_id
    out = image_to_numpy(msg)
    assert out.dtype == np.float32
    bad = np.zeros(d.shape, bool)
    for r, c, _ in invalid:
        bad[r, c] = True
    assert np.isnan(out[bad]).all() and np.isfinite(out[~bad]).all()
    np.testing.assert_array_equal(out[~bad], d[~bad].astype(np.float32))
    with pytest.raises(ImageConversionError, match="H x W"):
        depth_to_image(np.zeros((2, 3, 3)), hdr)


def test_depth_to_colored_image():
    d = np.tile(np.linspace(2.0, 40.0, 16), (5, 1))
    d[0, 0] = np.nan
    msg = depth_to_colored_image(d, Header(frame_id="f"))
    assert msg.encoding == "bgr8" and (msg.height, msg.width) == (5, 16)
    bgr = image_to_numpy(msg)
    assert bgr[0, 0].tolist() == [0, 0, 0]
    assert int(bgr[2, 1].sum()) > int(bgr[2, 15].sum())  # near brighter than far


def _best_ms(fn, repeats: int = 7) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, (time.perf_counter() - t0) * 1e3)
    return best


def test_kitti_size_depth_conversion_is_fast():
    d = RNG.uniform(1.0, 80.0, size=(375, 1242)).astype(np.float32)
    d[::7, ::5] = 0.0
    hdr = Header(frame_id="cam")
    msg = depth_to_image(d, hdr)
    to_msg = _best_ms(lambda: depth_to_image(d, hdr))
    from_msg = _best_ms(lambda: image_to_numpy(msg))
    print(f"1242x375 32FC1: depth_to_image {to_msg:.2f} ms, image_to_numpy {from_msg:.2f} ms")
    assert to_msg < 50.0 and from_msg < 50.0
    assert len(msg.data) == 1242 * 375 * 4


# ----------------------------------------------------------------------------- CameraInfo
def _camera_info(K=None, P=None, D=(), width=1242, height=375) -> CameraInfo:
    msg = CameraInfo(width=width, height=height)
    if K is not None:
        msg.k = np.asarray(K, float).ravel().tolist()
    if P is not None:
        msg.p = np.asarray(P, float).ravel().tolist()
    msg.d = list(D)
    return msg


K_RAW = [[721.5, 0, 609.6], [0, 721.5, 172.9], [0, 0, 1]]
P_RECT = [[707.0, 0, 604.0, 0], [0, 707.0, 180.5, 0], [0, 0, 1, 0]]


def test_camera_info_k_vs_p_selection():
    k_only = camera_info_to_intrinsics(_camera_info(K=K_RAW))
    assert (k_only.fx, k_only.cx, k_only.cy) == (721.5, 609.6, 172.9)
    assert (k_only.width, k_only.height) == (1242, 375)
    # rectified (no distortion): P by default
    for D in ((), (0.0, 0.0, 0.0, 0.0, 0.0)):
        rect = camera_info_to_intrinsics(_camera_info(K=K_RAW, P=P_RECT, D=D))
        assert (rect.fx, rect.fy, rect.cx, rect.cy) == (707.0, 707.0, 604.0, 180.5)
    # distorted raw image: K by default, P on request
    dist = _camera_info(K=K_RAW, P=P_RECT, D=(-0.37, 0.2, 0.0, 0.0, 0.0))
    assert camera_info_to_intrinsics(dist).fx == 721.5
    assert camera_info_to_intrinsics(dist, use_projection=True).fx == 707.0
    rect = _camera_info(K=K_RAW, P=P_RECT)
    assert camera_info_to_intrinsics(rect, use_projection=False).fx == 721.5


def test_camera_info_errors():
    with pytest.raises(CameraInfoError, match="K is all zero"):
        camera_info_to_intrinsics(_camera_info())
    with pytest.raises(CameraInfoError, match="use_projection=True"):
        camera_info_to_intrinsics(_camera_info(P=P_RECT, D=(0.1, 0, 0, 0, 0)))
    with pytest.raises(CameraInfoError, match="P is all zero"):
        camera_info_to_intrinsics(_camera_info(K=K_RAW), use_projection=True)
    nan_k = np.array(K_RAW)
    nan_k[0, 0] = np.nan
    with pytest.raises(CameraInfoError, match="non-finite"):
        camera_info_to_intrinsics(_camera_info(K=nan_k))
    with pytest.raises(CameraInfoError, match="zero image size"):
        camera_info_to_intrinsics(_camera_info(K=K_RAW, width=0))
    neg = np.array(K_RAW)
    neg[1, 1] = -5.0
    with pytest.raises(CameraInfoError, match="focal"):
        camera_info_to_intrinsics(_camera_info(K=neg))
    assert issubclass(CameraInfoError, ValueError)


def test_camera_info_round_trip_binning_roi():
    intr = Intrinsics(718.856, 718.856, 607.1928, 185.2157, 1241, 376)
    msg = intrinsics_to_camera_info(intr, Header(stamp=Time(sec=5)), frame_id="cam0")
    assert msg.header.frame_id == "cam0" and msg.header.stamp.sec == 5
    assert (msg.width, msg.height) == (1241, 376)
    np.testing.assert_array_equal(np.reshape(msg.k, (3, 3)), intr.K)
    P = np.reshape(msg.p, (3, 4))
    np.testing.assert_array_equal(P[:, :3], intr.K)
    assert not P[:, 3].any()
    np.testing.assert_array_equal(np.reshape(msg.r, (3, 3)), np.eye(3))
    assert len(msg.d) == 0 and msg.distortion_model == "plumb_bob"
    for use_p in (None, True, False):
        assert camera_info_to_intrinsics(msg, use_projection=use_p) == intr
    hdr = Header(frame_id="keep")
    intrinsics_to_camera_info(intr, hdr, frame_id="other")
    assert hdr.frame_id == "keep"  # the caller's header is not modified
    msg.binning_x = msg.binning_y = 2
    half = camera_info_to_intrinsics(msg)
    assert (half.width, half.height) == (620, 188)
    assert half.fx == pytest.approx(intr.fx / 2) and half.cy == pytest.approx(intr.cy / 2)
    msg.binning_x = msg.binning_y = 0
    msg.roi.x_offset, msg.roi.y_offset, msg.roi.width, msg.roi.height = 100, 50, 640, 200
    roi = camera_info_to_intrinsics(msg)
    assert (roi.width, roi.height) == (640, 200)
    assert roi.cx == pytest.approx(intr.cx - 100) and roi.cy == pytest.approx(intr.cy - 50)


def test_camera_info_beside_an_image_is_the_received_one_or_scaled_to_its_size():
    src = camera_info_msg(1242, 375, [[721.5, 0, 609.6], [0, 721.5, 172.9], [0, 0, 1]],
                          [[700, 0, 600, -380], [0, 700, 170, 0], [0, 0, 1, 0]],
                          D=[0.1, -0.2, 0.0, 0.0, 0.01], R=np.diag([1.0, -1.0, -1.0]),
                          header=Header(frame_id="camera_info_frame"))
    out = camera_info_for(src, 1242, 375, Header(frame_id="cam", stamp=Time(sec=3)))
    assert out.header.frame_id == "cam" and out.header.stamp.sec == 3
    for f in ("k", "p", "d", "r", "width", "height", "distortion_model", "binning_x"):
        np.testing.assert_array_equal(getattr(out, f), getattr(src, f))
    assert src.header.frame_id == "camera_info_frame"  # the received message is not modified
    half = camera_info_for(src, 621, 187, Header(frame_id="cam"))
    assert (half.width, half.height) == (621, 187) and half.header.frame_id == "cam"
    P = np.reshape(half.p, (3, 4))
    np.testing.assert_allclose(P[0], [350, 0, 300, -190])
    np.testing.assert_allclose(P[1], [0, 700 * 187 / 375, 170 * 187 / 375, 0])
    np.testing.assert_array_equal(half.d, src.d)
    np.testing.assert_array_equal(half.r, src.r)
    assert projection_of(half) == pytest.approx((350, 700 * 187 / 375, 300, 170 * 187 / 375))
    # binning and ROI describe a smaller image: kept as they are for it, applied when scaling
    src.binning_x = src.binning_y = 2
    binned = camera_info_for(src, 621, 187, Header())
    assert (binned.width, binned.height, binned.binning_x) == (1242, 375, 2)
    src.binning_x = src.binning_y = 0
    src.roi.x_offset, src.roi.y_offset, src.roi.width, src.roi.height = 100, 50, 640, 200
    assert camera_info_for(src, 640, 200, Header()).roi.x_offset == 100
    plain = scale_camera_info(src, 320, 100)
    assert (plain.width, plain.height, plain.roi.width, plain.binning_x) == (320, 100, 0, 0)
    np.testing.assert_allclose(np.reshape(plain.k, (3, 3))[:2],
                               [[360.75, 0, 254.8], [0, 360.75, 61.45]])
    assert camera_info_to_intrinsics(plain, use_projection=False) == pytest.approx(
        camera_info_to_intrinsics(src, use_projection=False).scaled(320, 100))
    with pytest.raises(CameraInfoError):
        scale_camera_info(src, 0, 100)
    # P all zero: the pinhole comes from K
    src.p = [0.0] * 12
    assert projection_of(src) == (721.5, 721.5, 609.6, 172.9)


# ---------------------------------------------------------------------------- PointCloud2
def test_depth_back_projected_as_depth_image_proc_every_stride_pixel_with_colours():
    h, w = 7, 9
    depth = np.full((h, w), 2.0, np.float32)
    depth[0, 2] = np.nan  # invalid
    depth[2, 0] = 0.0  # invalid
    depth[2, 2] = 50.0  # out of range
    rgb = RNG.integers(0, 256, size=(h, w, 3), dtype=np.uint8)
    info = camera_info_msg(w, h, np.eye(3), [[4, 0, 4, 0], [0, 5, 3, 0], [0, 0, 1, 0]],
                           header=Header(frame_id="cam"))
    msg = depth_to_pointcloud2(depth, rgb, info, stride=2, max_range=10.0)
    assert msg.header.frame_id == "cam" and msg.height == 1 and msg.is_dense is True
    pts = pointcloud2_to_numpy(msg)
    assert pts.dtype.names == ("x", "y", "z", "rgb")
    want = [(v, u) for v in range(0, h, 2) for u in range(0, w, 2)
            if (v, u) not in {(0, 2), (2, 0), (2, 2)}]
    assert pts.shape == (len(want),)
    v, u = np.array(want).T
    np.testing.assert_allclose(pts["z"], 2.0)
    np.testing.assert_allclose(pts["x"], (u - 4) * 2.0 / 4, rtol=1e-6)
    np.testing.assert_allclose(pts["y"], (v - 3) * 2.0 / 5, rtol=1e-6)
    np.testing.assert_array_equal(unpack_rgb(pts["rgb"]), rgb[v, u])
    assert (rgb[v[0], u[0]] @ [65536, 256, 1]) == pts["rgb"][:1].view(np.uint32)[0]
    # no range limit, stride 1, no colours; an all-invalid depth gives an empty cloud
    assert depth_to_pointcloud2(depth, None, info, stride=1).width == h * w - 2
    assert depth_to_pointcloud2(np.full((2, 2), np.nan), None, info).width == 0
    with pytest.raises(PointCloudError, match="stride"):
        depth_to_pointcloud2(depth, None, info, stride=0)
    with pytest.raises(PointCloudError, match="rgb"):
        depth_to_pointcloud2(depth, rgb[:3], info)


def test_pointcloud_round_trip_with_extra_field():
    xyz = RNG.normal(size=(100, 3)) * 10
    err = RNG.uniform(0, 2, size=100)
    msg = numpy_to_pointcloud2(xyz, Header(frame_id="map"), {"reprojection_error": err})
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (1, 100, 16, 1600)
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == [
        ("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("reprojection_error", 12, 7, 1)
    ]  # fmt: skip
    assert msg.is_bigendian is False and msg.is_dense is True
    assert msg.header.frame_id == "map" and len(msg.data) == 1600
    pts = pointcloud2_to_numpy(msg)
    assert pts.dtype.names == ("x", "y", "z", "reprojection_error") and pts.shape == (100,)
    np.testing.assert_array_equal(pts["reprojection_error"], err.astype(np.float32))
    np.testing.assert_array_equal(pointcloud2_to_xyz(msg), xyz.astype(np.float32))


def test_pointcloud_nan_not_dense_and_skip_nans():
    xyz = np.arange(15, dtype=np.float32).reshape(5, 3)
    assert numpy_to_pointcloud2(xyz, Header()).is_dense is True
    bad = xyz.copy()
    bad[2, 1] = np.nan
    msg = numpy_to_pointcloud2(bad, Header())
    assert msg.is_dense is False
    assert pointcloud2_to_xyz(msg).shape == (4, 3)
    kept = pointcloud2_to_xyz(msg, skip_nans=False)
    assert kept.shape == (5, 3) and np.isnan(kept[2, 1])
    nan_extra = numpy_to_pointcloud2(xyz, Header(), {"e": [0, 1, np.inf, 2, 3]})
    assert nan_extra.is_dense is False
    empty = numpy_to_pointcloud2(np.zeros((0, 3)), Header(), {"e": []})
    assert empty.width == 0 and empty.is_dense is True
    assert pointcloud2_to_xyz(empty).shape == (0, 3)


@pytest.mark.parametrize("bigendian", [False, True])
def test_pointcloud_height2_padded_mixed_types(bigendian):
    """An organized 2 x 3 cloud as a driver might send it: float64 field, uint16, padding."""
    o = ">" if bigendian else "<"
    dt = np.dtype(
        {"names": ["x", "y", "z", "intensity", "range"],
         "formats": [o + "f4", o + "f4", o + "f4", o + "u2", o + "f8"],
         "offsets": [0, 4, 8, 12, 16], "itemsize": 28}
    )  # fmt: skip
    h, w, row_step = 2, 3, 3 * 28 + 4
    rec = np.zeros(h * w, dtype=dt)
    rec["x"], rec["y"], rec["z"] = np.arange(6), np.arange(6) + 10, np.arange(6) + 20
    rec["intensity"] = [1, 2, 3, 60000, 5, 6]
    rec["range"] = np.arange(6) * 1.5
    raw = np.full((h, row_step), 0xEE, np.uint8)
    raw[:, : w * 28] = np.frombuffer(rec.tobytes(), np.uint8).reshape(h, w * 28)
    types = [7, 7, 7, PointField.UINT16, PointField.FLOAT64]
    msg = PointCloud2(height=h, width=w, point_step=28, row_step=row_step, is_bigendian=bigendian)
    msg.fields = [
        PointField(name=n, offset=off, datatype=t, count=1)
        for n, off, t in zip(dt.names, [0, 4, 8, 12, 16], types, strict=True)
    ]
    msg.data = array.array("B", raw.tobytes())
    pts = pointcloud2_to_numpy(msg)
    assert pts.shape == (6,) and pts.dtype.isnative is True
    assert pts["intensity"].tolist() == [1, 2, 3, 60000, 5, 6]
    np.testing.assert_array_equal(pts["range"], np.arange(6) * 1.5)
    np.testing.assert_array_equal(pointcloud2_to_xyz(msg)[:, 1], np.arange(6) + 10)
    # the last row's padding may be left out of the data
    msg.data = array.array("B", raw.tobytes()[:-4])
    np.testing.assert_array_equal(pointcloud2_to_numpy(msg)["z"], np.arange(6) + 20)


def test_pointcloud_errors():
    msg = numpy_to_pointcloud2(np.zeros((10, 3)), Header())
    msg.data = array.array("B", bytes(msg.data)[:-1])
    with pytest.raises(PointCloudError, match="expected 120 bytes.*got 119"):
        pointcloud2_to_numpy(msg)
    odd = numpy_to_pointcloud2(np.zeros((2, 3)), Header())
    odd.fields[2].datatype = 42
    with pytest.raises(PointCloudError, match="unknown datatype 42"):
        pointcloud2_to_numpy(odd)
    odd = numpy_to_pointcloud2(np.zeros((2, 3)), Header())
    odd.fields[2].offset = 10
    with pytest.raises(PointCloudError, match="does not fit"):
        pointcloud2_to_numpy(odd)
    no_z = numpy_to_pointcloud2(np.zeros((2, 3)), Header())
    no_z.fields = no_z.fields[:2]
    with pytest.raises(PointCloudError, match="no z field"):
        pointcloud2_to_xyz(no_z)
    with pytest.raises(PointCloudError, match="N x 3"):
        numpy_to_pointcloud2(np.zeros((4, 2)), Header())
    with pytest.raises(PointCloudError, match="3 values for 4 points"):
        numpy_to_pointcloud2(np.zeros((4, 3)), Header(), {"e": np.zeros(3)})
    with pytest.raises(PointCloudError, match="duplicate"):
        numpy_to_pointcloud2(np.zeros((4, 3)), Header(), {"x": np.zeros(4)})


# ---------------------------------------------------------------------------- diagnostics
def test_diagnostics():
    arr = make_diagnostic_array(
        Time(sec=3, nanosec=5), "sfm_ttr: refinement", "camera_color_left", "warn",
        "few SfM points",
        {"abs_rel": 0.056312345, "points": 1234, "ok": True, "lr": 1e-4, "note": "x", "n": None},
    )  # fmt: skip
    assert arr.header.stamp.sec == 3 and arr.header.stamp.nanosec == 5
    (st,) = arr.status
    assert st.level == DiagnosticStatus.WARN and st.name == "sfm_ttr: refinement"
    assert st.hardware_id == "camera_color_left" and st.message == "few SfM points"
    assert diagnostic_values(arr) == {
        "abs_rel": "0.0563123", "points": "1234", "ok": "true", "lr": "0.0001", "note": "x",
        "n": "",
    }  # fmt: skip
    assert diagnostic_values(arr, name="sfm_ttr: refinement")["points"] == "1234"
    with pytest.raises(KeyError):
        diagnostic_values(arr, name="other")
    levels = {"ok": DiagnosticStatus.OK, "ERROR": DiagnosticStatus.ERROR}
    for lv, want in levels.items():
        assert make_diagnostic_array(1.5, "n", "h", lv, "m", {}).status[0].level == want
    assert make_diagnostic_array(1.5, "n", "h", "ok", "m", {}).header.stamp.nanosec == 500000000
    np_vals = make_diagnostic_array(
        None, "n", "h", "ok", "m", {"f": np.float32(2.5), "i": np.int64(7)}
    )
    assert diagnostic_values(np_vals.status[0]) == {"f": "2.5", "i": "7"}
    with pytest.raises(InputError, match="level"):
        make_diagnostic_array(None, "n", "h", "fatal", "m", {})


# ---------------------------------------------------------------------------------------------
# One builder, two kinds of classes (rclpy's and a rosbags type store's), and depth reading
# ---------------------------------------------------------------------------------------------


def test_image_to_depth_rep118():
    mm = np.array([[0, 1500], [65535, 20]], np.uint16)
    for enc in ("16UC1", "mono16"):
        d = image_to_depth(numpy_to_image(mm, enc))
        assert d.dtype == np.float32 and np.isnan(d[0, 0])
        np.testing.assert_allclose(d.ravel()[1:], [1.5, 65.535, 0.02], rtol=1e-6)
    metres = np.array([[1.25, np.nan]], np.float32)
    _eq(image_to_depth(numpy_to_image(metres, "32FC1")), metres)
    with pytest.raises(ImageConversionError, match="must be 32FC1"):
        image_to_depth(numpy_to_image(np.zeros((2, 2, 3), np.uint8), "rgb8"))


def test_builders_give_rosbags_messages_equal_to_rclpy_ones():
    """numpy_to_image / depth_to_image / camera_info_msg / make_header fill a rosbags type
    store's classes exactly as rclpy's: rclpy decodes the rosbags CDR bytes (what a bag holds)
    into a message equal to the one built for rclpy. (The bytes themselves may differ in the
    alignment padding, which rclpy's serializer leaves uninitialised.)"""
    rosbags_typesys = pytest.importorskip("rosbags.typesys")
    from rclpy.serialization import deserialize_message

    store = rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_JAZZY)
    bag_classes = typestore_classes(store)

    def same_bytes(build, msgtype: str) -> None:
        ros_msg, bag_msg = build(None), build(bag_classes)
        assert type(bag_msg).__msgtype__ == msgtype and isinstance(ros_msg, (Image, CameraInfo))
        cdr = bytes(store.serialize_cdr(bag_msg, msgtype))
        assert deserialize_message(cdr, type(ros_msg)) == ros_msg

    for enc in ("rgb8", "mono8", "16UC1", "32FC1"):
        a = _random(enc)
        same_bytes(lambda c, a=a, enc=enc: numpy_to_image(
            a, enc, make_header(1_317_042_145_964_389_445, "cam", c), classes=c),
            "sensor_msgs/msg/Image")
    d = RNG.uniform(-1.0, 50.0, (4, 6))
    same_bytes(lambda c: depth_to_image(d, make_header(5, "d", c), classes=c),
               "sensor_msgs/msg/Image")
    bgr = _random("bgr8")
    same_bytes(lambda c: numpy_to_image(bgr, "bgr8", classes=c),
               "sensor_msgs/msg/Image")  # no header given: a zero stamp, no frame id
    K = np.array([[721.5, 0.0, 609.6], [0.0, 721.5, 172.9], [0.0, 0.0, 1.0]])
    P = np.hstack([K, [[44.9], [0.2], [0.003]]])
    same_bytes(lambda c: camera_info_msg(1242, 375, K, P, D=np.zeros(5),
                                         header=make_header(7, "cam", c), classes=c),
               "sensor_msgs/msg/CameraInfo")
    info = camera_info_msg(1242, 375, K, P, D=np.zeros(5), classes=bag_classes)
    assert camera_info_to_intrinsics(info) == Intrinsics(721.5, 721.5, 609.6, 172.9, 1242, 375)
    with pytest.raises(InputError, match="negative stamp"):
        make_header(-1, "cam")
    with pytest.raises(CameraInfoError, match="P must have 12 values"):
        camera_info_msg(10, 10, K, K)


# ------------------------------------------------------------------------------ Odometry
def test_odometry_written_for_bags_reads_back_in_rclpy_with_its_pose():
    from nav_msgs.msg import Odometry
    from rclpy.serialization import deserialize_message, serialize_message

    from msg_adapters import (
        OdometryError,
        odometry_msg,
        odometry_to_position,
        quaternion_to_rotation,
        rotation_to_quaternion,
    )
    from sfm_ttr_ros.ros.bag import serialize, typestore

    rng = np.random.default_rng(7)
    for angle in (0.0, 0.4, np.pi - 1e-9, np.pi):  # near and at 180 degrees too
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        R = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K
        q = rotation_to_quaternion(R)
        assert q[3] >= 0 and np.linalg.norm(q) == pytest.approx(1.0)
        np.testing.assert_allclose(quaternion_to_rotation(q), R, atol=1e-9)
    T = np.eye(4)
    T[:3, :3] = quaternion_to_rotation([0.1, -0.2, 0.3, 0.9])
    T[:3, 3] = [1.5, -2.25, 40.0]
    bag_msg = odometry_msg(1_317_042_145_964_389_086, "odom", "camera_color_left", T,
                           typestore())
    msg = deserialize_message(serialize(bag_msg, "nav_msgs/msg/Odometry"), Odometry)
    assert (msg.header.frame_id, msg.child_frame_id) == ("odom", "camera_color_left")
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_317_042_145, 964_389_086)
    stamp, xyz = odometry_to_position(msg)
    assert stamp == pytest.approx(1_317_042_145.964389086) and xyz.dtype == np.float64
    np.testing.assert_array_equal(xyz, [1.5, -2.25, 40.0])
    o = msg.pose.pose.orientation
    np.testing.assert_allclose(quaternion_to_rotation([o.x, o.y, o.z, o.w]), T[:3, :3],
                               atol=1e-12)
    assert not np.any(msg.pose.covariance) and msg.twist.twist.linear.x == 0.0
    # rclpy's own message, built by the same function, reads the same
    live = odometry_msg(5, "odom", "cam", T)
    assert odometry_to_position(deserialize_message(serialize_message(live), Odometry))[1] \
        .tolist() == [1.5, -2.25, 40.0]
    with pytest.raises(OdometryError, match="rotation"):
        odometry_msg(0, "odom", "cam", np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(OdometryError, match="4x4"):
        odometry_msg(0, "odom", "cam", np.eye(3))
    msg.pose.pose.position.x = float("nan")
    with pytest.raises(OdometryError, match="not finite"):
        odometry_to_position(msg)
