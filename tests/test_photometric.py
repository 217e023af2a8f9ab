"""Monodepth2's photometric loss with SfM poses (core/refinement/photometric.py): exact geometry on
an analytic plane, near-zero loss on rendered frames with the true depth and pose, auto-masking,
gradients, pose and intrinsics helpers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Intrinsics
from sfm_ttr_ros.core.models.mobilenet import MobileDepthNet
from sfm_ttr_ros.core.refinement.photometric import (
    PhotometricConfig,
    identity_errors,
    mean_3x3,
    network_intrinsics,
    photometric_loss,
    photometric_objective,
    prepare_frames,
    relative_pose,
    reprojection_error,
    scale_outputs,
    smoothness_loss,
    source_poses,
    ssim_target,
    ssim_term,
    warp,
)
from sfm_ttr_ros.data.synthetic import render_sequence, sample_scene_params

W, H = 256, 80  # small KITTI-shaped frames
SKY_DEPTH = 1e3  # the generator gives sky depth 0; at 1 km it moves < 0.2 px between frames
NAMES = ["f0", "f1", "f2"]


def to_tensor(image: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255.0


@pytest.fixture(scope="module")
def triplet():
    """Frames t-1, t, t+1 of a rendered drive, the target's true depth, K, true poses."""
    seq = render_sequence(sample_scene_params(0, "A"), 3, W, H, blur_sigma=0.8)
    depth = seq.depths[1].copy()
    depth[depth == 0] = SKY_DEPTH
    poses = dict(zip(NAMES, seq.cam_from_world, strict=True))
    return {
        "images": [to_tensor(im) for im in seq.images],
        "depth": torch.from_numpy(depth)[None, None],
        "K": seq.intrinsics.K,
        "T": [T for _, T in source_poses(NAMES, "f1", poses, 1.0)],
        "poses": poses,
        "raw": dict(zip(NAMES, seq.images, strict=True)),
        "intrinsics": seq.intrinsics,
    }


def loss_of(tr, depth_factor=1.0, poses=None, **kw) -> float:
    images = tr["images"]
    return float(photometric_loss(tr["depth"] * depth_factor, images[1], [images[0], images[2]],
                                  tr["K"], poses or tr["T"], **kw))


# -- per-pixel terms ----------------------------------------------------------------------------

def test_ssim_term_is_zero_for_an_image_with_itself_and_bounded():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, 20, 30, generator=g)
    y = torch.rand(2, 3, 20, 30, generator=g)
    assert ssim_term(x, x).abs().max() < 1e-6
    other = ssim_term(x, y)
    assert other.shape == x.shape
    assert float(other.min()) >= 0 and float(other.max()) <= 1 and float(other.mean()) > 0.2
    assert reprojection_error(x, x).abs().max() < 1e-6
    # alpha = 0: plain L1 averaged over RGB.
    torch.testing.assert_close(reprojection_error(x, y, alpha=0.0),
                               (x - y).abs().mean(1, keepdim=True))


def monodepth2_ssim(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Monodepth2's layers.py SSIM, written out as published (the reference)."""
    pool = torch.nn.AvgPool2d(3, 1)
    x, y = torch.nn.ReflectionPad2d(1)(x), torch.nn.ReflectionPad2d(1)(y)
    mu_x, mu_y = pool(x), pool(y)
    sigma_x = pool(x ** 2) - mu_x ** 2
    sigma_y = pool(y ** 2) - mu_y ** 2
    sigma_xy = pool(x * y) - mu_x * mu_y
    n = (2 * mu_x * mu_y + 0.01 ** 2) * (2 * sigma_xy + 0.03 ** 2)
    d = (mu_x ** 2 + mu_y ** 2 + 0.01 ** 2) * (sigma_x + sigma_y + 0.03 ** 2)
    return torch.clamp((1 - n / d) / 2, 0, 1)


def test_ssim_with_the_targets_statistics_cached_is_monodepth2s():
    g = torch.Generator().manual_seed(3)
    x = torch.rand(1, 3, 24, 40, generator=g)
    y = torch.rand(1, 3, 24, 40, generator=g)
    stats = ssim_target(y)
    torch.testing.assert_close(ssim_term(x, y), monodepth2_ssim(x, y), rtol=1e-5, atol=1e-6)
    assert torch.equal(ssim_term(x, y, stats), ssim_term(x, y))  # the same numbers, cached
    box = torch.nn.functional.avg_pool2d(x, 3, 1)  # the separable 3 x 3 mean is the pool
    torch.testing.assert_close(mean_3x3(x), box, rtol=1e-6, atol=1e-6)
    with pytest.raises(InputError, match="SSIM target"):
        ssim_term(x[..., :20], y[..., :20], stats)


def test_warp_with_identity_pose_returns_the_image():
    g = torch.Generator().manual_seed(1)
    image = torch.rand(1, 3, 24, 40, generator=g)
    depth = 1 + 20 * torch.rand(1, 1, 24, 40, generator=g)
    K = np.array([[30.0, 0, 19.3], [0, 30.0, 11.8], [0, 0, 1]])
    warped, valid = warp(image, depth, K, np.eye(4))
    torch.testing.assert_close(warped, image, atol=1e-5, rtol=0)
    assert bool(valid.all())


def plane_scene(depth: float = 8.0):
    """A textured fronto-parallel plane at ``depth`` seen by the target and by two sources
    moved by T_{s<-t} and roughly its opposite (rotation and translation): each source image
    is rendered exactly through the plane's homography H = K (R + t n^T / d) K^-1, with a
    smooth analytic texture. Returns target, sources, depth map, K, poses."""
    h, w = 48, 96
    K = np.array([[60.0, 0, 47.3], [0, 60.0, 23.6], [0, 0, 1]])

    def pose(a, b, t):
        ry = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
        rx = np.array([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = ry @ rx, t
        return T

    def texture(x, y):
        return np.stack([0.5 + 0.3 * np.sin(0.45 * x + 0.2 * y),
                         0.5 + 0.3 * np.cos(0.3 * y - 0.25 * x),
                         0.5 + 0.2 * np.sin(0.2 * x) * np.cos(0.35 * y)])

    def as_tensor(a):
        return torch.from_numpy(a)[None].float()

    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    poses = [pose(0.02, -0.015, [0.35, -0.05, -0.4]), pose(-0.02, 0.01, [-0.3, 0.04, 0.4])]
    sources = []
    for T in poses:
        homography = K @ (T[:3, :3] + np.outer(T[:3, 3], [0, 0, 1]) / depth) @ np.linalg.inv(K)
        q = np.linalg.inv(homography) @ np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
        sources.append(as_tensor(texture((q[0] / q[2]).reshape(h, w),
                                         (q[1] / q[2]).reshape(h, w))))
    return as_tensor(texture(xs, ys)), sources, torch.full((1, 1, h, w), depth), K, poses


def test_warp_is_exact_on_a_plane_seen_through_its_homography():
    target, sources, depth, K, poses = plane_scene()
    for source, T in zip(sources, poses, strict=True):
        warped, valid = warp(source, depth, K, T)
        assert bool(valid.all())
        # Bilinear sampling of a smooth texture; the outer 8 px leave the source's view.
        assert float((warped - target).abs()[..., 8:-8, 8:-8].max()) < 0.015
    # The two sources see each other's lost borders: the min over them is near zero.
    loss_true = float(photometric_loss(depth, target, sources, K, poses, automask=False))
    assert loss_true < 0.005
    for factor in (0.8, 1.25):
        assert float(photometric_loss(depth * factor, target, sources, K, poses,
                                      automask=False)) > 5 * loss_true


def test_points_behind_the_source_camera_are_invalid_and_leave_no_term():
    target, (source, _), depth, K, (T, _) = plane_scene()
    T_behind = np.eye(4)
    T_behind[2, 3] = -20.0  # the source camera 20 m ahead of a plane at 8 m
    _, valid = warp(source, depth, K, T_behind)
    assert not bool(valid.any())
    loss, maps = photometric_loss(depth, target, [source], K, [T_behind], automask=False,
                                  return_maps=True)
    assert float(loss) == 0.0 and bool(torch.isinf(maps.min_error).all())
    assert bool((maps.source_index == -1).all())
    # With a valid second source, that source alone makes the minimum.
    loss2, maps2 = photometric_loss(depth, target, [source, source], K, [T_behind, T],
                                    automask=False, return_maps=True)
    assert bool((maps2.source_index == 1).all())
    assert float(loss2) == pytest.approx(
        float(photometric_loss(depth, target, [source], K, [T], automask=False)))


# -- rendered frames: true depth and pose -------------------------------------------------------

def test_true_depth_and_pose_give_a_near_zero_loss(triplet):
    images = triplet["images"]
    identity = float(torch.minimum(reprojection_error(images[0], images[1]),
                                   reprojection_error(images[2], images[1])).mean())
    true = loss_of(triplet, automask=False)
    assert true < 0.02 and true < 0.2 * identity  # un-warped neighbours explain it far worse
    shifted = [T.copy() for T in triplet["T"]]
    for T in shifted:
        T[0, 3] += 0.1  # 10 cm sideways
    for wrong in (loss_of(triplet, 1.3, automask=False), loss_of(triplet, 0.7, automask=False),
                  loss_of(triplet, poses=shifted, automask=False)):
        assert wrong > 2 * true


def test_loss_grows_monotonically_with_the_depth_scale_error(triplet):
    below = [loss_of(triplet, f) for f in (1.0, 0.9, 0.7, 0.5)]
    above = [loss_of(triplet, f) for f in (1.0, 1.1, 1.3, 2.0)]
    assert all(np.diff(below) > 0), below
    assert all(np.diff(above) > 0), above


def test_sfm_poses_in_other_units_are_brought_to_depth_units_by_the_scale(triplet):
    """An SfM reconstruction in units where D_sfm = D / 2 has halved translations; with the
    alignment scale ŝ = 2 the poses (and the loss) are the true ones again."""
    sfm_poses = {}
    for name, T in triplet["poses"].items():
        T = T.copy()
        T[:3, 3] /= 2.0
        sfm_poses[name] = T
    scaled = [T for _, T in source_poses(NAMES, "f1", sfm_poses, 2.0)]
    for got, want in zip(scaled, triplet["T"], strict=True):
        np.testing.assert_allclose(got, want, atol=1e-12)
    unscaled = [T for _, T in source_poses(NAMES, "f1", sfm_poses, 1.0)]
    assert loss_of(triplet, poses=unscaled) > 1.5 * loss_of(triplet, poses=scaled)


def test_gradient_with_respect_to_depth_is_finite(triplet):
    images = triplet["images"]
    depth = (triplet["depth"] * 1.2).requires_grad_(True)
    loss = photometric_loss(depth, images[1], [images[0], images[2]], triplet["K"], triplet["T"])
    loss.backward()
    assert torch.isfinite(depth.grad).all() and float(depth.grad.abs().sum()) > 0
    disp = (1.0 / triplet["depth"]).requires_grad_(True)
    smoothness_loss(disp, images[1]).backward()
    assert torch.isfinite(disp.grad).all() and float(disp.grad.abs().sum()) > 0


# -- auto-masking -------------------------------------------------------------------------------

def test_automask_removes_a_static_copy(triplet):
    """Source = target (a camera that did not move, with SfM reporting motion anyway): every
    pixel falls back to the identity error, the loss is the tie-breaking noise only."""
    images = triplet["images"]
    target = images[1]
    loss, maps = photometric_loss(triplet["depth"], target, [target, target], triplet["K"],
                                  triplet["T"], return_maps=True)
    assert abs(float(loss)) < 1e-5
    assert bool(maps.identity_mask.all()) and bool((maps.source_index == -1).all())
    unmasked = photometric_loss(triplet["depth"], target, [target, target], triplet["K"],
                                triplet["T"], automask=False)
    assert float(unmasked) > 0.02
    # Deterministic: the noise comes from the seeded generator.
    again = photometric_loss(triplet["depth"], target, [target, target], triplet["K"],
                             triplet["T"])
    assert float(again) == float(loss)


def test_precomputed_identity_errors_give_the_same_loss(triplet):
    images = triplet["images"]
    sources = [images[0], images[2]]
    identity = identity_errors(images[1], sources, seed=3)
    assert identity.shape == (1, 2, H, W)
    inline = photometric_loss(triplet["depth"], images[1], sources, triplet["K"], triplet["T"],
                              seed=3)
    given = photometric_loss(triplet["depth"], images[1], sources, triplet["K"], triplet["T"],
                             identity=identity)
    assert float(given) == float(inline)
    with pytest.raises(InputError, match="identity errors"):
        photometric_loss(triplet["depth"], images[1], sources, triplet["K"], triplet["T"],
                         identity=identity[:, :1])


def test_automask_removes_an_object_moving_with_the_camera(triplet):
    """A patch that sits at the same pixels in every frame (an object driving with the camera)
    is explained by the un-warped sources; the static scene around it is not."""
    images = triplet["images"]
    rows, cols = slice(20, 60), slice(100, 160)
    sources = []
    for src in (images[0], images[2]):
        src = src.clone()
        src[..., rows, cols] = images[1][..., rows, cols]
        sources.append(src)
    _, maps = photometric_loss(triplet["depth"], images[1], sources, triplet["K"], triplet["T"],
                               return_maps=True)
    inside = maps.identity_mask[..., rows, cols].float().mean()
    outside = maps.identity_mask.float().sum() - maps.identity_mask[..., rows, cols].float().sum()
    outside = outside / (maps.identity_mask.numel() - 40 * 60)
    assert float(inside) > 0.95
    assert float(outside) < 0.3


# -- poses, intrinsics, scales, bad input -------------------------------------------------------

def test_source_poses_skip_unregistered_frames_and_window_ends(triplet):
    poses = triplet["poses"]
    np.testing.assert_allclose(relative_pose(poses["f0"], poses["f0"], 3.0), np.eye(4),
                               atol=1e-12)
    assert [n for n, _ in source_poses(NAMES, "f0", poses, 1.0)] == ["f1"]
    partial = {"f1": poses["f1"], "f2": poses["f2"]}
    assert [n for n, _ in source_poses(NAMES, "f1", partial, 1.0)] == ["f2"]
    assert source_poses(NAMES, "f0", partial, 1.0) == []  # the target itself is unregistered
    assert [n for n, _ in source_poses(NAMES, "f0", poses, 1.0, offsets=(1, 2))] == ["f1", "f2"]
    with pytest.raises(InputError):
        source_poses(NAMES, "f9", poses, 1.0)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(InputError):
            relative_pose(poses["f0"], poses["f1"], bad)


def test_network_intrinsics_follow_the_network_resize():
    """A Gaussian dot resized like DepthModel.preprocess lands where network_intrinsics
    projects it (Intrinsics.scaled's c·s would be 0.5·(1 − s) px off)."""
    intr = Intrinsics(100.0, 100.0, 63.7, 31.2, 128, 64)
    X = np.array([0.37, -0.21, 2.0])
    u, v = (intr.K @ X)[:2] / X[2]
    ys, xs = np.mgrid[0:64, 0:128]
    dot = np.exp(-((xs - u) ** 2 + (ys - v) ** 2) / (2 * 3.0 ** 2))
    small = F.interpolate(torch.from_numpy(dot)[None, None].float(), size=(32, 64),
                          mode="bilinear", align_corners=False, antialias=True)[0, 0].numpy()
    ys, xs = np.mgrid[0:32, 0:64]
    centroid = np.array([(small * xs).sum(), (small * ys).sum()]) / small.sum()
    K = network_intrinsics(intr, (32, 64))
    expected = (K @ X)[:2] / X[2]
    np.testing.assert_allclose(centroid, expected, atol=0.02)
    naive = intr.scaled(64, 32).K
    assert np.abs((naive @ X)[:2] / X[2] - centroid).max() > 0.2


def test_scale_outputs_and_objective_with_a_multi_scale_decoder():
    torch.manual_seed(0)
    model = MobileDepthNet(input_size=(64, 128)).eval()
    x = torch.rand(1, 3, 64, 128)
    features = model.encoder(x)
    single = scale_outputs(model, features)
    assert len(single) == 1 and single[0].depth.shape == (1, 1, 64, 128)
    torch.testing.assert_close(single[0].depth, model(x))
    outs = scale_outputs(model, features, scales=(0, 1, 2, 3))
    assert [o.scale for o in outs] == [0, 1, 2, 3]
    for o in outs:
        assert o.depth.shape == (1, 1, 64, 128)
        assert o.disp.shape == (1, 1, 64 // 2 ** o.scale, 128 // 2 ** o.scale)
    K = network_intrinsics(Intrinsics(70.0, 70.0, 63.5, 31.5, 128, 64), (64, 128))
    T = np.eye(4)
    T[2, 3] = -0.5
    cfg = PhotometricConfig(scales=(0, 1, 2, 3))
    terms = photometric_objective(outs, x, [x.flip(-1)], K, [T], cfg)
    manual = sum(photometric_loss(o.depth, x, [x.flip(-1)], K, [T])
                 + 1e-3 / 2 ** o.scale * smoothness_loss(o.disp, x) for o in outs) / 4
    torch.testing.assert_close(terms.total, manual)
    terms.total.backward()
    grads = [p.grad for p in model.encoder.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)


def test_prepare_frames_at_the_network_size(triplet):
    """A window's frames at a network input size smaller than the images: sources by offset,
    unregistered frames left out, K and images consistent (true depth beats scaled depth)."""
    model = MobileDepthNet(input_size=(64, 224)).eval()
    poses = triplet["poses"]
    frames = prepare_frames(model, NAMES, triplet["raw"], poses, 1.0, triplet["intrinsics"])
    assert [(f.name, f.source_names) for f in frames] == [
        ("f0", ["f1"]), ("f1", ["f0", "f2"]), ("f2", ["f1"])]
    f1 = frames[1]
    assert f1.target.shape == (1, 3, 64, 224) and f1.identity.shape == (1, 2, 64, 224)
    depth = F.interpolate(triplet["depth"], size=(64, 224), mode="nearest")
    losses = [float(photometric_loss(depth * k, f1.target, f1.sources, f1.K, f1.poses,
                                     identity=f1.identity)) for k in (1.0, 0.7, 1.3)]
    assert losses[0] < 0.6 * min(losses[1:]), losses
    partial = {n: poses[n] for n in ("f0", "f2")}  # the middle frame not registered
    assert prepare_frames(model, NAMES, triplet["raw"], partial, 1.0,
                          triplet["intrinsics"]) == []
    cfg = PhotometricConfig(source_offsets=(2,), automask=False)
    only = prepare_frames(model, NAMES, triplet["raw"], partial, 1.0, triplet["intrinsics"], cfg)
    assert [(f.name, f.source_names, f.identity) for f in only] == [("f0", ["f2"], None)]


def test_bad_input_is_refused():
    image = torch.rand(1, 3, 16, 16)
    depth = torch.ones(1, 1, 16, 16)
    K = np.array([[10.0, 0, 7.5], [0, 10.0, 7.5], [0, 0, 1]])
    with pytest.raises(InputError, match="at least one source"):
        photometric_loss(depth, image, [], K, [])
    with pytest.raises(InputError, match="poses"):
        photometric_loss(depth, image, [image], K, [np.eye(4), np.eye(4)])
    with pytest.raises(InputError):
        photometric_loss(depth, image, [torch.rand(1, 3, 8, 8)], K, [np.eye(4)])
    with pytest.raises(InputError):
        warp(image, depth, K, np.eye(3))
    with pytest.raises(InputError):
        warp(image, torch.ones(1, 1, 8, 8), K, np.eye(4))
    for kwargs in ({"alpha": 1.5}, {"smoothness_weight": -1.0}, {"source_offsets": (0, 1)},
                   {"source_offsets": ()}, {"scales": (-1,)}):
        with pytest.raises(InputError):
            PhotometricConfig(**kwargs)

