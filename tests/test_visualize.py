"""sfm_ttr_ros.core.visualize: depth / error colour maps and binary PLY."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.visualize import colorize_depth, colorize_error, read_ply, write_ply


def _gray(bgr: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY).astype(np.int32)


def _cmap_colour(level: int, cmap: int) -> np.ndarray:
    return cv2.applyColorMap(np.full((1, 1), level, np.uint8), cmap)[0, 0]


def test_colorize_depth_shape_dtype_and_invalid_black():
    rng = np.random.default_rng(0)
    depth = rng.uniform(2.0, 60.0, size=(37, 53)).astype(np.float32)
    bad = [(0, 0, np.nan), (1, 1, 0.0), (2, 2, -3.0), (3, 3, np.inf), (4, 4, -np.inf)]
    for r, c, v in bad:
        depth[r, c] = v
    out = colorize_depth(depth)
    assert out.shape == (37, 53, 3) and out.dtype == np.uint8
    for r, c, _ in bad:
        assert out[r, c].tolist() == [0, 0, 0]
    valid = np.ones(depth.shape, bool)
    for r, c, _ in bad:
        valid[r, c] = False
    # magma's darkest entry is not pure black, so every valid pixel stays distinguishable
    assert (out[valid].sum(axis=1) > 0).all()


def test_colorize_depth_near_is_brighter_and_monotone():
    depth = np.tile(np.linspace(1.0, 80.0, 200), (4, 1))  # near on the left, far on the right
    out = colorize_depth(depth, vmin=1.0, vmax=80.0)
    g = _gray(out)[0]
    assert g[0] > g[-1] + 100  # near bright, far dark (inverse-depth magma)
    assert (np.diff(g) <= 1).all()  # non-increasing with depth (1 level of rounding slack)
    # explicit range: vmin gets the top of the map, vmax and beyond the bottom
    assert out[0, 0].tolist() == _cmap_colour(255, cv2.COLORMAP_MAGMA).tolist()
    far = colorize_depth(np.array([[80.0, 500.0]]), vmin=1.0, vmax=80.0)
    assert far[0, 0].tolist() == far[0, 1].tolist() == _cmap_colour(0, cv2.COLORMAP_MAGMA).tolist()


def test_colorize_depth_default_range_and_degenerate_inputs():
    depth = np.tile(np.geomspace(2.0, 50.0, 100), (3, 1))
    out = colorize_depth(depth)
    g = _gray(out)[0]
    assert g[0] > g[-1]
    assert colorize_depth(np.full((4, 5), np.nan)).max() == 0  # nothing valid: all black
    const = colorize_depth(np.full((4, 5), 7.0))
    assert (const == const[0, 0]).all() and const[0, 0].sum() > 0
    other = colorize_depth(depth, cmap=cv2.COLORMAP_JET)
    assert not np.array_equal(other, out)
    with pytest.raises(InputError, match="H x W"):
        colorize_depth(np.zeros((2, 3, 3)))
    with pytest.raises(InputError, match="vmin must be < vmax"):
        colorize_depth(depth, vmin=10.0, vmax=5.0)


def test_colorize_error():
    gt = np.full((10, 12), 10.0)
    pred = gt.copy()
    pred[:, 6:] = 13.0  # 30 % error on the right half
    gt[0, 0] = 0.0  # no ground truth
    gt[0, 1] = np.nan
    pred[0, 2] = np.inf  # bad prediction
    out = colorize_error(pred, gt, vmax=0.3)
    assert out.shape == (10, 12, 3) and out.dtype == np.uint8
    for c in (0, 1, 2):
        assert out[0, c].tolist() == [0, 0, 0]
    assert out[5, 0].tolist() == _cmap_colour(0, cv2.COLORMAP_JET).tolist()
    assert out[5, 11].tolist() == _cmap_colour(255, cv2.COLORMAP_JET).tolist()
    auto = colorize_error(pred, gt)  # 95th percentile range: the error half is the top colour
    assert auto[5, 11].tolist() == _cmap_colour(255, cv2.COLORMAP_JET).tolist()
    with pytest.raises(InputError, match="same shape"):
        colorize_error(pred, gt[:5])


def _parse_header(raw: bytes) -> tuple[list[str], int]:
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    return raw[:end].decode("ascii").splitlines(), end


def test_write_ply_header_and_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    n = 257
    xyz = rng.normal(size=(n, 3)).astype(np.float64)
    rgb = rng.integers(0, 256, size=(n, 3), dtype=np.uint8)
    err = rng.uniform(0, 2, size=n).astype(np.float32)
    err[3] = np.nan
    path = write_ply(tmp_path / "sub" / "cloud.ply", xyz, rgb, {"reprojection_error": err})
    raw = path.read_bytes()
    lines, body_start = _parse_header(raw)
    assert lines == [
        "ply",
        "format binary_little_endian 1.0",
        f"element vertex {n}",
        "property float x",
        "property float y",
        "property float z",
        "property uchar red",
        "property uchar green",
        "property uchar blue",
        "property float reprojection_error",
        "end_header",
    ]
    dtype = np.dtype(
        [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"),
         ("blue", "u1"), ("reprojection_error", "<f4")]
    )  # fmt: skip
    assert len(raw) - body_start == n * dtype.itemsize == n * 19
    rec = np.frombuffer(raw[body_start:], dtype=dtype)
    np.testing.assert_array_equal(np.stack([rec["x"], rec["y"], rec["z"]], 1), xyz.astype("f4"))
    np.testing.assert_array_equal(np.stack([rec["red"], rec["green"], rec["blue"]], 1), rgb)
    np.testing.assert_array_equal(rec["reprojection_error"], err)  # NaN compares equal here
    back = read_ply(path)
    assert back.dtype.names == dtype.names
    np.testing.assert_array_equal(back["reprojection_error"], err)


def test_write_ply_xyz_only_and_errors(tmp_path):
    xyz = np.arange(12, dtype=np.float32).reshape(4, 3)
    back = read_ply(write_ply(tmp_path / "p.ply", xyz))
    assert back.dtype.names == ("x", "y", "z")
    np.testing.assert_array_equal(back["z"], xyz[:, 2])
    empty = read_ply(write_ply(tmp_path / "e.ply", np.zeros((0, 3))))
    assert empty.shape == (0,)
    with pytest.raises(InputError, match="N x 3"):
        write_ply(tmp_path / "bad.ply", np.zeros((4, 2)))
    with pytest.raises(InputError, match="rgb"):
        write_ply(tmp_path / "bad.ply", xyz, np.zeros((3, 3), np.uint8))
    with pytest.raises(InputError, match="3 values for 4 points"):
        write_ply(tmp_path / "bad.ply", xyz, extra={"e": np.zeros(3)})
    with pytest.raises(InputError, match="whitespace"):
        write_ply(tmp_path / "bad.ply", xyz, extra={"bad name": np.zeros(4)})
    (tmp_path / "trunc.ply").write_bytes((tmp_path / "p.ply").read_bytes()[:-5])
    with pytest.raises(InputError, match="truncated"):
        read_ply(tmp_path / "trunc.ply")
