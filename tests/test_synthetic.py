"""Synthetic KITTI-like street drives: exact depth / poses, domains, determinism, SIFT texture."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.geometry import camera_centre
from sfm_ttr_ros.data.synthetic import (
    SceneParams,
    SyntheticSequence,
    _materials,
    camera_pose,
    make_sequence,
    render_sequence,
    sample_scene_params,
)

SIFT_W, SIFT_H = 480, 145  # a small KITTI-shaped frame
MIN_SIFT_MATCHES = 100  # ratio-test (0.75) matches between two consecutive frames


@pytest.fixture(scope="module")
def seq_a() -> SyntheticSequence:
    return make_sequence(seed=0, domain="A", num_frames=3, width=SIFT_W, height=SIFT_H)


@pytest.fixture(scope="module")
def seq_b() -> SyntheticSequence:
    return make_sequence(seed=0, domain="B", num_frames=3, width=SIFT_W, height=SIFT_H)


def reproject(seq: SyntheticSequence, i: int, j: int, uv: np.ndarray, z: np.ndarray):
    """Pixels ``uv`` (N x 2) of frame i with depths ``z`` -> pixels and depths in frame j."""
    K = seq.intrinsics.K
    rays = np.linalg.inv(K) @ np.vstack([uv.T, np.ones(len(uv))])
    T = seq.cam_from_world[j] @ np.linalg.inv(seq.cam_from_world[i])
    Y = T[:3, :3] @ (rays * z) + T[:3, 3:]
    q = K @ Y
    return (q[:2] / q[2]).T, Y[2]


def test_shapes_dtypes_and_poses(seq_a):
    seq = seq_a
    assert len(seq) == 3
    assert len(seq.images) == len(seq.depths) == len(seq.cam_from_world) == len(seq.stamps) == 3
    intr = seq.intrinsics
    assert (intr.width, intr.height) == (SIFT_W, SIFT_H)
    assert intr.fx == pytest.approx(seq.params.focal_scale * SIFT_W)
    assert intr.fy == intr.fx
    for img, d, T in zip(seq.images, seq.depths, seq.cam_from_world, strict=True):
        assert img.shape == (SIFT_H, SIFT_W, 3) and img.dtype == np.uint8
        assert d.shape == (SIFT_H, SIFT_W) and d.dtype == np.float32
        assert T.shape == (4, 4) and T.dtype == np.float64
        R = T[:3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
        assert np.isfinite(d).all() and (d >= 0).all()
    np.testing.assert_allclose(np.diff(seq.stamps), 0.1, atol=1e-6)  # 10 Hz (float64 epoch)
    # the camera drives forward at params.speed metres per frame, ~camera_height above the road
    centres = [camera_centre(T) for T in seq.cam_from_world]
    step = np.linalg.norm(centres[1] - centres[0])
    assert step == pytest.approx(seq.params.speed, rel=0.01)
    assert -centres[0][1] == pytest.approx(seq.params.camera_height, abs=0.02)
    forward = seq.cam_from_world[0][2, :3]  # camera z axis in world coordinates
    assert forward[2] > 0.99


def test_deterministic_for_a_seed_and_prefix_stable():
    a = make_sequence(seed=7, domain="A", num_frames=2, width=160, height=48)
    _materials.cache_clear()  # regenerate the textures too
    b = make_sequence(seed=7, domain="A", num_frames=2, width=160, height=48)
    for x, y in zip(a.images + a.depths, b.images + b.depths, strict=True):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(a.cam_from_world[1], b.cam_from_world[1])
    # a longer drive of the same scene starts with the same frames
    longer = render_sequence(a.params, 4, 160, 48)
    np.testing.assert_array_equal(longer.images[1], a.images[1])
    np.testing.assert_array_equal(longer.depths[1], a.depths[1])
    # another seed is another scene
    c = make_sequence(seed=0, domain="A", num_frames=1, width=160, height=48)
    assert c.params != a.params
    assert not np.array_equal(c.images[0], a.images[0])


def test_domains_differ_in_parameters():
    for seed in range(6):
        a, b = sample_scene_params(seed, "A"), sample_scene_params(seed, "B")
        assert isinstance(a, SceneParams) and (a.domain, b.domain) == ("A", "B")
        assert b.street_width < a.street_width
        assert b.facade_height_range[0] > a.facade_height_range[1] - 10
        assert b.facade_height_range[1] > a.facade_height_range[1]
        assert b.camera_height < a.camera_height
        assert b.focal_scale < a.focal_scale
        assert b.ambient > a.ambient
        assert (a.texture_style, b.texture_style) == ("classic", "modern")
        assert 1.5 < a.camera_height < 1.8 and 0.5 <= a.speed <= 1.5  # KITTI-like
        assert sample_scene_params(seed, "A") == a  # deterministic
    with pytest.raises(InputError, match="domain"):
        sample_scene_params(0, "Z")


def test_domain_c_is_a_road_with_real_edges():
    """Domain C: A's camera on a cambered road of plain asphalt, a wall, a raised track bed and
    the bonnet in view; the camera rides its lane (height over the road under it) and the
    bottom of the image is the bonnet, at the depth its top gives."""
    from sfm_ttr_ros.data.synthetic.scene import road_level

    a, c = sample_scene_params(2, "A"), sample_scene_params(2, "C")
    assert c.domain == "C" and (c.camera_height, c.focal_scale) == (a.camera_height,
                                                                    a.focal_scale)
    assert 0.02 <= c.camber <= 0.03 and c.road_contrast < 0.5 and c.wall_height > 1.5
    assert c.tram_bed_height > c.kerb_height and c.bonnet_length > 1.5
    assert (a.camber, a.wall_height, a.tram_bed_width, a.bonnet_length) == (0, 0, 0, 0)
    _, C = camera_pose(c, 0.0)
    assert road_level(c, C[0]) - C[1] == pytest.approx(c.camera_height, abs=0.011)
    assert road_level(c, 0.0) == pytest.approx(-c.camber * c.street_width / 2)
    seq = make_sequence(seed=2, domain="C", num_frames=1, width=320, height=96)
    intr, depth = seq.intrinsics, seq.depths[0]
    slope = (95 - intr.cy) / intr.fy  # the bottom row's ray, below the optical axis
    expected = c.bonnet_drop / (slope + c.pitch)  # ~ flat: pitch and roll are small
    assert float(np.median(depth[95, 140:180])) == pytest.approx(expected, rel=0.1)


def test_domains_differ_in_image_statistics(seq_a, seq_b):
    """Sunny classic town (A): brighter, more saturated, more contrast than overcast B."""

    def stats(seq):
        hsv = np.stack([cv2.cvtColor(im, cv2.COLOR_RGB2HSV) for im in seq.images])
        return hsv[..., 1].mean(), hsv[..., 2].mean(), np.mean([im.std() for im in seq.images])

    sat_a, val_a, std_a = stats(seq_a)
    sat_b, val_b, std_b = stats(seq_b)
    assert sat_a > sat_b + 5
    assert val_a > val_b + 5
    assert std_a > std_b * 1.15


@pytest.mark.parametrize("domain", ["A", "B"])
def test_depth_valid_below_horizon_and_zero_in_sky(domain, seq_a, seq_b):
    seq = seq_a if domain == "A" else seq_b
    p = seq.params
    for d, T in zip(seq.depths, seq.cam_from_world, strict=True):
        h = d.shape[0]
        assert (d[h // 2 :] > 0).mean() > 0.99  # lower half: road, kerbs, cars, facades
        assert (d[: h // 5] == 0).mean() > 0.005  # some sky at the top
        assert (d == 0).mean() < 0.25
        # every depth-0 pixel looks at the sky or at something beyond max_depth: everything
        # lies above the road plane, so its ray meets the road (if at all) beyond max_depth
        v, u = np.nonzero(d == 0)
        rays = np.linalg.inv(seq.intrinsics.K) @ np.vstack([u, v, np.ones_like(u)])
        dy = (T[:3, :3].T @ rays)[1]  # world y (down) of rays with camera z = 1
        highest_camera = p.camera_height + 0.011  # the path bounces by 1 cm
        with np.errstate(divide="ignore"):
            road_depth = np.where(dy > 0, highest_camera / dy, np.inf)
        assert (road_depth > p.max_depth).all()
        assert d.max() <= p.max_depth
        # and a depth-0 pixel is never below a valid one in the same column near the bottom
        assert (d[-1] > 0).all()


@pytest.mark.parametrize("domain", ["A", "B"])
def test_gt_depth_consistent_with_poses(domain, seq_a, seq_b):
    """Reproject frame-0 depths into frame 1: frame 1's depth there matches (exact geometry)."""
    seq = seq_a if domain == "A" else seq_b
    d0, d1 = seq.depths[0], seq.depths[1]
    h, w = d0.shape
    v, u = np.nonzero(d0 > 0)
    q, z1 = reproject(seq, 0, 1, np.stack([u, v], 1).astype(float), d0[v, u].astype(float))
    qi = np.round(q).astype(int)
    inside = (qi[:, 0] >= 0) & (qi[:, 0] < w) & (qi[:, 1] >= 0) & (qi[:, 1] < h) & (z1 > 0)
    assert inside.mean() > 0.7
    got = d1[qi[inside, 1], qi[inside, 0]]
    want = z1[inside]
    ok = got > 0
    rel = np.abs(got[ok] - want[ok]) / want[ok]
    assert np.median(rel) < 0.01
    assert (rel < 0.02).mean() > 0.9  # the rest: occlusion edges and rounding to the pixel grid


@pytest.mark.parametrize("domain", ["A", "B"])
def test_textures_give_many_consistent_sift_matches(domain, seq_a, seq_b):
    seq = seq_a if domain == "A" else seq_b
    sift = cv2.SIFT_create()
    grey = [cv2.cvtColor(seq.images[k], cv2.COLOR_RGB2GRAY) for k in (0, 1)]
    k0, d0 = sift.detectAndCompute(grey[0], None)
    k1, d1 = sift.detectAndCompute(grey[1], None)
    pairs = cv2.BFMatcher().knnMatch(d0, d1, k=2)
    good = [m for m, n in pairs if m.distance < 0.75 * n.distance]
    assert len(good) > MIN_SIFT_MATCHES, f"only {len(good)} SIFT matches"
    # geometric consistency with the ground truth: predicted vs matched position in frame 1
    p0 = np.array([k0[m.queryIdx].pt for m in good])
    p1 = np.array([k1[m.trainIdx].pt for m in good])
    h, w = seq.depths[0].shape
    ui = np.clip(np.round(p0[:, 0]).astype(int), 0, w - 1)
    vi = np.clip(np.round(p0[:, 1]).astype(int), 0, h - 1)
    z = seq.depths[0][vi, ui].astype(float)
    has = z > 0
    q, _ = reproject(seq, 0, 1, p0[has], z[has])
    err = np.linalg.norm(q - p1[has], axis=1)
    assert has.mean() > 0.9
    assert np.median(err) < 1.0
    assert (err < 2.0).mean() > 0.75


def test_long_drive_has_scenery_all_along():
    p = sample_scene_params(0, "A")
    seq = render_sequence(p, 2, 160, 48, start_offset=900.0)
    for d in seq.depths:
        assert (d[24:] > 0).mean() > 0.99
        # buildings / cars close by on both sides, not an empty plane
        assert np.median(d[8:30, :20]) < 40 and np.median(d[8:30, -20:]) < 40
    centre = camera_centre(seq.cam_from_world[0])
    assert centre[2] == pytest.approx(900.0)


def test_augmentation_and_bad_input():
    p = sample_scene_params(0, "B")
    clean = render_sequence(p, 1, 96, 32)
    noisy = render_sequence(p, 1, 96, 32, blur_sigma=1.0, noise_std=4.0)
    np.testing.assert_array_equal(clean.depths[0], noisy.depths[0])
    diff = np.abs(clean.images[0].astype(int) - noisy.images[0].astype(int))
    assert 0.5 < diff.mean() < 20
    with pytest.raises(InputError):
        render_sequence(p, 0, 96, 32)
    with pytest.raises(InputError):
        render_sequence(p, 1, 4, 32)


def test_rooms_are_closed_boxes_with_exact_depth_seen_from_inside():
    """An indoor room (the embedded network's training set): every pixel has depth (a closed
    room), within the room's diagonal, the cameras inside it and clear of its walls, the same
    frames for the same seed, and frame 0's depth reprojected into frame 1 agrees."""
    from sfm_ttr_ros.data.synthetic.rooms import render_room, sample_room

    seq = render_room(3, 2, 160, 120, focal_scale=0.6)
    again = render_room(3, 2, 160, 120, focal_scale=0.6)
    assert all(np.array_equal(a, b) for a, b in zip(seq.images, again.images, strict=True))
    room, _ = sample_room(3)
    diagonal = np.hypot(np.hypot(room.x1 - room.x0, room.z1 - room.z0), room.height)
    for d, T in zip(seq.depths, seq.cam_from_world, strict=True):
        assert (d > 0).all() and d.max() < diagonal
        c = camera_centre(T)
        assert room.x0 < c[0] < room.x1 and room.z0 < c[2] < room.z1 and -room.height < c[1] < 0
    assert seq.intrinsics.fx == pytest.approx(0.6 * 160)
    d0 = seq.depths[0]
    v, u = np.nonzero(d0 > 0)
    q, z1 = reproject(seq, 0, 1, np.stack([u, v], 1).astype(float), d0[v, u].astype(float))
    qi = np.round(q).astype(int)
    inside = (qi[:, 0] >= 0) & (qi[:, 0] < 160) & (qi[:, 1] >= 0) & (qi[:, 1] < 120) & (z1 > 0)
    rel = np.abs(seq.depths[1][qi[inside, 1], qi[inside, 0]] - z1[inside]) / z1[inside]
    assert inside.mean() > 0.3 and np.median(rel) < 0.01
