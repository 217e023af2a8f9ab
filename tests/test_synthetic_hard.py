"""Synthetic hard drives: segments of turning on the spot, a standing camera, cars
crossing, a vehicle ahead moving with the camera, an exposure change, turning while creeping,
creeping straight and a truck ahead, between ordinary driving; exact depth of the moving
objects; labels; ``sfm-ttr generate --scenario hard``."""

from __future__ import annotations

import math
import types

import cv2
import numpy as np
import pytest

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Intrinsics
from sfm_ttr_ros.data.kitti import (
    SEGMENTS_FILE,
    KittiDrive,
    read_segments,
    write_kitti_drive,
    write_segments,
)
from sfm_ttr_ros.data.synthetic import (
    DEFAULT_HARD_SEGMENTS,
    Segment,
    as_segments,
    camera_pose,
    make_sequence,
    plan_drive,
    render_frames,
    render_hard_drive,
    sample_scene_params,
)
from sfm_ttr_ros.data.synthetic.geometry import _Builder, _car_shape
from sfm_ttr_ros.data.synthetic.scenario import (
    CREEP_STEP,
    EXPOSURE_FACTORS,
    TRUCK_DISTANCE,
    TRUCK_SIZE,
    TURN_AMPLITUDE_DEG,
    TURN_STEP,
)
from sfm_ttr_ros.tools.cli import main as cli_main

W, H = 240, 72
SEGS = [("drive", 3), ("rotate", 7), ("static", 4), ("drive", 2), ("crossing", 8), ("lead", 6),
        ("exposure", 6, 0.45), ("drive", 2)]
# the low-parallax and large-vehicle kinds, in their own drive (SEGS keeps its frames)
NEW_SEGS = [("drive", 3), ("turn", 11), ("drive", 1), ("creep", 4), ("truck", 5), ("drive", 2)]
DRIVE = "2011_09_26_drive_0001_sync"


@pytest.fixture(scope="module")
def drive():
    params = sample_scene_params(0, "A")
    return render_hard_drive(params, SEGS, W, H), plan_drive(params, SEGS)


@pytest.fixture(scope="module")
def new_drive():
    params = sample_scene_params(0, "A")
    return render_hard_drive(params, NEW_SEGS, W, H), plan_drive(params, NEW_SEGS)


def frames_of(labels: list[str], kind: str, nth: int = 0) -> list[int]:
    """Frame indices of the ``nth`` segment of ``kind``."""
    runs, prev = [], None
    for i, lab in enumerate(labels):
        if lab != prev:
            runs.append((lab, []))
        runs[-1][1].append(i)
        prev = lab
    return [r for lab, r in runs if lab == kind][nth]


def centre(T: np.ndarray) -> np.ndarray:
    return -T[:3, :3].T @ T[:3, 3]


def heading_deg(T: np.ndarray) -> float:
    fwd = T[2, :3]  # camera z axis in world coordinates
    return math.degrees(math.atan2(fwd[0], fwd[2]))


def project(seq, i: int, P) -> tuple[float, float, float]:
    """World point -> (u, v, depth) in frame i."""
    X = seq.cam_from_world[i] @ np.append(np.asarray(P, float), 1.0)
    q = seq.intrinsics.K @ X[:3]
    return q[0] / q[2], q[1] / q[2], X[2]


def depth_at(seq, i: int, u: float, v: float) -> float:
    return float(seq.depths[i][int(round(v)), int(round(u))])


def inside(seq, u: float, v: float) -> bool:
    return 0 <= round(u) < seq.intrinsics.width and 0 <= round(v) < seq.intrinsics.height


def test_labels_align_with_frames(drive):
    seq, plan = drive
    want = [s[0] for s in SEGS for _ in range(s[1])]
    assert seq.labels == plan.labels == want
    assert len(seq) == len(seq.depths) == len(seq.cam_from_world) == len(seq.stamps) == len(want)
    np.testing.assert_allclose(np.diff(seq.stamps), 0.1, atol=1e-6)
    # a plain street drive carries no labels
    assert make_sequence(0, "A", 1, 16, 8).labels == []


def test_path_is_continuous(drive):
    seq, _ = drive
    speed = seq.params.speed
    C = np.array([centre(T) for T in seq.cam_from_world])
    steps = np.linalg.norm(np.diff(C, axis=0), axis=1)
    assert steps.max() <= speed * 1.01  # no jump between segments
    turn = np.abs(np.diff([heading_deg(T) for T in seq.cam_from_world]))
    assert turn.max() <= 4 * 20 / (7 + 1) + 0.5  # the rotate segment's step, path wobble
    # the drive advances in moving segments only (half speed while cars cross)
    for kind, per_frame in (("drive", 1.0), ("crossing", 0.5), ("lead", 1.0), ("exposure", 1.0)):
        idx = frames_of(seq.labels, kind)
        np.testing.assert_allclose(np.diff(C[idx, 2]), speed * per_frame, rtol=1e-9)


def test_rotate_segment_turns_on_the_spot(drive):
    seq, _ = drive
    idx = frames_of(seq.labels, "rotate")
    before, after = idx[0] - 1, idx[-1] + 1
    for i in idx:  # the centre stays where the last drive frame was
        np.testing.assert_allclose(centre(seq.cam_from_world[i]),
                                   centre(seq.cam_from_world[before]), atol=1e-9)
    yaw = np.array([heading_deg(seq.cam_from_world[i]) for i in idx])
    yaw0 = heading_deg(seq.cam_from_world[before])
    assert np.abs(np.diff(np.r_[yaw0, yaw])).min() > 2.0  # every frame turns
    assert 15.0 < (yaw - yaw0).max() <= 20.01 and -20.01 <= (yaw - yaw0).min() < -15.0
    # and the drive goes on with the heading the rotation started from
    assert abs(heading_deg(seq.cam_from_world[after]) - yaw0) < 1.0
    for i in idx:  # every frame's view differs from the one before
        assert not np.array_equal(seq.images[i], seq.images[i - 1])


def test_static_segment_stands_still(drive):
    seq, _ = drive
    idx = frames_of(seq.labels, "static")
    for i in idx:  # identical poses, images and depths
        np.testing.assert_array_equal(seq.cam_from_world[i], seq.cam_from_world[idx[0]])
        np.testing.assert_allclose(centre(seq.cam_from_world[i]),  # where the last frame was
                                   centre(seq.cam_from_world[idx[0] - 1]), atol=1e-9)
        np.testing.assert_array_equal(seq.images[i], seq.images[idx[0]])
        np.testing.assert_array_equal(seq.depths[i], seq.depths[idx[0]])
    # with pixel noise the images differ, the poses do not
    # after a drive: the drive's last pose; with pixel noise the images differ, the poses do not
    noisy = render_hard_drive(seq.params, [("drive", 2), ("static", 3)], 160, 48, seed=1,
                              noise_std=3.0)
    for i in (2, 3, 4):
        np.testing.assert_array_equal(noisy.cam_from_world[i], noisy.cam_from_world[1])
    assert not np.array_equal(noisy.images[2], noisy.images[3])


def test_crossing_cars_move_across_the_image_with_exact_depth(drive):
    seq, plan = drive
    idx = frames_of(seq.labels, "crossing")
    hw = seq.params.street_width / 2
    assert all(len(plan.vehicles[i]) == 2 for i in idx)
    assert all(not plan.vehicles[i] for i in frames_of(seq.labels, "drive"))
    xs = np.array([[v.centre[0] for v in plan.vehicles[i]] for i in idx])
    vx = np.diff(xs, axis=0) * 10.0  # m/s
    assert np.all(np.abs(vx) >= 3.0 - 1e-9) and np.all(np.abs(vx) <= 6.0 + 1e-9)
    assert np.all(np.sign(vx[:, 0]) == -np.sign(vx[:, 1]))  # opposite directions
    checked, us = 0, []
    first = plan.vehicles[idx[0]][0]
    for i in idx:
        car = plan.vehicles[i][0]  # the nearer one
        # its texture moves with it
        assert car.anchor[0] - first.anchor[0] == pytest.approx(car.x0 - first.x0, abs=1e-9)
        x, _ = car.centre
        y = (car.shape[0] + -0.3) / 2  # middle of the body
        u, v, z = project(seq, i, (x, y, car.z0))  # middle of its near side
        assert 8.0 < z < 32.0
        us.append(u)
        # away from the parked cars: nothing between the camera and the car
        if inside(seq, u, v) and abs(x) < hw - 2.4:
            assert depth_at(seq, i, u, v) == pytest.approx(z, rel=0.03)
            checked += 1
    assert checked >= 3
    du = np.diff(us)
    assert np.all(np.sign(du) == np.sign(vx[0, 0])) and abs(us[-1] - us[0]) > 10


def test_lead_vehicle_keeps_its_depth_while_the_scene_flows(drive):
    seq, plan = drive
    idx = frames_of(seq.labels, "lead")
    K = seq.intrinsics.K
    depths = []
    for i in idx:
        (car,) = plan.vehicles[i]
        x, _ = car.centre
        y = (car.shape[0] + -0.3) / 2 * car.height
        u, v, z = project(seq, i, (x, y, car.z0))  # middle of its back
        assert inside(seq, u, v) and 9.0 <= z <= 13.2
        assert depth_at(seq, i, u, v) == pytest.approx(z, rel=0.01)
        depths.append(depth_at(seq, i, u, v))
    assert np.ptp(depths) / np.mean(depths) < 0.02  # constant depth ...
    car_z = [plan.vehicles[i][0].z0 for i in idx]  # ... because it drives with the camera
    np.testing.assert_allclose(np.diff(car_z), seq.params.speed, rtol=1e-9)
    # the static-world reprojection with exact poses and depth holds for the scene around it and
    # fails on the lead vehicle by about speed / distance (the trap for SfM)
    i, j = idx[1], idx[2]
    d = seq.depths[i]
    vv, uu = np.nonzero(d > 0)
    rays = np.linalg.inv(K) @ np.vstack([uu, vv, np.ones(uu.size)])
    Tji = seq.cam_from_world[j] @ np.linalg.inv(seq.cam_from_world[i])
    Y = Tji[:3, :3] @ (rays * d[vv, uu]) + Tji[:3, 3:]
    q = K @ Y
    qu, qv = np.round(q[0] / q[2]).astype(int), np.round(q[1] / q[2]).astype(int)
    ok = (qu >= 0) & (qu < W) & (qv >= 0) & (qv < H) & (Y[2] > 0)
    got = seq.depths[j][qv[ok], qu[ok]]
    rel = np.abs(got - Y[2][ok]) / Y[2][ok]
    (car,) = plan.vehicles[i]
    corners = [project(seq, i, (cx, cy * car.height, car.z0)) for cx in (car.x0, car.x1)
               for cy in (car.shape[0], -0.3)]  # its body's back
    u0, u1 = min(c[0] for c in corners), max(c[0] for c in corners)
    v0, v1 = min(c[1] for c in corners), max(c[1] for c in corners)
    on_car = (uu[ok] > u0 + 2) & (uu[ok] < u1 - 2) & (vv[ok] > v0 + 1) & (vv[ok] < v1 - 1)
    near_car = (uu[ok] > u0 - 3) & (uu[ok] < u1 + 3)
    assert on_car.sum() >= 10
    assert np.median(rel[~near_car]) < 0.01
    assert np.median(rel[on_car]) > 0.6 * seq.params.speed / np.mean(depths)


def path_heading_deg(params, z: float) -> float:
    """The camera path's heading at path position z (no turn applied)."""
    R_wc, _ = camera_pose(params, z)
    return math.degrees(math.atan2(R_wc[0, 2], R_wc[2, 2]))


def test_turn_sweeps_the_yaw_while_creeping_forward(new_drive):
    seq, _ = new_drive
    speed = seq.params.speed
    idx = frames_of(seq.labels, "turn")
    C = np.array([centre(seq.cam_from_world[i]) for i in [idx[0] - 1, *idx]])
    # a small, nonzero forward step every frame (the path's z), the camera on the path
    np.testing.assert_allclose(np.diff(C[:, 2]), speed * TURN_STEP, rtol=1e-9)
    assert 0 < speed * TURN_STEP < 0.25 * speed
    for c in C[1:]:
        np.testing.assert_allclose(c, camera_pose(seq.params, c[2])[1], atol=1e-9)
    # the yaw sweeps 0 -> +A -> -A -> 0 about the path's heading, every frame turning
    yaw = np.array([heading_deg(seq.cam_from_world[i]) - path_heading_deg(seq.params, c[2])
                    for i, c in zip(idx, C[1:], strict=True)])
    amp = TURN_AMPLITUDE_DEG
    assert 0.8 * amp < yaw.max() <= amp + 0.01 and -amp - 0.01 <= yaw.min() < -0.8 * amp
    assert np.abs(np.diff(np.r_[0.0, yaw, 0.0])).min() > 0.5 * 4 * amp / (len(idx) + 1)
    assert yaw.argmax() < yaw.argmin()  # +A first, then -A
    after = idx[-1] + 1  # the drive goes on with the path's heading
    assert abs(heading_deg(seq.cam_from_world[after])
               - path_heading_deg(seq.params, centre(seq.cam_from_world[after])[2])) < 1e-6


def test_creep_moves_a_few_centimetres_a_frame(new_drive):
    seq, _ = new_drive
    speed = seq.params.speed
    idx = frames_of(seq.labels, "creep")
    C = np.array([centre(seq.cam_from_world[i]) for i in [idx[0] - 1, *idx]])
    np.testing.assert_allclose(np.diff(C[:, 2]), speed * CREEP_STEP, rtol=1e-9)
    steps = np.linalg.norm(np.diff(C, axis=0), axis=1)
    assert np.all(steps > 0.005) and np.all(steps < 0.1)  # a few cm, never standing
    for i, c in zip(idx, C[1:], strict=True):  # straight on the path, with its heading
        np.testing.assert_allclose(seq.cam_from_world[i][:3, :3],
                                   camera_pose(seq.params, c[2])[0].T, atol=1e-12)
    for i in idx:  # and the view changes, a little
        assert not np.array_equal(seq.images[i], seq.images[i - 1])


def test_truck_covers_a_large_share_at_constant_depth(new_drive):
    seq, plan = new_drive
    idx = frames_of(seq.labels, "truck")
    (w_lo, w_hi), (h_lo, h_hi), _ = TRUCK_SIZE
    bare = render_frames(seq.params, [plan.poses[i] for i in idx], W, H)  # without the truck
    depths, shares = [], []
    for k, i in enumerate(idx):
        (truck,) = plan.vehicles[i]
        assert truck.body == "truck" and w_lo <= truck.x1 - truck.x0 <= w_hi
        assert h_lo <= truck.height <= h_hi and max(truck.colour) > 0.3  # tall, not black
        x, _ = truck.centre
        u, v, z = project(seq, i, (x, -truck.height / 2, truck.z0))  # middle of its back
        assert inside(seq, u, v) and TRUCK_DISTANCE[0] - 0.1 <= z <= TRUCK_DISTANCE[1] + 0.1
        assert depth_at(seq, i, u, v) == pytest.approx(z, rel=0.01)
        depths.append(depth_at(seq, i, u, v))
        # its pixels: nearer than the street without it
        on_truck = np.abs(seq.depths[i] - bare.depths[k]) > 0.05
        shares.append(on_truck.mean())
        assert np.abs(seq.depths[i][on_truck] - z).max() < 0.2 * z  # the flat back and chassis
    assert min(shares) > 0.12  # a big share of the image
    assert np.ptp(depths) / np.mean(depths) < 0.02  # constant depth: it drives with the camera
    np.testing.assert_allclose(np.diff([plan.vehicles[i][0].z0 for i in idx]),
                               seq.params.speed, rtol=1e-9)
    assert all(not plan.vehicles[i] for i in frames_of(seq.labels, "creep"))


def test_moving_vehicle_carries_its_texture():
    """A car and the camera both moved by 1.3 m along x: with the anchor the car looks the same,
    without it the world-anchored texture would slide over it."""
    params = sample_scene_params(0, "A")
    R, C = camera_pose(params, 10.0)
    shift = np.array([1.3, 0.0, 0.0])
    shape = _car_shape(np.random.default_rng(3))

    def car(dx, anchor):
        b = _Builder()
        b.car(C[0] - 1 + dx, C[0] + 1 + dx, C[2] + 8, C[2] + 12.5, (0.8, 0.2, 0.2), (0.3, 0.7),
              shape, anchor=(anchor, 0.0, 0.0))
        return b

    seq = render_frames(params, [(R, C), (R, C + shift), (R, C + shift), (R, C)], W, H,
                        objects=[car(0, 0), car(1.3, 1.3), car(1.3, 0), None])
    on_car = (seq.depths[0] < seq.depths[3] - 0.5) & (np.abs(seq.depths[0] - seq.depths[1]) < 1e-3)
    assert on_car.sum() > 300
    img = [s.astype(int) for s in seq.images]
    assert np.abs(img[1] - img[0])[on_car].max() <= 3
    assert np.abs(img[2] - img[0])[on_car].mean() > 4 * np.abs(img[1] - img[0])[on_car].mean()


def test_exposure_jumps_by_its_factor(drive):
    seq, plan = drive
    idx = frames_of(seq.labels, "exposure")
    k0 = idx[len(idx) // 2]  # the change: from the segment's middle frame on
    assert [plan.exposure[i] for i in idx] == [1.0] * 3 + [0.45] * 3
    mean = [float(seq.images[i].mean()) for i in range(len(seq))]
    expect = 0.45 ** (1 / seq.params.gamma)
    assert mean[k0] / mean[k0 - 1] == pytest.approx(expect, rel=0.08)
    assert mean[k0 - 1] / mean[k0 - 2] == pytest.approx(1.0, rel=0.03)
    assert mean[k0 + 1] / mean[k0] == pytest.approx(1.0, rel=0.03)
    assert mean[idx[-1] + 1] / mean[idx[-1]] == pytest.approx(1 / expect, rel=0.08)  # back after


def test_default_hard_drive_plan():
    params = sample_scene_params(1, "B")
    plan = plan_drive(params)
    n = sum(s.frames for s in DEFAULT_HARD_SEGMENTS)
    assert len(plan) == len(plan.labels) == len(plan.vehicles) == len(plan.exposure) == n == 280
    # each hard segment covers at least one whole window of 15 frames side by side
    for kind in ("rotate", "static", "crossing", "lead", "exposure", "turn", "creep", "truck"):
        idx = frames_of(plan.labels, kind)
        assert any(set(range(w, w + 15)) <= set(idx) for w in range(0, n, 15)), kind
    changed = [i for i, e in enumerate(plan.exposure) if e != 1.0]
    assert changed == list(range(140, 150))
    assert plan.exposure[140] in EXPOSURE_FACTORS
    # the first 250 frames are the drive before its last segment grew from 10 to 40 frames
    shorter = plan_drive(params, (*DEFAULT_HARD_SEGMENTS[:-1], Segment("drive", 10)))
    assert len(shorter) == 250 and shorter.vehicles == plan.vehicles[:250]
    assert shorter.exposure == plan.exposure[:250]
    # the first 165 frames are the drive of the first five kinds, as they were
    first = plan_drive(params, DEFAULT_HARD_SEGMENTS[:11])
    assert len(first) == 165 and first.vehicles == plan.vehicles[:165]
    assert [s.kind for s in DEFAULT_HARD_SEGMENTS[:11]] == [
        "drive", "rotate", "drive", "static", "drive", "crossing", "drive", "lead", "drive",
        "exposure", "drive"]
    # deterministic for the scene
    again = plan_drive(params)
    assert again.vehicles == plan.vehicles and again.exposure == plan.exposure
    for (R0, C0), (R1, C1) in zip(plan.poses, again.poses, strict=True):
        np.testing.assert_array_equal(R0, R1)
        np.testing.assert_array_equal(C0, C1)


def test_render_is_deterministic():
    params = sample_scene_params(0, "A")
    a = render_hard_drive(params, [("crossing", 2), ("lead", 2)], 160, 48)
    b = render_hard_drive(params, [("crossing", 2), ("lead", 2)], 160, 48)
    for x, y in zip(a.images + a.depths, b.images + b.depths, strict=True):
        np.testing.assert_array_equal(x, y)


def test_bad_segments_and_frames_are_clear_errors():
    for bad in ([("fly", 3)], [("drive", 0)], [("drive", 1.5)], [("rotate", 3, 2.0)],
                [("exposure", 3, 0.0)], [], ["drive"]):
        with pytest.raises(InputError):
            as_segments(bad)
    assert as_segments([("exposure", 2, 0.5)]) == (Segment("exposure", 2, 0.5),)
    params = sample_scene_params(0, "A")
    pose = camera_pose(params, 0.0)
    with pytest.raises(InputError):
        render_frames(params, [pose, pose], 16, 8, objects=[None])
    with pytest.raises(InputError):
        render_frames(params, [], 16, 8)


def test_kitti_writer_labels(tmp_path):
    intr = Intrinsics(20.0, 20.0, 8.0, 4.0, 16, 8)
    seq = types.SimpleNamespace(images=[np.zeros((8, 16, 3), np.uint8)] * 3,
                                depths=[np.ones((8, 16), np.float32)] * 3,
                                stamps=[0.0, 0.1, 0.2], intrinsics=intr,
                                labels=["drive", "static", "static"])
    write_kitti_drive(seq, tmp_path / "raw", tmp_path / "gt", gt_skip_ends=0)
    path = tmp_path / "raw" / "2011_09_26" / DRIVE / "image_02" / SEGMENTS_FILE
    assert path.read_text() == "0 drive\n1 static\n2 static\n"
    assert read_segments(path) == seq.labels
    # overwritten by a drive without labels: no stale segments file
    write_kitti_drive(types.SimpleNamespace(**{**vars(seq), "labels": []}), tmp_path / "raw",
                      overwrite=True)
    assert not path.exists()
    for labels in (["drive"] * 2, ["drive", "two words", "x"]):  # checked before any writing
        with pytest.raises(InputError):
            write_kitti_drive(types.SimpleNamespace(**{**vars(seq), "labels": labels}),
                              tmp_path / "raw2")
        assert not (tmp_path / "raw2").exists()
    for text in ("0 drive\n0 static\n", "1 drive\n", "0 drive extra\n"):
        path.write_text(text)
        with pytest.raises(InputError):
            read_segments(path)
    with pytest.raises(InputError):
        write_segments(path, ["a b"])


def test_cli_generate_hard_and_street(tmp_path, capsys):
    raw, gt = tmp_path / "raw", tmp_path / "gt"
    common = ["--kitti-raw", str(raw), "--kitti-gt", str(gt), "--width", "160", "--height", "48"]
    assert cli_main(["generate", "--scenario", "hard", "--domain", "B", "--seed", "1",
                     *common]) == 0
    drive = KittiDrive(raw, DRIVE, gt)
    n = sum(s.frames for s in DEFAULT_HARD_SEGMENTS)
    assert len(drive) == n
    labels = read_segments(drive.drive_dir / "image_02" / SEGMENTS_FILE)
    assert labels == [s.kind for s in DEFAULT_HARD_SEGMENTS for _ in range(s.frames)]
    assert [drive.gt_path(i) is not None for i in range(n)] == [5 <= i < n - 5 for i in range(n)]
    assert "segments.txt" in capsys.readouterr().out
    # --replace: the counterfactual drive, equal frame for frame outside the replaced segment
    raw2, gt2 = tmp_path / "raw_nt", tmp_path / "gt_nt"
    assert cli_main(["generate", "--scenario", "hard", "--domain", "B", "--seed", "1",
                     "--replace", "truck=drive", "--kitti-raw", str(raw2), "--kitti-gt",
                     str(gt2), "--width", "160", "--height", "48"]) == 0
    other = KittiDrive(raw2, DRIVE, gt2)
    truck = [k == "truck" for k in labels]
    assert read_segments(other.drive_dir / "image_02" / SEGMENTS_FILE) == \
        ["drive" if t else k for k, t in zip(labels, truck, strict=True)]
    changed = [not np.array_equal(drive.load_image(i), other.load_image(i)) for i in range(n)]
    assert changed == truck
    for bad in (["--replace", "truck"], ["--replace", "truck=bus"]):
        assert cli_main(["generate", "--scenario", "hard", *bad, "--drive-number", "3",
                         *common]) == 2
        assert "truck" in capsys.readouterr().err
    assert cli_main(["generate", "--replace", "truck=drive", "--drive-number", "4",
                     *common]) == 2
    assert "--replace" in capsys.readouterr().err
    # --frames belongs to the street scenario
    assert cli_main(["generate", "--scenario", "hard", "--frames", "10", "--drive-number", "2",
                     *common]) == 2
    assert "--frames" in capsys.readouterr().err
    # the street scenario is today's drive
    raw, gt = tmp_path / "street_raw", tmp_path / "street_gt"
    assert cli_main(["generate", "--frames", "3", "--domain", "A", "--seed", "2", "--kitti-raw",
                     str(raw), "--kitti-gt", str(gt), "--width", "160", "--height", "48"]) == 0
    street = KittiDrive(raw, DRIVE, gt)
    ref = make_sequence(seed=2, domain="A", num_frames=3, width=160, height=48)
    assert len(street) == 3
    for i in range(3):
        np.testing.assert_array_equal(street.load_image(i), ref.images[i])
    assert not (street.drive_dir / "image_02" / SEGMENTS_FILE).exists()
    assert cv2.imread(str(street.image_path(0))) is not None


def test_replace_segments_keeps_lengths_and_order():
    from sfm_ttr_ros.data.synthetic import Segment, replace_segments

    segs = (Segment("drive", 5), Segment("exposure", 4, 2.0), Segment("truck", 3),
            ("exposure", 2))
    out = replace_segments(segs, "exposure", "drive")
    assert out == (Segment("drive", 5), Segment("drive", 4), Segment("truck", 3),
                   Segment("drive", 2))
    assert replace_segments(segs, "truck", "exposure")[2] == Segment("exposure", 3)
    assert replace_segments(segs, "static", "drive") == tuple(
        s if isinstance(s, Segment) else Segment(*s) for s in segs)
    for old, new in (("bus", "drive"), ("truck", "bus")):
        with pytest.raises(InputError, match="bus"):
            replace_segments(segs, old, new)
