"""A drive's camera poses and camera height, and real KITTI's OXTS as poses (ROS-free).

Files beside a drive's images (``<raw>/<date>/<drive>/``; also the layout of an image folder
of a recorded video with poses, ``poses.txt`` beside ``images/``):

* ``poses.txt``: one row per frame, in frame order: the 4x4 camera-to-world matrix, row-major,
  16 numbers, metres (:func:`read_poses`, :func:`write_poses`);
* ``camera_height.txt``: the camera's height above the road, metres, one number (generated
  drives know it; :func:`read_camera_height`, :func:`write_camera_height`).

Real KITTI raw drives have no camera poses but the GPS/IMU's: ``oxts/data/NNNNNNNNNN.txt`` (30
numbers: lat, lon, alt, roll, pitch, yaw, ...) with ``oxts/timestamps.txt``.
:func:`oxts_poses` converts them as the KITTI devkit does (``convertOxtsToPose``): a Mercator
projection with the scale of the first frame's latitude, the rotation Rz(yaw) Ry(pitch)
Rx(roll), every pose relative to the first frame's. The result is the IMU's pose (x forward,
y left, z up) in metres, not the camera's: its positions are enough for the distance travelled
between frames, its orientation is not the camera's.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from sfm_ttr_ros.core.errors import InputError

POSES_FILE = "poses.txt"
CAMERA_HEIGHT_FILE = "camera_height.txt"
OXTS_DIR = "oxts"
EARTH_RADIUS_M = 6378137.0  # the devkit's (WGS84 equatorial radius)


def write_poses(path: str | Path, cam_to_world: Sequence[np.ndarray]) -> None:
    """One row per 4x4 camera-to-world matrix: its 16 numbers, row-major (numpy's text)."""
    arr = np.asarray(cam_to_world, np.float64)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4) or not np.isfinite(arr).all():
        raise InputError(f"poses must be finite 4x4 matrices, got shape {arr.shape}")
    np.savetxt(path, arr.reshape(len(arr), 16))


def read_poses(path: str | Path) -> np.ndarray:
    """The N x 4 x 4 camera-to-world matrices of a ``poses.txt``; InputError for a row that is
    not 16 finite numbers ending in 0 0 0 1."""
    path = Path(path)
    try:
        rows = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read poses from {path}: {exc}") from exc
    if rows.shape[0] == 0 or rows.shape[1] != 16:
        raise InputError(f"{path}: expected rows of 16 numbers (a 4x4 camera-to-world "
                         f"matrix, row-major), got shape {rows.shape}")
    poses = rows.reshape(-1, 4, 4)
    bad = ~np.isfinite(rows).all(1) | ~np.all(np.abs(poses[:, 3] - [0, 0, 0, 1]) < 1e-6, axis=1)
    if bad.any():
        raise InputError(f"{path}: row {int(np.argmax(bad)) + 1} is not a rigid 4x4 pose "
                         "(non-finite, or its last row is not 0 0 0 1)")
    return poses


def write_camera_height(path: str | Path, metres: float) -> None:
    if not (math.isfinite(metres) and metres > 0):
        raise InputError(f"camera height must be > 0 m, got {metres}")
    Path(path).write_text(f"{float(metres):.6f}\n")


def read_camera_height(path: str | Path) -> float:
    path = Path(path)
    try:
        value = float(path.read_text().split()[0])
    except (OSError, ValueError, IndexError) as exc:
        raise InputError(f"cannot read a camera height (metres) from {path}: {exc}") from exc
    if not (math.isfinite(value) and value > 0):
        raise InputError(f"{path}: camera height must be > 0 m, got {value}")
    return value


def read_oxts_packet(path: str | Path) -> np.ndarray:
    """The numbers of one ``oxts/data/*.txt`` (lat, lon, alt, roll, pitch, yaw first)."""
    path = Path(path)
    try:
        values = np.array(path.read_text().split(), dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read OXTS data from {path}: {exc}") from exc
    if values.size < 6 or not np.isfinite(values[:6]).all():
        raise InputError(f"{path}: expected at least lat lon alt roll pitch yaw, got "
                         f"{values.size} numbers")
    return values


def oxts_poses(packets: Sequence[np.ndarray]) -> np.ndarray:
    """The devkit's ``convertOxtsToPose``: N x 4 x 4 IMU poses in metres, relative to the first
    packet's (so the first is the identity); Mercator scale of the first latitude."""
    if not len(packets):
        raise InputError("no OXTS packets")
    scale = math.cos(math.radians(float(packets[0][0])))
    out, first_inv = [], None
    for p in packets:
        lat, lon, alt, roll, pitch, yaw = (float(v) for v in p[:6])
        t = [scale * lon * math.pi * EARTH_RADIUS_M / 180.0,
             scale * EARTH_RADIUS_M * math.log(math.tan((90.0 + lat) * math.pi / 360.0)), alt]
        T = np.eye(4)
        T[:3, :3] = rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)
        T[:3, 3] = t
        if first_inv is None:
            first_inv = np.linalg.inv(T)
        out.append(first_inv @ T)
    return np.array(out)


def rot_x(a: float) -> np.ndarray:
    """Rotation by ``a`` radians about x."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    """Rotation by ``a`` radians about y."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(a: float) -> np.ndarray:
    """Rotation by ``a`` radians about z."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def read_frame_poses(path: str | Path, frames: int) -> np.ndarray | None:
    """The camera poses of a ``poses.txt`` that holds one row per frame of a sequence of
    ``frames`` frames; None when there is no such file, InputError when its rows are not one
    per frame (it would belong to another sequence)."""
    path = Path(path)
    if not path.is_file():
        return None
    poses = read_poses(path)
    if len(poses) != frames:
        raise InputError(f"{path}: {len(poses)} poses for {frames} frames")
    return poses


def drive_oxts_poses(drive_dir: str | Path, frame_names: Sequence[str]) -> np.ndarray | None:
    """The IMU poses of a real KITTI drive's frames from its ``oxts/`` (frame by name: the
    ``_sync`` drives have one packet per image, same file names), or None when the drive has no
    ``oxts/data``. InputError when a frame has no packet or ``oxts/timestamps.txt`` is missing
    or shorter than the packets."""
    oxts = Path(drive_dir) / OXTS_DIR
    data = oxts / "data"
    if not data.is_dir() or not any(data.glob("*.txt")):
        return None
    stamps = oxts / "timestamps.txt"
    n_stamps = (len([ln for ln in stamps.read_text().splitlines() if ln.strip()])
                if stamps.is_file() else 0)
    packets = []
    for name in frame_names:
        path = data / f"{name}.txt"
        if not path.is_file():
            raise InputError(f"{data} has no OXTS packet for frame {name}")
        packets.append(read_oxts_packet(path))
    if n_stamps < len(packets):
        raise InputError(f"{stamps}: {n_stamps} timestamps for {len(packets)} OXTS packets "
                         "(an incomplete oxts/ folder)")
    return oxts_poses(packets)
