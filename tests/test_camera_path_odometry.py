"""The camera's path as the robot base's odometry (core/stream/base_odometry.py), message by
message: the base's pose for a camera mounted off it, odom's gravity-aligned axes, no step
across a fresh map that does not fit the path exactly nor across a break, the twist against
finite differences, and covariances that stay positive definite and grow with the distance."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_camera_path import _rot, _window

from sfm_ttr_ros.core.camera_path import BODY_FROM_OPTICAL, CameraPath, WindowPoses
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.stream.base_odometry import (
    DEFAULT_CAMERA_MOUNT,
    DRIFT_PER_DISTANCE,
    BaseOdometry,
    parse_camera_mount,
    rotation_vector,
)

UP = np.array([0.0, -1.0, 0.0])  # the drives' world: y down (data/synthetic conventions)
DT = 0.1  # _window's stamps: 0.1 s per frame


def _car_drive(n: int = 30) -> list[np.ndarray]:
    """Base-to-world poses (REP 103 axes: x forward, y left, z up) of a car driving 1 m per
    frame (10 m/s) on the level ground of a world with y down (data/synthetic's), turning left
    0.02 rad per frame."""
    car_axes = np.column_stack([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    poses, c = [], np.zeros(3)
    for i in range(n):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = car_axes @ _rot(2, 0.02 * i), c
        poses.append(T)
        c = c + T[:3, 0]
    return poses


def _cameras(cars: list[np.ndarray], mount: np.ndarray) -> list[np.ndarray]:
    """Camera-to-world optical poses of a camera mounted on the car by ``mount``."""
    return [car @ mount for car in cars]


def _odometry(mount: np.ndarray, windows: list[WindowPoses]):
    path, odometry, out = CameraPath(), BaseOdometry(mount), []
    for w in windows:
        out += [(p, odometry.add(p)) for p in path.add(w)]
    return path, out


def test_the_default_mount_is_rep103s_optical_frame_and_a_bad_one_is_refused():
    np.testing.assert_allclose(parse_camera_mount(DEFAULT_CAMERA_MOUNT)[:3, :3],
                               BODY_FROM_OPTICAL, atol=1e-12)
    T = parse_camera_mount("1, 2, 3, 0, 0, 90")
    np.testing.assert_allclose(T[:3, 3], [1, 2, 3])
    np.testing.assert_allclose(T[:3, :3], _rot(2, math.pi / 2), atol=1e-12)
    for bad in ("", "1 2 3", "0 0 0 0 0 x", "0 0 0 0 0 nan"):
        with pytest.raises(InputError, match="odom.camera_mount"):
            parse_camera_mount(bad)


def test_the_pose_is_the_bases_not_the_cameras_for_a_mount_off_its_origin():
    gt = _car_drive(20)
    mount = parse_camera_mount("1.5 0.3 1.2 -95 4 -88")  # roughly forward, up and pitched
    cam = _cameras(gt, mount)
    R, t, s = _rot(0, 0.3) @ _rot(2, -1.1), np.array([3.0, -2.0, 7.0]), 0.25

    def windows():
        return [_window(cam, range(0, 10), s, R, t, "fresh", metres=1 / s),
                _window(cam, range(5, 20), s, R, t, "continued")]

    _, out = _odometry(mount, windows())
    assert len(out) == 20
    np.testing.assert_allclose(out[0][1].odom_from_base, np.eye(4), atol=1e-9)
    for i, (_, odom) in enumerate(out):  # the car's pose against its first, REP 103 axes
        np.testing.assert_allclose(odom.odom_from_base, np.linalg.inv(gt[0]) @ gt[i], atol=1e-8)
    # the camera's own path (a mount at the base's origin) turns about another point: the car
    # turned 0.38 rad with the camera 1.5 m ahead of it
    _, camera = _odometry(parse_camera_mount(DEFAULT_CAMERA_MOUNT), windows())
    assert np.linalg.norm(camera[-1][1].odom_from_base[:3, 3]
                          - out[-1][1].odom_from_base[:3, 3]) > 0.3


@pytest.mark.parametrize("pitch_deg, roll_deg", [(8.0, 3.0), (-5.0, 0.0)])
def test_odom_is_gravity_aligned_where_the_window_measured_the_ground(pitch_deg, roll_deg):
    """The mount says level (the default), the camera is pitched and rolled on the car: the
    first base pose is tilted, yet odom's z is the ground's up when the window measured it, and
    off by the tilt when it did not (the first base pose's axes)."""
    mount = parse_camera_mount(DEFAULT_CAMERA_MOUNT)
    tilted = np.eye(4)  # the camera pitched down and rolled on the car, in the car's axes
    tilted[:3, :3] = _rot(1, math.radians(pitch_deg)) @ _rot(0, math.radians(roll_deg))
    gt = _cameras(_car_drive(20), tilted @ mount)
    R, t, s = _rot(1, 0.7) @ _rot(0, -0.4), np.array([1.0, 2.0, 3.0]), 0.5
    tilt = math.radians(math.hypot(pitch_deg, roll_deg))
    for ground in (True, False):
        window = _window(gt, range(0, 20), s, R, t, "fresh", metres=1 / s)
        window.ground_up = R @ UP if ground else None  # the plane's up in the SfM world
        _, out = _odometry(mount, [window])
        for i, (_, odom) in enumerate(out):
            up_in_base = mount[:3, :3] @ gt[i][:3, :3].T @ UP  # the truth, in the base's axes
            up_in_odom = odom.odom_from_base[:3, :3] @ up_in_base
            angle = math.acos(np.clip(up_in_odom[2], -1.0, 1.0))
            if ground:
                assert angle < math.radians(0.01), (i, math.degrees(angle))
            else:
                assert angle == pytest.approx(tilt, abs=math.radians(0.5))
        first = out[0][1].odom_from_base
        assert abs(first[1, 0]) < 1e-9  # x: the first heading (on the plane)
        np.testing.assert_allclose(first[:3, 3], 0.0, atol=1e-12)


def _steps(out) -> np.ndarray:
    T = [o.odom_from_base for _, o in out]
    return np.array([np.linalg.norm(b[:3, 3] - a[:3, 3])
                     for a, b in zip(T[:-1], T[1:], strict=True)])


def test_a_fresh_map_that_fits_the_path_badly_does_not_step_the_odometry():
    """The second map's metres are 6 % off: fitted to the path through the shared frames with
    that scale, its first new frame lands ~0.2 m off the path's end. The path steps; ~/odom's
    base moves as the window says (1 m per frame, 10 m/s), the step absorbed into odom."""
    mount = parse_camera_mount(DEFAULT_CAMERA_MOUNT)
    cam = _cameras(_car_drive(25), mount)
    R2, t2 = _rot(1, 2.0) @ _rot(0, -0.4), np.array([-5.0, 1.0, 0.5])
    path, out = _odometry(mount, [
        _window(cam, range(0, 10), 1.0, np.eye(3), np.zeros(3), "fresh", metres=1.0),
        _window(cam, range(5, 25), 0.3, R2, t2, "fresh", metres=1.06 / 0.3)])
    poses = [p for p, _ in out]
    assert poses[10].chain == "shared" and poses[10].jump is not None
    raw = np.linalg.norm(poses[10].position - poses[9].position)
    assert abs(raw - 1.0) > 0.1  # the path itself steps where the second map joins
    speed = 1.0 / DT
    assert (_steps(out) <= speed * DT + 0.07).all(), _steps(out)  # 6 % of 1 m, plus slack
    assert (_steps(out) >= 1.0 - 0.07).all()
    cov = np.array([np.diag(o.covariance) for _, o in out])
    assert cov[10, 0] - cov[9, 0] >= 0.01  # the absorbed step, squared, is uncertainty


def test_a_break_continues_on_the_last_velocity_and_inflates_the_covariance():
    mount = parse_camera_mount(DEFAULT_CAMERA_MOUNT)
    cam = _cameras(_car_drive(25), mount)
    path, out = _odometry(mount, [
        _window(cam, range(0, 10), 1.0, np.eye(3), np.zeros(3), "fresh", metres=1.0),
        _window(cam, range(13, 20), 0.5, _rot(0, 1.0), np.zeros(3), "fresh", metres=2.0)])
    assert path.breaks == 1 and out[10][0].chain == "break"
    dts = np.diff([o.stamp for _, o in out])
    assert (_steps(out) <= (1.0 / DT) * dts + 0.05).all()
    var = [o.covariance[0, 0] for _, o in out]
    assert var[10] > var[9] + 9.0 - 1e-6  # the guessed 4 m, squared (core/camera_path.py)


def test_the_twist_is_the_bases_finite_difference_and_unknown_without_a_previous_pose():
    mount = parse_camera_mount("0.8 0 1.4 -90 0 -90")
    cam = _cameras(_car_drive(12), mount)
    _, out = _odometry(mount, [_window(cam, range(0, 12), 1.0, np.eye(3), np.zeros(3),
                                       metres=1.0)])
    first = out[0][1]
    assert not first.twist_known and first.twist_covariance[0, 0] == -1.0
    assert not first.twist.any() and not first.twist_covariance.ravel()[1:].any()
    for (_, a), (_, b) in zip(out[:-1], out[1:], strict=True):
        assert b.twist_known
        dt = b.stamp - a.stamp
        # finite differences: the displacement in the base's frame; the small rotation's
        # skew part (R_aᵀ R_b ≈ I + [ω dt]×)
        v = a.odom_from_base[:3, :3].T @ (b.odom_from_base[:3, 3] - a.odom_from_base[:3, 3])
        D = a.odom_from_base[:3, :3].T @ b.odom_from_base[:3, :3]
        w = np.array([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]]) / 2
        np.testing.assert_allclose(b.twist[:3], v / dt, atol=1e-9)
        np.testing.assert_allclose(b.twist[3:], w / dt, rtol=1e-3, atol=1e-9)
        # a car at 10 m/s turning at 0.2 rad/s about its z: forward, level, yawing left
        assert b.twist[0] == pytest.approx(10.0, rel=1e-3)
        np.testing.assert_allclose(b.twist[[1, 2, 3, 4]], 0.0, atol=1e-9)
        assert b.twist[5] == pytest.approx(0.2, rel=1e-6)
        assert (np.linalg.eigvalsh(b.twist_covariance) > 0).all()
    np.testing.assert_allclose(rotation_vector(_rot(1, math.pi)), [0.0, math.pi, 0.0],
                               atol=1e-9)


def test_the_pose_covariance_is_positive_definite_and_grows_with_the_distance():
    mount = parse_camera_mount(DEFAULT_CAMERA_MOUNT)
    cam = _cameras(_car_drive(30), mount)
    _, out = _odometry(mount, [
        _window(cam, range(0, 15), 1.0, np.eye(3), np.zeros(3), "fresh", metres=1.0, var=0.0),
        _window(cam, range(10, 30), 1.0, np.eye(3), np.zeros(3), "continued", var=0.0)])
    position = []
    for i, (_, o) in enumerate(out):
        assert (np.linalg.eigvalsh(o.covariance) > 0).all()
        travelled = np.linalg.norm(
            o.odom_from_base[:3, 3] - out[0][1].odom_from_base[:3, 3]) if i else 0.0
        assert o.covariance[0, 0] >= (DRIFT_PER_DISTANCE * travelled) ** 2
        position.append(o.covariance[0, 0])
    assert (np.diff(position) > 0).all()
    assert math.sqrt(position[-1]) == pytest.approx(DRIFT_PER_DISTANCE * 29.0, rel=0.01)
