"""Rendering: one frame (:func:`_render`: ground planes, objects front to back, shading;
image + exact z-depth), the finishing (exposure, gamma, optional blur and noise), frames of
given camera poses with optional per-frame moving objects and exposure (:func:`render_frames`),
and street drives along the path (:func:`render_sequence`, :func:`make_sequence`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import cv2
import numpy as np

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Intrinsics
from sfm_ttr_ros.data.synthetic.geometry import (
    _build_scene,
    _Builder,
    _Scene,
    _with_objects,
    bonnet,
)
from sfm_ttr_ros.data.synthetic.raycast import _BATCH_AREA, _cast_batch, _intersect, _screen_rects
from sfm_ttr_ros.data.synthetic.scene import (
    FRAME_RATE,
    KITTI_START_STAMP,
    camera_pose,
    sample_scene_params,
    scene_intrinsics,
)
from sfm_ttr_ros.data.synthetic.shading import _shade

if TYPE_CHECKING:
    from sfm_ttr_ros.data.synthetic.scene import SceneParams


def _crowned(p: SceneParams, C: np.ndarray, Dx: np.ndarray, Dy: np.ndarray) -> np.ndarray:
    """Ray parameters of the hits on a cambered road (``p.camber``: y = −camber·(hw − |x|),
    two planes meeting at the crown x = 0), inf where a ray misses it."""
    f32 = np.float32
    s, hw, Cx, Cy = f32(p.camber), f32(p.street_width / 2), f32(C[0]), f32(C[1])
    best = np.full(Dx.shape, np.inf, f32)
    for sgn in (f32(-1), f32(1)):
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            t = (s * sgn * Cx - s * hw - Cy) / (Dy - s * sgn * Dx)
            x = Cx + t * Dx
            hit = (t > 0) & (sgn * x >= 0) & (np.abs(x) < hw) & (t < best)
        best = np.where(hit, t, best)
    return best


def _render(scene: _Scene, R_wc: np.ndarray, C: np.ndarray, intr: Intrinsics):
    p = scene.params
    W, H = intr.width, intr.height
    K = intr.K
    f32 = np.float32
    xn = ((np.arange(W, dtype=np.float64) - intr.cx) / intr.fx).astype(f32)
    yn = ((np.arange(H, dtype=np.float64) - intr.cy) / intr.fy).astype(f32)
    R = R_wc.astype(f32)
    Dx = R[0, 0] * xn[None, :] + R[0, 1] * yn[:, None] + R[0, 2]
    Dy = R[1, 0] * xn[None, :] + R[1, 1] * yn[:, None] + R[1, 2]
    Dz = R[2, 0] * xn[None, :] + R[2, 1] * yn[:, None] + R[2, 2]
    with np.errstate(divide="ignore"):
        iDx = np.where(Dx == 0, f32(1e30), 1.0 / Dx).astype(f32)
        iDy = np.where(Dy == 0, f32(1e30), 1.0 / Dy).astype(f32)
        iDz = np.where(Dz == 0, f32(1e30), 1.0 / Dz).astype(f32)
    Cx, Cy, Cz = (f32(c) for c in C)

    T = np.full((H, W), np.inf, f32)  # depth (= ray parameter, since D_cam has z = 1)
    OID = np.full((H, W), -1, np.int32)
    FACE = np.zeros((H, W), np.int8)  # 0..5: -x,+x,-y,+y,-z,+z normals; 6: curved

    # ground: road (y = 0, |x| < hw), sidewalks (y = -kh, |x| >= hw), kerb faces (x = +-hw)
    hw, kh = f32(p.street_width / 2), f32(p.kerb_height)
    down = Dy > 0
    with np.errstate(invalid="ignore", over="ignore"):
        t_road = np.where(down, -Cy * iDy, np.inf) if not p.camber else _crowned(p, C, Dx, Dy)
        ok = np.abs(Cx + t_road * Dx) < hw
        T = np.where(ok, t_road, T)
        t_side = np.where(down, (-kh - Cy) * iDy, np.inf)
        ok = (np.abs(Cx + t_side * Dx) >= hw) & (t_side < T)
        T = np.where(ok, t_side, T)
        OID[np.isfinite(T)] = 0
        OID[ok] = 1
        FACE[:] = 2
        for sgn in (-1.0, 1.0):
            t_k = (f32(sgn) * hw - Cx) * iDx
            y_k = Cy + t_k * Dy
            ok = (t_k > 0) & (y_k >= -kh) & (y_k <= 0) & (t_k < T)
            T[ok] = t_k[ok]
            OID[ok] = 2
            FACE[ok] = 0 if sgn > 0 else 1

    # objects: large screen rectangles one by one (front to back, skipping hidden ones), the
    # many small ones in one vectorised batch (a z-buffer is order independent)
    rects = _screen_rects(scene, R_wc, C, K, W, H, p.max_depth)
    rays = (Dx, Dy, Dz, iDx, iDy, iDz)
    small = []
    for rect in rects:
        oid, near, v0, v1, u0, u1 = rect
        if (v1 - v0) * (u1 - u0) <= _BATCH_AREA:
            small.append(rect)
            continue
        sl = (slice(v0, v1), slice(u0, u1))
        Ts = T[sl]
        if near >= Ts.max():  # hidden behind what is already drawn there
            continue
        t, hit, face = _intersect(scene, scene.kind[oid], oid, [r[sl] for r in rays], Cx, Cy, Cz)
        hit &= t < Ts
        if hit.any():
            Ts[hit] = t[hit]
            FACE[sl][hit] = face[hit] if isinstance(face, np.ndarray) else face
            OID[sl][hit] = oid
    if small:
        _cast_batch(scene, np.array(small), rays, (Cx, Cy, Cz), T, OID, FACE)

    # shading
    hitm = OID >= 0
    far = hitm & (T > p.max_depth)
    depth = np.where(hitm & ~far, T, 0).astype(f32)
    img = _shade(scene, intr, T, OID, FACE, hitm, Dx, Dy, Dz, C)
    return img, depth


@dataclass
class SyntheticSequence:
    """A rendered drive: images, exact depths and poses, shared intrinsics, 10 Hz stamps, and
    per-frame segment labels (scenario drives, :mod:`.scenario`; empty for a street drive)."""

    images: list[np.ndarray]  # H x W x 3 uint8 RGB
    depths: list[np.ndarray]  # H x W float32 metres, 0 = no depth (sky / beyond max_depth)
    cam_from_world: list[np.ndarray]  # 4x4 float64, x_cam = R x_world + t
    intrinsics: Intrinsics
    stamps: list[float]  # seconds, 10 Hz
    params: SceneParams
    labels: list[str] = field(default_factory=list)  # one per frame, or empty

    def __len__(self) -> int:
        return len(self.images)


def _with_bonnet(params: SceneParams, extra: _Builder | None, C: np.ndarray,
                 C0: np.ndarray) -> _Builder | None:
    """A frame's extra objects with the car's bonnet (:func:`geometry.bonnet`) when the scene
    has one."""
    hood = bonnet(params, np.asarray(C, float), np.asarray(C0, float))
    if hood is None:
        return extra
    if extra is not None:
        hood.rows = [*extra.rows, *hood.rows]
    return hood


def _finish(img: np.ndarray, p: SceneParams, rng, blur_sigma: float, noise_std: float):
    out = np.clip(img * p.exposure, 0, 1)
    if p.gamma != 1.0:
        out = out ** (1.0 / p.gamma)
    out = out * 255.0
    if blur_sigma > 0:
        out = cv2.GaussianBlur(out, (0, 0), blur_sigma)
    if noise_std > 0:
        out = out + rng.normal(0, noise_std, out.shape).astype(np.float32)
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def render_frames(
    params: SceneParams,
    poses: Sequence[tuple[np.ndarray, np.ndarray]],
    width: int = 1242,
    height: int = 375,
    seed: int = 0,
    *,
    objects: Sequence[_Builder | None] | None = None,
    exposure: Sequence[float] | None = None,
    labels: Sequence[str] | None = None,
    blur_sigma: float = 0.0,
    noise_std: float = 0.0,
    start_stamp: float = KITTI_START_STAMP,
    scene: _Scene | None = None,
) -> SyntheticSequence:
    """Render one frame per camera pose ``poses[i] = (R_wc, C)`` (world-from-camera rotation,
    camera centre) in the scene of ``params``, built once over the poses' ``z`` range.

    ``objects[i]`` (optional): extra objects of frame ``i`` only (moving vehicles, see
    :meth:`geometry._Builder.car`), appended to the scene for that frame; they are rendered, so
    the depth includes them exactly. ``exposure[i]`` (optional): a factor on ``params.exposure``
    for frame ``i``. ``labels`` (optional): one per frame, kept in the sequence. A frame with
    the previous frame's pose and no extra objects reuses its rendering (a standing camera).
    ``seed`` only drives the augmentation (``blur_sigma``, ``noise_std``), as in
    :func:`render_sequence`. ``scene`` (optional): a scene built elsewhere (an indoor room,
    :mod:`.rooms`) instead of the street of ``params``.
    """
    n = len(poses)
    if n < 1:
        raise InputError("no camera poses to render")
    if width < 8 or height < 8:
        raise InputError(f"image size too small: {width}x{height}")
    for name, per_frame in (("objects", objects), ("exposure", exposure), ("labels", labels)):
        if per_frame is not None and len(per_frame) != n:
            raise InputError(f"{name} has {len(per_frame)} entries for {n} camera poses")
    intr = scene_intrinsics(params, int(width), int(height))
    zs = [float(C[2]) for _, C in poses]
    if scene is None:
        scene = _build_scene(params, min(zs) - 40.0, max(zs) + params.max_depth * 1.5 + 20.0)
    rng = np.random.default_rng([int(seed), 4242])
    images, depths, cams, stamps = [], [], [], []
    prev = None  # (R_wc, C, image, depth) of a frame without extra objects
    for i, (R_wc, C) in enumerate(poses):
        extra = _with_bonnet(params, objects[i] if objects is not None else None, C,
                             poses[0][1])
        if extra is None and prev is not None and np.array_equal(R_wc, prev[0]) and \
                np.array_equal(C, prev[1]):
            img, depth = prev[2], prev[3].copy()
        else:
            frame_scene = scene if extra is None else _with_objects(scene, extra)
            img, depth = _render(frame_scene, R_wc, C, intr)
        prev = (R_wc, C, img, depth) if extra is None else None
        p = params
        if exposure is not None and exposure[i] != 1.0:
            p = dataclasses.replace(params, exposure=params.exposure * float(exposure[i]))
        images.append(_finish(img, p, rng, blur_sigma, noise_std))
        depths.append(depth)
        T = np.eye(4)
        T[:3, :3] = R_wc.T
        T[:3, 3] = -R_wc.T @ C
        cams.append(T)
        stamps.append(float(start_stamp + i / FRAME_RATE))
    return SyntheticSequence(images, depths, cams, intr, stamps, params,
                             list(labels) if labels is not None else [])


def render_sequence(
    params: SceneParams,
    num_frames: int,
    width: int = 1242,
    height: int = 375,
    seed: int = 0,
    start_offset: float = 0.0,
    blur_sigma: float = 0.0,
    noise_std: float = 0.0,
    start_stamp: float = KITTI_START_STAMP,
) -> SyntheticSequence:
    """Render ``num_frames`` frames of the scene ``params`` at ``width`` x ``height``.

    Frame ``i`` is taken at path position ``z = start_offset + i * params.speed``. ``seed`` only
    drives the optional augmentation (``blur_sigma`` px Gaussian blur, ``noise_std`` grey levels of
    Gaussian pixel noise); the scene itself is fixed by ``params`` (deterministic).
    """
    if num_frames < 1:
        raise InputError(f"num_frames must be >= 1, got {num_frames}")
    poses = [camera_pose(params, start_offset + i * params.speed) for i in range(num_frames)]
    return render_frames(params, poses, width, height, seed, blur_sigma=blur_sigma,
                         noise_std=noise_std, start_stamp=start_stamp)


def street_frames(params: SceneParams, num_frames: int, width: int = 1242, height: int = 375,
                  seed: int = 0) -> Iterator[tuple[np.ndarray, np.ndarray, float]]:
    """The frames of :func:`render_sequence` (same images, depths and 10 Hz stamps), one
    ``(image, depth, stamp)`` at a time, along ONE street laid out for the whole drive: a long
    drive without holding more than one frame. (``render_sequence(start_offset=...)`` lays a
    street out from its first frame's cell, so drives rendered piece by piece that way would
    not join.) The intrinsics are ``scene_intrinsics(params, width, height)``."""
    if num_frames < 1:
        raise InputError(f"num_frames must be >= 1, got {num_frames}")
    intr = scene_intrinsics(params, int(width), int(height))
    z_end = (num_frames - 1) * params.speed
    scene = _build_scene(params, -40.0, z_end + params.max_depth * 1.5 + 20.0)
    rng = np.random.default_rng([int(seed), 4242])
    C0 = camera_pose(params, 0.0)[1]
    for i in range(num_frames):
        R_wc, C = camera_pose(params, i * params.speed)
        extra = _with_bonnet(params, None, C, C0)
        img, depth = _render(scene if extra is None else _with_objects(scene, extra), R_wc, C,
                             intr)
        yield _finish(img, params, rng, 0.0, 0.0), depth, float(KITTI_START_STAMP + i / FRAME_RATE)


def make_sequence(
    seed: int = 0, domain: str = "A", num_frames: int = 10, width: int = 1242, height: int = 375
) -> SyntheticSequence:
    """Convenience: sample the scene of ``seed`` in ``domain`` and render ``num_frames`` frames."""
    return render_sequence(sample_scene_params(seed, domain), num_frames, width, height, seed=seed)
