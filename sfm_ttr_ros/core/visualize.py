"""Pictures and point-cloud files for humans: depth / error colour maps and binary PLY.

ROS-free (numpy + OpenCV only). Every colour image returned here is H x W x 3 uint8 in **BGR**
order (OpenCV's), ready for ``cv2.imwrite`` or a ``bgr8`` ROS image.

Depth is coloured by *inverse* depth, as in the Monodepth2 / SfM-TTR figures: near surfaces get
the bright end of the colour map, far ones the dark end. Invalid pixels (NaN, +-inf, <= 0) are
black.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from sfm_ttr_ros.core.errors import InputError

#: Percentiles of the valid inverse depths used as the colour range when none is given.
DEPTH_PERCENTILES = (5.0, 95.0)
#: Percentile of the valid relative errors used as the top of the error colour range.
ERROR_PERCENTILE = 95.0


def _check_2d(a: np.ndarray, what: str) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.ndim != 2:
        raise InputError(f"{what}: expected an H x W array, got shape {a.shape}")
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise InputError(f"{what}: zero-size array {a.shape}")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise InputError(f"{what}: expected a numeric array, got dtype {a.dtype}")
    return a.astype(np.float64, copy=False)


def _apply_cmap(values01: np.ndarray, valid: np.ndarray, cmap: int) -> np.ndarray:
    """Colour ``values01`` (in [0, 1]) with an OpenCV colour map; invalid pixels black."""
    v = np.where(valid, np.clip(values01, 0.0, 1.0), 0.0)
    u8 = np.round(v * 255.0).astype(np.uint8)
    bgr = cv2.applyColorMap(u8, cmap)
    bgr[~valid] = 0
    return bgr


def colorize_depth(
    depth: np.ndarray,
    vmin: float | None = None,
    vmax: float | None = None,
    cmap: int = cv2.COLORMAP_MAGMA,
) -> np.ndarray:
    """Colour a depth map by inverse depth; returns H x W x 3 uint8 BGR.

    ``vmin`` / ``vmax`` are *depths* (same unit as ``depth``): pixels at ``vmin`` or nearer get
    the top colour of ``cmap`` (bright for magma), pixels at ``vmax`` or farther the bottom one.
    Either left ``None`` is taken from the 5th / 95th percentiles of the valid inverse depths.
    Pixels that are NaN, infinite or <= 0 are black; an image with no valid pixel is all black.
    """
    d = _check_2d(depth, "depth")
    valid = np.isfinite(d) & (d > 0)
    if vmin is not None and not (np.isfinite(vmin) and vmin > 0):
        raise InputError(f"vmin must be a positive finite depth, got {vmin}")
    if vmax is not None and not (np.isfinite(vmax) and vmax > 0):
        raise InputError(f"vmax must be a positive finite depth, got {vmax}")
    if vmin is not None and vmax is not None and vmin >= vmax:
        raise InputError(f"vmin must be < vmax, got vmin={vmin}, vmax={vmax}")
    if not valid.any():
        return np.zeros((*d.shape, 3), dtype=np.uint8)
    inv = np.zeros_like(d)
    inv[valid] = 1.0 / d[valid]
    if vmin is None or vmax is None:
        lo_p, hi_p = np.percentile(inv[valid], DEPTH_PERCENTILES)
    inv_hi = 1.0 / vmin if vmin is not None else hi_p  # nearest -> top of the map
    inv_lo = 1.0 / vmax if vmax is not None else lo_p  # farthest -> bottom of the map
    span = inv_hi - inv_lo
    if not span > 0:  # constant depth (or percentile range collapsed): mid colour
        norm = np.full_like(inv, 0.5)
    else:
        norm = (inv - inv_lo) / span
    return _apply_cmap(norm, valid, cmap)


def colorize_error(
    pred: np.ndarray,
    gt: np.ndarray,
    vmax: float | None = None,
    cmap: int = cv2.COLORMAP_JET,
) -> np.ndarray:
    """Colour the relative error ``|pred - gt| / gt``; returns H x W x 3 uint8 BGR.

    Zero error is the bottom colour of ``cmap``, ``vmax`` (a relative error; default the 95th
    percentile of the valid errors, at least 1e-6) and above the top. Pixels where ``gt`` is
    not finite and > 0 (no ground truth, e.g. sparse KITTI) or ``pred`` is not finite are black.
    """
    p = _check_2d(pred, "pred")
    g = _check_2d(gt, "gt")
    if p.shape != g.shape:
        raise InputError(f"pred and gt must have the same shape, got {p.shape} and {g.shape}")
    if vmax is not None and not (np.isfinite(vmax) and vmax > 0):
        raise InputError(f"vmax must be a positive finite relative error, got {vmax}")
    valid = np.isfinite(g) & (g > 0) & np.isfinite(p)
    if not valid.any():
        return np.zeros((*p.shape, 3), dtype=np.uint8)
    err = np.zeros_like(p)
    err[valid] = np.abs(p[valid] - g[valid]) / g[valid]
    if vmax is None:
        vmax = max(float(np.percentile(err[valid], ERROR_PERCENTILE)), 1e-6)
    return _apply_cmap(err / vmax, valid, cmap)


def _ply_name(name: str) -> str:
    if not name or any(c.isspace() for c in name) or not name.isprintable():
        raise InputError(f"PLY property names must be non-empty without whitespace, got {name!r}")
    return name


def write_ply(
    path: str | Path,
    xyz: np.ndarray,
    rgb: np.ndarray | None = None,
    extra: dict[str, np.ndarray] | None = None,
) -> Path:
    """Write points to a binary little-endian PLY file; returns the path.

    Vertex properties: ``float x, y, z``; then ``uchar red, green, blue`` when ``rgb`` (N x 3
    uint8, RGB order) is given; then one ``float`` property per ``extra`` entry (N values each,
    e.g. ``{"reprojection_error": r}``), in the dict's order. Non-finite values are written as
    they are (MeshLab / CloudCompare / Open3D read them).
    """
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"xyz must be N x 3, got shape {xyz.shape}")
    n = xyz.shape[0]
    fields: list[tuple[str, str]] = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if rgb is not None:
        rgb = np.asarray(rgb)
        if rgb.shape != (n, 3):
            raise InputError(f"rgb must be {n} x 3 (like xyz), got shape {rgb.shape}")
        if rgb.dtype != np.uint8:
            raise InputError(f"rgb must be uint8, got {rgb.dtype}")
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    extras: dict[str, np.ndarray] = {}
    for name, values in (extra or {}).items():
        name = _ply_name(name)
        if name in {f for f, _ in fields}:
            raise InputError(f"extra property {name!r} clashes with a standard PLY property")
        v = np.asarray(values).reshape(-1)
        if v.shape[0] != n:
            raise InputError(f"extra property {name!r} has {v.shape[0]} values for {n} points")
        extras[name] = v
        fields.append((name, "<f4"))
    rec = np.empty(n, dtype=np.dtype(fields))
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if rgb is not None:
        rec["red"], rec["green"], rec["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    for name, v in extras.items():
        rec[name] = v
    type_names = {"<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property {type_names[t]} {name}" for name, t in fields]
    header.append("end_header")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(rec.tobytes())
    return path


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


def read_ply(path: str | Path) -> np.ndarray:
    """Read the vertices of a binary PLY file with only scalar vertex properties (as written
    by :func:`write_ply`) into a structured numpy array (one field per property)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read PLY file {path}: {exc}") from exc
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise InputError(f"{path}: not a PLY file (missing 'ply' / 'end_header')")
    lines = raw[:end].decode("ascii", errors="replace").splitlines()
    order, n, fields, element = None, None, [], None
    for line in lines[1:]:
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(tok[1])
            if order is None:
                raise InputError(f"{path}: unsupported PLY format {tok[1]!r} (binary only)")
        elif tok[0] == "element":
            element = tok[1]
            if element == "vertex":
                n = int(tok[2])
        elif tok[0] == "property" and element == "vertex":
            if tok[1] == "list" or tok[1] not in _PLY_TYPES:
                raise InputError(f"{path}: unsupported vertex property {line!r}")
            fields.append((tok[2], order + _PLY_TYPES[tok[1]]))
    if order is None or n is None:
        raise InputError(f"{path}: PLY header without format or vertex element")
    dtype = np.dtype(fields)
    body = raw[end + len(b"end_header\n") :]
    if len(body) < n * dtype.itemsize:
        raise InputError(
            f"{path}: truncated PLY, expected {n * dtype.itemsize} bytes of vertices, "
            f"got {len(body)}"
        )
    return np.frombuffer(body, dtype=dtype, count=n).copy()
