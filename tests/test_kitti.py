"""KITTI raw / depth-GT layouts: the real calibration file, write -> read round trips, bad input."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

import cv2
import numpy as np
import pytest

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.data.kitti import (
    KittiDrive,
    format_kitti_timestamp,
    kitti_intrinsics,
    lidar_like_mask,
    parse_drive_name,
    parse_kitti_timestamp,
    read_calib_cam_to_cam,
    read_depth_png,
    read_timestamps,
    write_calib_cam_to_cam,
    write_depth_png,
    write_kitti_drive,
)
from sfm_ttr_ros.data.synthetic import SyntheticSequence, make_sequence

REAL_CALIB = (
    Path(__file__).resolve().parents[2]
    / "shared"
    / "data"
    / "kitti_calib_2011_09_26"
    / "calib_cam_to_cam.txt"
)
needs_real_calib = pytest.mark.skipif(
    not REAL_CALIB.is_file(), reason=f"real KITTI calibration not available at {REAL_CALIB}"
)
N_FRAMES = 13  # with 5 skipped at each end, frames 5..7 have ground truth


@pytest.fixture(scope="module")
def seq() -> SyntheticSequence:
    return make_sequence(seed=0, domain="A", num_frames=N_FRAMES, width=160, height=48)


@pytest.fixture()
def written(seq, tmp_path):
    raw, gt = tmp_path / "raw", tmp_path / "gt"
    name = write_kitti_drive(seq, raw, gt, drive_number=7)
    return raw, gt, name


@needs_real_calib
def test_real_calibration_file():
    calib = read_calib_cam_to_cam(REAL_CALIB)
    assert calib["calib_time"] == "09-Jan-2012 13:57:47"
    assert calib["P_rect_02"].shape == (12,)
    intr = kitti_intrinsics(calib, "02")
    assert intr.fx == pytest.approx(721.5377)
    assert intr.fy == pytest.approx(721.5377)
    assert intr.cx == pytest.approx(609.5593)
    assert intr.cy == pytest.approx(172.854)
    assert (intr.width, intr.height) == (1242, 375)
    assert calib["P_rect_02"][3] == pytest.approx(44.85728)  # stereo offset column kept
    assert kitti_intrinsics(calib, "00").fx == pytest.approx(721.5377)


@needs_real_calib
def test_written_calibration_has_the_real_fields(tmp_path):
    real = read_calib_cam_to_cam(REAL_CALIB)
    intr = Intrinsics(700.123456789, 701.5, 600.25, 180.125, 1200, 360)
    path = tmp_path / "calib_cam_to_cam.txt"
    write_calib_cam_to_cam(path, intr)
    ours = read_calib_cam_to_cam(path)
    assert list(ours) == list(real)  # same keys, same order
    for key, value in real.items():
        if isinstance(value, np.ndarray):
            assert ours[key].shape == value.shape, key
        else:
            assert isinstance(ours[key], str)
    assert kitti_intrinsics(ours, "02") == intr  # lossless
    P1 = ours["P_rect_01"].reshape(3, 4)
    assert P1[0, 3] / P1[0, 0] == pytest.approx(-0.5372)  # stereo baseline like the real rig
    # lines look like the real file's ("key: 7.215377e+02 ...")
    first = path.read_text().splitlines()[2]
    assert first.startswith("S_00: 1.200000e+03 3.600000e+02")


def test_roundtrip_images_stamps_gt_intrinsics(seq, written):
    raw, gt, name = written
    assert name == "2011_09_26_drive_0007_sync"
    drive_dir = raw / "2011_09_26" / name
    assert (drive_dir / "image_02" / "data" / "0000000000.png").is_file()
    assert (raw / "2011_09_26" / "calib_cam_to_cam.txt").is_file()
    lines = (drive_dir / "image_02" / "timestamps.txt").read_text().splitlines()
    assert len(lines) == N_FRAMES and lines[0].startswith("2011-09-26 13:02:25.9643")

    drive = KittiDrive(raw, name, gt_root=gt)
    assert drive.date == "2011_09_26"
    assert len(drive) == N_FRAMES
    assert drive.frame_names == [f"{i:010d}" for i in range(N_FRAMES)]
    assert drive.intrinsics == seq.intrinsics
    assert drive.stamps_from_file
    np.testing.assert_allclose(drive.stamps, seq.stamps, rtol=0, atol=1e-6)
    assert drive.gt_dir == gt / "val" / name / "proj_depth" / "groundtruth" / "image_02"
    for i in range(N_FRAMES):
        np.testing.assert_array_equal(drive.load_image(i), seq.images[i])
        gt_i = drive.load_gt(i)
        if i < 5 or i >= N_FRAMES - 5:
            assert drive.gt_path(i) is None and gt_i is None
            continue
        assert drive.gt_path(i).name == f"{i:010d}.png"
        assert gt_i.dtype == np.float32 and gt_i.shape == seq.depths[i].shape
        want = np.round(seq.depths[i].astype(np.float64) * 256) / 256
        np.testing.assert_allclose(gt_i, want, rtol=0, atol=1e-6)
        assert (gt_i[seq.depths[i] == 0] == 0).all()
        assert (gt_i > 0).mean() > 0.8  # dense
    raw_png = cv2.imread(str(drive.gt_path(5)), cv2.IMREAD_UNCHANGED)
    assert raw_png.dtype == np.uint16

    frames = drive.frames([5, 6])
    assert [f.name for f in frames] == ["0000000005", "0000000006"]
    assert all(isinstance(f, Frame) for f in frames)
    assert frames[1].stamp == drive.stamps[6] and frames[0].index == 5
    np.testing.assert_array_equal(frames[0].image, seq.images[5])
    assert len(drive.frames()) == N_FRAMES


def test_sparse_lidar_like_gt(seq, tmp_path):
    name = write_kitti_drive(
        seq, tmp_path / "raw", tmp_path / "gt", gt_density=0.05, gt_split="train"
    )
    drive = KittiDrive(tmp_path / "raw", name, gt_root=tmp_path / "gt")
    assert drive.gt_dir.parts[-5] == "train"
    gt = drive.load_gt(6)
    h = gt.shape[0]
    assert 0.03 < (gt > 0).mean() < 0.07
    assert (gt[: int(0.3 * h)] == 0).all()  # nothing in the top of the image
    nz = gt > 0
    np.testing.assert_allclose(gt[nz], np.round(seq.depths[6][nz] * 256) / 256, atol=1e-6)
    # explicit split lookup, and a split with no ground truth
    assert KittiDrive(tmp_path / "raw", name, tmp_path / "gt", split="train").gt_dir is not None
    with pytest.raises(InputError, match="no ground truth"):
        KittiDrive(tmp_path / "raw", name, tmp_path / "gt", split="val")


def test_lidar_like_mask_density():
    rng = np.random.default_rng(0)
    m = lidar_like_mask(375, 1242, 0.05, rng)
    assert 0.045 < m.mean() < 0.055 and not m[:112].any()
    assert len(np.unique(np.nonzero(m)[0])) < 375 // 4  # scan lines, not every row
    assert lidar_like_mask(40, 50, 1.0, rng)[12:].all()
    with pytest.raises(InputError):
        lidar_like_mask(10, 10, 0.0, rng)


def test_timestamps_nanoseconds():
    s = "2011-09-26 13:02:25.964389445"
    want = datetime(2011, 9, 26, 13, 2, 25, tzinfo=UTC).timestamp() + 0.964389445
    assert parse_kitti_timestamp(s) == pytest.approx(want, abs=1e-6)
    assert parse_kitti_timestamp("2011-09-26 13:02:25") == pytest.approx(want - 0.964389445)
    assert format_kitti_timestamp(parse_kitti_timestamp(s))[:26] == s[:26]
    assert format_kitti_timestamp(1.0) == "1970-01-01 00:00:01.000000000"
    assert format_kitti_timestamp(1.9999999999) == "1970-01-01 00:00:02.000000000"
    for t in (1317042145.964389, 1317042146.064389, 0.5):
        assert parse_kitti_timestamp(format_kitti_timestamp(t)) == pytest.approx(t, abs=1e-6)
    with pytest.raises(InputError, match="timestamp"):
        parse_kitti_timestamp("26/09/2011 13:02")


def test_depth_png_helpers(tmp_path):
    d = np.array([[0.0, 1.0, 2.5004], [65.535, 65.6, -1.0], [np.nan, np.inf, 0.0004]])
    write_depth_png(tmp_path / "holo.png", d, scale=1000.0)
    got = read_depth_png(tmp_path / "holo.png", scale=1000.0)
    np.testing.assert_allclose(got, [[0, 1, 2.5], [65.535, 0, 0], [0, 0, 0]], atol=1e-6)
    write_depth_png(tmp_path / "kitti.png", np.array([[80.0, 255.99, 300.0]]))
    np.testing.assert_allclose(read_depth_png(tmp_path / "kitti.png"), [[80, 256 - 3 / 256, 0]])
    cv2.imwrite(str(tmp_path / "rgb.png"), np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(InputError, match="single-channel"):
        read_depth_png(tmp_path / "rgb.png")
    with pytest.raises(InputError, match="not found"):
        read_depth_png(tmp_path / "nope.png")


def test_missing_and_bad_inputs(seq, written, tmp_path):
    raw, gt, name = written
    missing = "2011_09_26_drive_0099_sync"
    with pytest.raises(InputError) as err:
        KittiDrive(raw, missing)
    assert str(raw / "2011_09_26" / missing) in str(err.value)
    with pytest.raises(InputError, match="ground-truth root"):
        KittiDrive(raw, name, gt_root=tmp_path / "no_gt")
    with pytest.raises(InputError, match="drive name"):
        KittiDrive(raw, "short")
    with pytest.raises(InputError, match="out of range"):
        KittiDrive(raw, name).load_image(N_FRAMES)
    # writing the same drive again needs overwrite=True
    with pytest.raises(InputError, match="already holds images"):
        write_kitti_drive(seq, raw, gt, drive_number=7)
    write_kitti_drive(seq, raw, gt, drive_number=7, overwrite=True)
    # another drive of the same date with other intrinsics conflicts with the shared calibration
    other = make_sequence(seed=0, domain="B", num_frames=1, width=160, height=48)
    with pytest.raises(InputError, match="calib_cam_to_cam"):
        write_kitti_drive(other, raw, drive_number=8)

    calib = raw / "2011_09_26" / "calib_cam_to_cam.txt"
    text = calib.read_text()
    calib.write_text(text.replace("P_rect_02: ", "P_rect_02: 1 2 3 #"))
    with pytest.raises(InputError, match="P_rect_02"):
        KittiDrive(raw, name)
    calib.write_text("this line has no colon\n")
    with pytest.raises(InputError, match="key: values"):
        KittiDrive(raw, name)
    calib.unlink()
    with pytest.raises(InputError, match="calib_cam_to_cam.txt"):
        KittiDrive(raw, name)
    calib.write_text(text)

    # timestamps: too few lines is an error; no file means 10 Hz from the frame numbers
    ts = raw / "2011_09_26" / name / "image_02" / "timestamps.txt"
    lines = ts.read_text().splitlines()
    ts.write_text("\n".join(lines[:3]) + "\n")
    with pytest.raises(InputError, match="no timestamp for frame"):
        KittiDrive(raw, name)
    ts.unlink()
    drive = KittiDrive(raw, name)
    assert not drive.stamps_from_file
    np.testing.assert_allclose(drive.stamps, np.arange(N_FRAMES) * 0.1)
    with pytest.raises(InputError, match="not found"):
        read_timestamps(ts)


def test_drive_name_parsing():
    assert parse_drive_name("2011_09_26_drive_0001_sync") == ("2011_09_26", 1)
    with pytest.raises(InputError):
        parse_drive_name("2011_09_26_drive_1_sync")


def test_a_generated_drive_carries_its_camera_poses_and_height(seq, written, capsys):
    from sfm_ttr_ros.data.poses import read_camera_height, read_poses

    raw, _, name = written
    drive_dir = raw / "2011_09_26" / name
    poses = read_poses(drive_dir / "poses.txt")
    assert poses.shape == (N_FRAMES, 4, 4)
    for T, cam_from_world in zip(poses, seq.cam_from_world, strict=True):
        np.testing.assert_allclose(T @ cam_from_world, np.eye(4), atol=1e-9)
    # the camera drives ~speed metres a frame at camera_height above the road (y down)
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    np.testing.assert_allclose(steps, seq.params.speed, rtol=0.01)
    assert read_camera_height(drive_dir / "camera_height.txt") == pytest.approx(
        seq.params.camera_height, abs=1e-6)
    np.testing.assert_allclose(-poses[:, 1, 3], seq.params.camera_height, atol=0.011)
    # the same through the CLI, which says where it wrote them
    from sfm_ttr_ros.tools.cli import main

    assert main(["generate", "--kitti-raw", str(raw / "cli"), "--frames", "2", "--width", "64",
                 "--height", "32", "--seed", "3"]) == 0
    out = capsys.readouterr().out
    cli_dir = raw / "cli" / "2011_09_26" / "2011_09_26_drive_0001_sync"
    height = read_camera_height(cli_dir / "camera_height.txt")
    assert f"camera height above the road: {height:.3f} m" in out and "poses.txt" in out
    assert read_poses(cli_dir / "poses.txt").shape == (2, 4, 4)


def test_poses_and_oxts_files_are_checked(tmp_path):
    from sfm_ttr_ros.data.poses import (
        drive_oxts_poses,
        oxts_poses,
        read_camera_height,
        read_poses,
        write_camera_height,
    )

    bad = tmp_path / "poses.txt"
    bad.write_text("1 2 3\n")
    with pytest.raises(InputError, match="16 numbers"):
        read_poses(bad)
    bad.write_text("1 0 0 0 0 1 0 0 0 0 1 0 0 0 1 1\n")
    with pytest.raises(InputError, match="row 1 is not a rigid 4x4 pose"):
        read_poses(bad)
    with pytest.raises(InputError, match="> 0 m"):
        write_camera_height(tmp_path / "h.txt", -1.0)
    (tmp_path / "h.txt").write_text("tall\n")
    with pytest.raises(InputError, match="camera height"):
        read_camera_height(tmp_path / "h.txt")
    # OXTS as the KITTI devkit converts it: 10 m east then 10 m north at 49 deg latitude
    er, lat0 = 6378137.0, 49.0
    dlon = np.degrees(10.0 / (er * np.cos(np.radians(lat0))))
    packets = [[lat0, 8.4, 110.0, 0, 0, 0.3], [lat0, 8.4 + dlon, 110.0, 0, 0, 0.3],
               [lat0 + np.degrees(10.0 / er), 8.4 + dlon, 111.0, 0, 0, 0.3]]
    poses = oxts_poses([np.array(p) for p in packets])
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-9)
    for T in poses:  # the same heading throughout: no rotation relative to the first
        np.testing.assert_allclose(T[:3, :3], np.eye(3), atol=1e-9)
    moves = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    np.testing.assert_allclose(moves, [10.0, np.hypot(10.0, 1.0)], rtol=1e-4)
    # in the first IMU frame (x forward = the heading yaw 0.3 from east): east is -0.3 rad away
    np.testing.assert_allclose(poses[1][:2, 3], 10.0 * np.array([np.cos(0.3), -np.sin(0.3)]),
                               rtol=1e-4)
    drive = tmp_path / "drive"
    assert drive_oxts_poses(drive, ["0000000000"]) is None  # no oxts/: no odometry
    (drive / "oxts" / "data").mkdir(parents=True)
    for i, p in enumerate(packets):
        (drive / "oxts" / "data" / f"{i:010d}.txt").write_text(" ".join(map(str, p + [0] * 24)))
    with pytest.raises(InputError, match="0 timestamps for 3 OXTS packets"):
        drive_oxts_poses(drive, [f"{i:010d}" for i in range(3)])
    (drive / "oxts" / "timestamps.txt").write_text("2011-09-26 13:02:25.964389445\n" * 3)
    np.testing.assert_allclose(drive_oxts_poses(drive, [f"{i:010d}" for i in range(3)]), poses)
    with pytest.raises(InputError, match="no OXTS packet for frame 0000000009"):
        drive_oxts_poses(drive, ["0000000009"])
