"""sensor_msgs/PointCloud2 <-> numpy, without sensor_msgs_py.

Clouds written here are unorganized (height 1, width N), little-endian, float32 x, y, z at
offsets 0, 4, 8 followed by one float32 per extra field (e.g. ``reprojection_error``, or
``rgb``), with no padding. Reading handles any scalar layout: all PointField datatypes,
``count`` > 1, ``point_step`` padding, ``row_step`` padding, height > 1 and ``is_bigendian``.

:func:`depth_to_pointcloud2` back-projects a depth image with the CameraInfo published beside it,
as depth_image_proc's ``point_cloud_xyzrgb`` does (P's fx, fy, cx, cy; x = (u - cx) z / fx),
every ``stride``-th pixel, with PCL's packed ``rgb`` (:func:`pack_rgb`).
"""

from __future__ import annotations

import array

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from sfm_ttr_ros.core.errors import InputError


class PointCloudError(InputError):
    """A PointCloud2 (or array) that cannot be converted."""


#: PointField datatype -> numpy element type (without byte order).
DATATYPES: dict[int, str] = {
    PointField.INT8: "i1",
    PointField.UINT8: "u1",
    PointField.INT16: "i2",
    PointField.UINT16: "u2",
    PointField.INT32: "i4",
    PointField.UINT32: "u4",
    PointField.FLOAT32: "f4",
    PointField.FLOAT64: "f8",
}


def numpy_to_pointcloud2(
    xyz: np.ndarray,
    header: Header | None = None,
    fields: dict[str, np.ndarray] | None = None,
) -> PointCloud2:
    """An unorganized PointCloud2 of N points: float32 x, y, z plus one float32 field per entry
    of ``fields`` (N values each, in the dict's order). ``is_dense`` is true only when every
    value (coordinates and extra fields) is finite."""
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise PointCloudError(f"xyz must be N x 3, got shape {xyz.shape}")
    n = int(xyz.shape[0])
    names = ["x", "y", "z"]
    extra: list[np.ndarray] = []
    for name, values in (fields or {}).items():
        if not isinstance(name, str) or not name:
            raise PointCloudError(f"field names must be non-empty strings, got {name!r}")
        if name in names:
            raise PointCloudError(f"duplicate point field name {name!r}")
        v = np.asarray(values).reshape(-1)
        if v.shape[0] != n:
            raise PointCloudError(f"field {name!r} has {v.shape[0]} values for {n} points")
        names.append(name)
        extra.append(v)
    dtype = np.dtype({"names": names, "formats": ["<f4"] * len(names)})
    rec = np.empty(n, dtype=dtype)
    for i, name in enumerate(("x", "y", "z")):
        rec[name] = xyz[:, i]
    for name, v in zip(names[3:], extra, strict=True):
        rec[name] = v
    msg = PointCloud2()
    if header is not None:
        msg.header = header
    msg.height, msg.width = 1, n
    msg.fields = [
        PointField(name=name, offset=4 * i, datatype=PointField.FLOAT32, count=1)
        for i, name in enumerate(names)
    ]
    msg.is_bigendian = False
    msg.point_step = dtype.itemsize
    msg.row_step = dtype.itemsize * n
    flat = rec.view(np.float32).reshape(-1) if n else np.empty(0, np.float32)
    msg.is_dense = bool(np.isfinite(flat).all())
    msg.data = array.array("B", rec.tobytes())
    return msg


def pack_rgb(rgb: np.ndarray) -> np.ndarray:
    """N x 3 uint8 RGB -> N float32 holding the bits 0x00RRGGBB (PCL's ``rgb`` field, as RViz
    and depth_image_proc read it)."""
    c = np.asarray(rgb, np.uint8).reshape(-1, 3).astype(np.uint32)
    return ((c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]).view(np.float32)


def unpack_rgb(packed: np.ndarray) -> np.ndarray:
    """The inverse of :func:`pack_rgb`: N float32 -> N x 3 uint8 RGB."""
    bits = np.ascontiguousarray(packed, np.float32).view(np.uint32)
    return np.stack([(bits >> 16) & 0xFF, (bits >> 8) & 0xFF, bits & 0xFF], 1).astype(np.uint8)


def depth_to_pointcloud2(
    depth: np.ndarray,
    rgb: np.ndarray | None,
    camera_info,
    stride: int = 4,
    max_range: float = 0.0,
    header: Header | None = None,
) -> PointCloud2:
    """The depth image back-projected into an unorganized cloud (x, y, z and, with ``rgb``,
    PCL's packed ``rgb``), in the depth's optical frame and units.

    ``camera_info``: the CameraInfo published beside the depth (:func:`~msg_adapters.
    camera_info.projection_of`: P, else K). Pixels (u, v) with u, v multiples of ``stride``,
    row by row; z = depth, x = (u - cx) z / fx, y = (v - cy) z / fy. Left out: non-finite or
    non-positive depth and, with ``max_range`` > 0, points farther than ``max_range`` from the
    camera centre. ``rgb``: H x W x 3 uint8 RGB of the same size as ``depth`` (the input image).
    ``header`` default: the CameraInfo's. ``is_dense`` is true only when every point is finite.
    """
    from msg_adapters.camera_info import projection_of

    d = np.asarray(depth)
    if d.ndim != 2 or not d.size:
        raise PointCloudError(f"depth must be a non-empty H x W array, got shape {d.shape}")
    if int(stride) < 1:
        raise PointCloudError(f"stride must be >= 1, got {stride}")
    if rgb is not None and np.shape(rgb) != (*d.shape, 3):
        raise PointCloudError(f"rgb must be {d.shape[0]} x {d.shape[1]} x 3 like the depth, got "
                              f"shape {np.shape(rgb)}")
    fx, fy, cx, cy = projection_of(camera_info)
    s = int(stride)
    z = d[::s, ::s].astype(np.float64)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(z) & (z > 0)
    rows, cols = np.nonzero(valid)
    z = z[rows, cols]
    xyz = np.empty((z.size, 3), np.float64)
    xyz[:, 0] = (cols * s - cx) * z / fx
    xyz[:, 1] = (rows * s - cy) * z / fy
    xyz[:, 2] = z
    if max_range > 0:
        near = np.einsum("ij,ij->i", xyz, xyz) <= float(max_range) ** 2
        xyz, rows, cols = xyz[near], rows[near], cols[near]
    fields = None
    if rgb is not None:
        fields = {"rgb": pack_rgb(np.asarray(rgb)[::s, ::s][rows, cols])}
    return numpy_to_pointcloud2(xyz.astype(np.float32), camera_info.header if header is None
                                else header, fields)


def _dtype_of(msg: PointCloud2) -> np.dtype:
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    point_step = int(msg.point_step)
    for f in msg.fields:
        if f.datatype not in DATATYPES:
            raise PointCloudError(
                f"point field {f.name!r} has unknown datatype {f.datatype} "
                f"(known: {sorted(DATATYPES)})"
            )
        if f.name in names:
            raise PointCloudError(f"duplicate point field name {f.name!r}")
        base = np.dtype(order + DATATYPES[f.datatype])
        count = max(int(f.count), 1)
        fmt = base if count == 1 else np.dtype((base, (count,)))
        if int(f.offset) + fmt.itemsize > point_step:
            raise PointCloudError(
                f"point field {f.name!r} (offset {f.offset}, {fmt.itemsize} bytes) does not fit "
                f"in point_step {point_step}"
            )
        names.append(f.name)
        formats.append(fmt)
        offsets.append(int(f.offset))
    return np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step}
    )


def _packed(dtype: np.dtype) -> np.dtype:
    """The same fields, in the same order, without padding and in native byte order."""
    formats = [dtype[n].newbyteorder("=") for n in dtype.names]
    return np.dtype({"names": list(dtype.names), "formats": formats})


def pointcloud2_to_numpy(msg: PointCloud2) -> np.ndarray:
    """Decode a PointCloud2 into a 1-D structured array of height x width points (row-major;
    ``.reshape(msg.height, msg.width)`` restores an organized cloud), one field per
    PointField, packed (no padding), in native byte order. Always a copy."""
    if not msg.fields:
        raise PointCloudError("PointCloud2 has no fields")
    dtype = _dtype_of(msg)
    h, w = int(msg.height), int(msg.width)
    if h == 0 or w == 0:
        return np.empty(0, dtype=_packed(dtype))
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    if point_step <= 0:
        raise PointCloudError(f"PointCloud2 point_step must be positive, got {point_step}")
    row_bytes = w * point_step
    if row_step < row_bytes:
        raise PointCloudError(
            f"PointCloud2 row_step {row_step} is smaller than width x point_step = "
            f"{w} x {point_step} = {row_bytes}"
        )
    expected = row_step * (h - 1) + row_bytes  # the last row's padding may be left out
    got = len(msg.data)
    if got < expected:
        raise PointCloudError(
            f"truncated PointCloud2 {w}x{h}: expected {expected} bytes "
            f"(row_step {row_step}, point_step {point_step}), got {got}"
        )
    buf = np.frombuffer(msg.data, dtype=np.uint8, count=got)
    if row_step == row_bytes:
        raw = buf[: h * row_bytes]
    elif got >= h * row_step:
        raw = np.ascontiguousarray(buf[: h * row_step].reshape(h, row_step)[:, :row_bytes])
    else:
        raw = np.concatenate([buf[r * row_step : r * row_step + row_bytes] for r in range(h)])
    return raw.reshape(-1).view(dtype).astype(_packed(dtype))  # a copy: packed, native byte order


def pointcloud2_to_xyz(msg: PointCloud2, skip_nans: bool = True) -> np.ndarray:
    """The x, y, z of every point as an N x 3 float32 array; with ``skip_nans`` the points with
    any non-finite coordinate are left out."""
    names = [f.name for f in msg.fields]
    missing = [c for c in ("x", "y", "z") if c not in names]
    if missing:
        raise PointCloudError(f"PointCloud2 has no {'/'.join(missing)} field (fields: {names})")
    pts = pointcloud2_to_numpy(msg)
    xyz = np.empty((pts.shape[0], 3), dtype=np.float32)
    for i, c in enumerate(("x", "y", "z")):
        if pts.dtype[c].shape:
            raise PointCloudError(f"PointCloud2 field {c!r} has count > 1")
        xyz[:, i] = pts[c]
    if skip_nans:
        xyz = xyz[np.isfinite(xyz).all(axis=1)]
    return xyz
