"""compressedDepth as compressed_depth_image_transport writes and reads it (codec.cpp): the
12-byte ConfigHeader, the 16-bit PNG of quantised inverse depth, the decoder's rules, and the
bytes it saves on a real network depth at KITTI size."""

from __future__ import annotations

import struct
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

pytest.importorskip("sensor_msgs")

from msg_adapters.compressed_depth import (  # noqa: E402
    CompressedDepthError,
    compressed_depth_to_depth,
    compressed_depth_to_numpy,
    depth_to_compressed_depth,
    quantisation,
    quantisation_error,
)
from sfm_ttr_ros.core.errors import InputError  # noqa: E402

KITTI_SIZE = (1242, 375)  # width, height


def test_the_message_is_codec_cpps_header_then_a_png_of_quantised_inverse_depth():
    depth = np.array([[0.5, 1.0, 2.0], [9.99, 10.0, np.nan], [0.0, -1.0, 0.01]], np.float32)
    msg = depth_to_compressed_depth(depth)
    assert msg.format == "32FC1; compressedDepth png"
    data = bytes(msg.data)
    fmt, a, b = struct.unpack("<iff", data[:12])
    # defaults depth_quantization 100, depth_max 10: A = 100 * 101, B = 1 - A / 10
    assert (fmt, a, b) == (0, 10100.0, np.float32(1 - 10100 / 10))
    q = cv2.imdecode(np.frombuffer(data[12:], np.uint8), cv2.IMREAD_UNCHANGED)
    assert q.dtype == np.uint16 and q.shape == (3, 3)
    # q = A / d + B truncated; none (0) at or beyond depth_max, for NaN and for d <= 0; 65535
    # where the uint16 overflows (d = 1 cm)
    want = [[int(np.float32(10100) / np.float32(d) + np.float32(b)) for d in (0.5, 1.0, 2.0)],
            [int(np.float32(10100) / np.float32(9.99) + np.float32(b)), 0, 0], [0, 0, 65535]]
    np.testing.assert_array_equal(q, want)


def test_a_depth_decodes_back_within_one_step_of_inverse_depth():
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.3, 90.0, (40, 60)).astype(np.float32)
    depth[0, :5] = np.nan
    msg = depth_to_compressed_depth(depth, depth_max=80.0)
    back = compressed_depth_to_depth(msg)
    near = depth < 80.0
    assert np.all(np.isnan(back[~near])) and np.all(np.isfinite(back[near]))
    inv_err = 1 / depth[near] - 1 / back[near]  # d' >= d: truncation rounds q down
    assert inv_err.min() >= -1e-7 and inv_err.max() <= quantisation_error(80.0) * 1.001
    assert quantisation_error(80.0) == pytest.approx(1 / 10100)
    a, b = quantisation(80.0)
    assert (a, b) == (10100.0, pytest.approx(1 - 10100 / 80))


def test_16uc1_depth_is_the_png_itself_cut_at_depth_max():
    mm = np.array([[0, 1500, 9000], [10000, 10001, 65535]], np.uint16)
    msg = depth_to_compressed_depth(mm, encoding="16UC1")
    assert msg.format == "16UC1; compressedDepth png"
    encoding, back = compressed_depth_to_numpy(msg)
    assert encoding == "16UC1"
    np.testing.assert_array_equal(back, [[0, 1500, 9000], [10000, 0, 0]])
    metres = compressed_depth_to_depth(msg)
    assert np.isnan(metres[0, 0]) and metres[0, 1] == pytest.approx(1.5)


def _msg(fmt: str, data: bytes):
    return SimpleNamespace(format=fmt, data=data)


def test_what_the_decoder_refuses_is_an_input_error():
    good = depth_to_compressed_depth(np.full((4, 4), 2.0, np.float32))
    data = bytes(good.data)
    eight_bit = cv2.imencode(".png", np.zeros((4, 4), np.uint8))[1].tobytes()
    cases = {
        "only png": _msg("32FC1; compressedDepth rvl", data),
        "no image after": _msg("32FC1; compressedDepth png", data[:12]),
        "not INV_DEPTH": _msg("32FC1; compressedDepth png", struct.pack("<iff", -1, 1, 1)
                              + data[12:]),
        "16-bit": _msg("32FC1; compressedDepth png", data[:12] + eight_bit),
        "not a depth encoding": _msg("rgb8; compressedDepth png", data),
        "neither JPEG nor PNG": _msg("32FC1; compressedDepth png", data[:12] + b"garbage!" * 4),
    }
    for what, msg in cases.items():
        with pytest.raises(CompressedDepthError, match=what):
            compressed_depth_to_numpy(msg)
    assert issubclass(CompressedDepthError, InputError)
    # an old message without the "; compressedDepth" part is a PNG (decodeCompressedDepthImage)
    np.testing.assert_allclose(compressed_depth_to_depth(_msg("32FC1", data)), 2.0, rtol=1e-3)
    with pytest.raises(CompressedDepthError, match="floating point"):
        depth_to_compressed_depth(np.ones((2, 2), np.uint16))
    with pytest.raises(CompressedDepthError, match="32FC1 or 16UC1"):
        depth_to_compressed_depth(np.ones((2, 2), np.float32), encoding="bgr8")
    with pytest.raises(CompressedDepthError, match="depth_max"):
        depth_to_compressed_depth(np.ones((2, 2), np.float32), depth_max=0.0)


@pytest.mark.slow
def test_a_real_depth_at_kitti_size_takes_at_most_a_quarter_of_the_raw_bytes(shared_data,
                                                                              one_thread):
    """The default network's depth of a real frame (hololens_000), at KITTI's size, with the
    node's defaults (depth_max 100, PNG level 1): measured 0.18 of the 32FC1 bytes."""
    from sfm_ttr_ros.core.models.registry import ModelConfig, build_model

    frame = cv2.imread(str(sorted((shared_data / "hololens_000" / "images").glob("*.png"))[0]))
    rgb = np.ascontiguousarray(cv2.resize(frame, KITTI_SIZE)[:, :, ::-1])
    depth = build_model(ModelConfig()).predict([rgb])[0].astype(np.float32)
    msg = depth_to_compressed_depth(depth, depth_max=100.0, png_level=1)
    ratio = len(msg.data) / depth.nbytes
    assert depth.shape == KITTI_SIZE[::-1] and ratio <= 0.25, ratio
    back = compressed_depth_to_depth(msg)
    assert np.max(np.abs(1 / depth - 1 / back)) <= quantisation_error(100.0) * 1.001
