"""KITTI-like synthetic street drives with exact depth and poses (analytic ray casting).

A street seen from a forward-moving car: road plane with lane markings, raised sidewalks with a
kerb, building blocks on both sides (a front row with varying set-back / height / length and a
taller back row seen through the gaps), parked cars (body, cabin and undercarriage boxes), poles
(vertical cylinders, some carrying a sign board), trees (cylindrical trunk + spherical crown) and
sky (no depth).

Conventions
-----------
* World frame: ``x`` right (across the street), ``y`` down, ``z`` along the street. The road is
  the plane ``y = 0``; the camera drives along ``+z`` at ``y = -camera_height``.
* Camera: OpenCV optical frame (x right, y down, z forward). ``cam_from_world[i]`` maps a world
  point to camera ``i``: ``x_cam = R @ x_world + t``.
* Pixel ``(u, v)`` (integer = pixel centre, the OpenCV / KITTI-projection convention) samples the
  ray ``K^-1 [u, v, 1]``. Depth is the ``z`` of the hit point in the camera frame (REP 118 / KITTI
  style), *not* the ray length. Sky, and anything farther than ``max_depth``, has depth 0.

Rendering: every pixel's ray is intersected with the ground (road, kerb faces, sidewalk), then
each object whose screen-space bounding rectangle overlaps the image is tested only on the pixels
of that rectangle (slab method for boxes, quadratics for cylinders and spheres), keeping the
nearest hit. The hit point's surface coordinates (metres on that surface) index world-anchored
per-material textures (multi-scale value noise, bricks, window grids, paving tiles, asphalt with
patches and cracks, foliage blobs, ...) through ``cv2.remap`` with wrap-around and trilinear
mip-mapping chosen from the pixel footprint, then Lambertian shading with a sun direction, an
ambient term, distance haze, exposure and gamma.

Domains (see :func:`sample_scene_params`): ``"A"`` is a sunny KITTI-like town (wide street, low
warm plaster/brick facades, trees, KITTI camera); ``"B"`` is an overcast dense downtown (narrow
street, tall grey concrete/glass facades, darker asphalt, more parked cars, few trees, lower and
wider-angle camera, more yaw wobble, flatter contrast).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from sfm_ttr_ros.core.frames import InputError, Intrinsics

DOMAINS = ("A", "B")
KITTI_START_STAMP = 1317042145.964389  # 2011-09-26 13:02:25.964389 UTC, a KITTI-like epoch
FRAME_RATE = 10.0  # Hz, like KITTI

# ---------------------------------------------------------------------------------------------
# Scene parameters
# ---------------------------------------------------------------------------------------------


@dataclass
class SceneParams:
    """All the randomness of one scene (drawn from a seed by :func:`sample_scene_params`).

    Lengths in metres, angles in radians. Object counts are *per 100 m of street and per side*
    (the scene is generated procedurally along the whole path, whatever its length).
    """

    seed: int = 0
    domain: str = "A"
    street_width: float = 12.0  # kerb to kerb
    sidewalk_width: float = 3.0
    kerb_height: float = 0.13
    facade_height_range: tuple[float, float] = (8.0, 18.0)
    facade_setback_max: float = 4.0  # front-row set-back behind the sidewalk
    block_length_range: tuple[float, float] = (10.0, 30.0)
    camera_height: float = 1.65
    focal_scale: float = 0.58  # fx = fy = focal_scale * width (KITTI: 721.5 / 1242 = 0.581)
    cx_frac: float = 0.4908  # cx = cx_frac * width (KITTI: 609.6 / 1242)
    cy_frac: float = 0.4609  # cy = cy_frac * height (KITTI: 172.9 / 375)
    speed: float = 1.0  # metres per frame (10 Hz)
    yaw_amplitude: float = 0.02  # heading amplitude of the gentle lateral S-curve
    yaw_period: float = 120.0  # metres per S-curve period
    yaw_jitter: float = 0.003  # extra small steering wobble (rad)
    pitch: float = 0.005  # positive = looking down
    lane_offset: float = 2.0  # camera x (right of the street centre)
    texture_style: str = "classic"
    sun_direction: tuple[float, float, float] = (-0.4, -0.75, 0.5)  # towards the sun, world
    ambient: float = 0.4
    sun_strength: float = 1.0
    exposure: float = 1.05
    gamma: float = 1.0
    haze_distance: float = 350.0
    haze_color: tuple[float, float, float] = (0.75, 0.8, 0.88)
    sky_top: tuple[float, float, float] = (0.35, 0.55, 0.85)
    sky_horizon: tuple[float, float, float] = (0.78, 0.85, 0.93)
    num_cars: int = 8
    num_poles: int = 4
    num_trees: int = 4
    max_depth: float = 200.0  # hits farther than this get depth 0 (like a LiDAR's range)


def sample_scene_params(seed: int, domain: str = "A") -> SceneParams:
    """Draw the parameters of one scene of ``domain`` ("A" or "B") from ``seed``.

    Domain A (sunny KITTI-like town): street 10-14 m, sidewalks 2.5-4 m, facades 8-18 m with up to
    4 m set-back, camera 1.60-1.70 m high with KITTI's focal (0.56-0.60 x width) and principal
    point, 0.6-1.3 m/frame, heading wobble 0.005-0.03 rad, warm "classic" plaster / brick
    textures, low sun from the left (ambient 0.35-0.45), 6-10 parked cars, 3-5 poles and 3-6
    trees per 100 m per side.

    Domain B (overcast dense downtown): street 7.5-9.5 m, sidewalks 1.8-2.8 m, facades 15-35 m
    with at most 1.5 m set-back, lower camera 1.35-1.50 m with a wider field of view (focal
    0.45-0.50 x width, centred principal point), 0.6-1.1 m/frame, heading wobble 0.02-0.05 rad
    and more downward pitch, cool "modern" concrete / glass textures with darker asphalt, weak
    sun from the right and high ambient (0.6-0.75), lower exposure and gamma 1.2 (flat contrast),
    grey sky, 10-14 cars, 5-8 poles and 0-2 trees per 100 m per side.
    """
    if domain not in DOMAINS:
        raise InputError(f"unknown synthetic domain {domain!r}; expected one of {DOMAINS}")
    rng = np.random.default_rng([int(seed), 0 if domain == "A" else 1, 7])
    u = rng.uniform
    if domain == "A":
        street = u(10.0, 14.0)
        lo_h = u(7.0, 10.0)
        sun = np.array([u(-0.6, -0.25), u(-0.9, -0.6), u(0.2, 0.6)])
        sun /= np.linalg.norm(sun)
        return SceneParams(
            seed=int(seed),
            domain="A",
            street_width=street,
            sidewalk_width=u(2.5, 4.0),
            kerb_height=u(0.11, 0.15),
            facade_height_range=(lo_h, lo_h + u(6.0, 10.0)),
            facade_setback_max=u(2.0, 4.0),
            block_length_range=(10.0, 30.0),
            camera_height=u(1.60, 1.70),
            focal_scale=u(0.56, 0.60),
            cx_frac=0.4908,
            cy_frac=0.4609,
            speed=u(0.6, 1.3),
            yaw_amplitude=u(0.005, 0.03),
            yaw_period=u(90.0, 160.0),
            yaw_jitter=u(0.001, 0.004),
            pitch=u(-0.005, 0.015),
            lane_offset=street / 2 - 2.2 - u(1.4, 2.0),
            texture_style="classic",
            sun_direction=tuple(float(x) for x in sun),
            ambient=u(0.35, 0.45),
            sun_strength=1.0,
            exposure=u(1.0, 1.15),
            gamma=1.0,
            haze_distance=u(300.0, 500.0),
            haze_color=(0.75, 0.8, 0.88),
            sky_top=(0.35, 0.55, 0.85),
            sky_horizon=(0.78, 0.85, 0.93),
            num_cars=int(rng.integers(6, 11)),
            num_poles=int(rng.integers(3, 6)),
            num_trees=int(rng.integers(3, 7)),
        )
    street = u(7.5, 9.5)
    lo_h = u(15.0, 20.0)
    sun = np.array([u(0.3, 0.7), u(-0.5, -0.3), u(-0.2, 0.4)])
    sun /= np.linalg.norm(sun)
    return SceneParams(
        seed=int(seed),
        domain="B",
        street_width=street,
        sidewalk_width=u(1.8, 2.8),
        kerb_height=u(0.15, 0.18),
        facade_height_range=(lo_h, lo_h + u(10.0, 15.0)),
        facade_setback_max=u(0.5, 1.5),
        block_length_range=(15.0, 40.0),
        camera_height=u(1.35, 1.50),
        focal_scale=u(0.45, 0.50),
        cx_frac=0.5,
        cy_frac=0.5,
        speed=u(0.6, 1.1),
        yaw_amplitude=u(0.02, 0.05),
        yaw_period=u(60.0, 100.0),
        yaw_jitter=u(0.003, 0.008),
        pitch=u(0.01, 0.03),
        lane_offset=street / 2 - 2.2 - u(0.9, 1.2),
        texture_style="modern",
        sun_direction=tuple(float(x) for x in sun),
        ambient=u(0.6, 0.75),
        sun_strength=0.7,
        exposure=u(0.8, 0.95),
        gamma=1.2,
        haze_distance=u(180.0, 260.0),
        haze_color=(0.68, 0.7, 0.72),
        sky_top=(0.6, 0.63, 0.67),
        sky_horizon=(0.8, 0.81, 0.82),
        num_cars=int(rng.integers(10, 15)),
        num_poles=int(rng.integers(5, 9)),
        num_trees=int(rng.integers(0, 3)),
    )


# ---------------------------------------------------------------------------------------------
# Textures (world-anchored, seamless, multi-scale)
# ---------------------------------------------------------------------------------------------


def _upsample_wrapped(img: np.ndarray, size: int, interp: int) -> np.ndarray:
    """Periodic upsampling of a square periodic image to ``size`` (pixel-centre aligned)."""
    f = img.shape[0] / size
    M = np.array([[f, 0, 0.5 * f - 0.5], [0, f, 0.5 * f - 0.5]])
    flags = interp | cv2.WARP_INVERSE_MAP
    out = cv2.warpAffine(img, M, (size, size), flags=flags, borderMode=cv2.BORDER_WRAP)
    return out.reshape(size, size, -1)


def _value_noise(rng: np.random.Generator, size: int, cells: int, channels: int = 1) -> np.ndarray:
    """Seamless (periodic) value noise in [0, 1]: a random cells x cells grid, cubic-upsampled."""
    g = rng.random((cells, cells, channels), dtype=np.float32)
    return _upsample_wrapped(g if channels > 1 else g[:, :, 0], size, cv2.INTER_CUBIC)


def _fbm(
    rng: np.random.Generator,
    size: int,
    base_cells: int = 4,
    max_cells: int | None = None,
    persistence: float = 0.65,
    channels: int = 1,
) -> np.ndarray:
    """Multi-scale (fractal) seamless noise, zero mean, unit standard deviation.

    Octaves with cells of 16 texels or more are summed at a quarter of the resolution and
    upsampled once (they are smooth at that scale anyway).
    """
    max_cells = max_cells or size // 2
    low_size = max(size // 4, 1)
    low = np.zeros((low_size, low_size, channels), np.float32)
    out = np.zeros((size, size, channels), np.float32)
    amp, cells = 1.0, base_cells
    while cells <= max_cells:
        if size // cells >= 16:
            low += amp * (_value_noise(rng, low_size, cells, channels) - 0.5)
        else:
            out += amp * (_value_noise(rng, size, cells, channels) - 0.5)
        amp *= persistence
        cells *= 2
    low2 = low if channels > 1 else low[:, :, 0]
    out += _upsample_wrapped(low2, size, cv2.INTER_LINEAR)
    out -= out.mean()
    out /= out.std() + 1e-6
    return out if channels > 1 else out[:, :, 0]


def _wrapped(size: int):
    """Offsets to draw a shape 9 times so that textures wrap seamlessly."""
    return [(dx * size, dy * size) for dx in (-1, 0, 1) for dy in (-1, 0, 1)]


def _draw_blobs(img, rng, n, rmin, rmax, values, aa=True):
    """Random filled circles / ellipses with values drawn from ``values(rng)`` (wrapped)."""
    size = img.shape[0]
    lt = cv2.LINE_AA if aa else cv2.LINE_8
    for _ in range(n):
        c = rng.uniform(0, size, 2)
        ax = rng.uniform(rmin, rmax, 2)
        ang = rng.uniform(0, 180)
        val = values(rng)
        for dx, dy in _wrapped(size):
            cen = (int(c[0] + dx), int(c[1] + dy))
            cv2.ellipse(img, cen, (int(ax[0]), int(ax[1])), ang, 0, 360, val, -1, lt)


def _draw_lines(img, rng, n, lmin, lmax, thick, values, segs=4):
    size = img.shape[0]
    for _ in range(n):
        p = rng.uniform(0, size, 2)
        ang = rng.uniform(0, 2 * np.pi)
        pts = [p.copy()]
        for _ in range(segs):
            ang += rng.normal(0, 0.6)
            p = p + rng.uniform(lmin, lmax) / segs * np.array([np.cos(ang), np.sin(ang)])
            pts.append(p.copy())
        val = values(rng)
        t = int(rng.integers(thick[0], thick[1] + 1))
        for dx, dy in _wrapped(size):
            q = np.array([[x + dx, y + dy] for x, y in pts], np.int32)
            cv2.polylines(img, [q], False, val, t, cv2.LINE_AA)


def _cell_random(rng, ids: np.ndarray, n: int, channels: int = 1) -> np.ndarray:
    table = rng.random((n, channels), dtype=np.float32)
    return table[ids % n]


def _to_u8(img: np.ndarray) -> np.ndarray:
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    return np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)


def _tex_road(rng, style: str) -> np.ndarray:
    s = 1024  # 64 texels / m, 16 m tile
    base = 0.40 if style == "classic" else 0.31
    img = base * (1 + 0.2 * _fbm(rng, s, 4, 512)) + 0.09 * _fbm(rng, s, 64, 512, 0.9)
    layer = np.zeros((s, s), np.float32)
    # repairs / patches (darker or lighter polygons), stains, cracks, aggregate speckles
    for _ in range(45):
        c = rng.uniform(0, s, 2)
        w, h = rng.uniform(15, 200, 2)
        ang = rng.uniform(0, 180)
        box = cv2.boxPoints(((float(c[0]), float(c[1])), (float(w), float(h)), float(ang)))
        val = float(rng.choice([-1, 1]) * rng.uniform(0.05, 0.14))
        for dx, dy in _wrapped(s):
            cv2.fillPoly(layer, [(box + (dx, dy)).astype(np.int32)], val, cv2.LINE_AA)
    _draw_blobs(layer, rng, 220, 4, 45, lambda r: float(r.uniform(-0.16, 0.1)))
    _draw_lines(layer, rng, 90, 40, 300, (1, 4), lambda r: float(-r.uniform(0.1, 0.22)))
    _draw_blobs(layer, rng, 4000, 1, 4, lambda r: float(r.uniform(-0.14, 0.18)), aa=False)
    img = img + cv2.GaussianBlur(layer, (0, 0), 0.7)
    tint = np.array([1.0, 1.0, 1.03] if style == "classic" else [0.98, 1.0, 1.04], np.float32)
    return _to_u8(img[:, :, None] * tint)


def _tex_sidewalk(rng, style: str) -> np.ndarray:
    s = 1024  # 64 texels / m, 16 m tile
    yy, xx = np.indices((s, s))
    if style == "classic":  # 0.5 m square slabs
        tw, th, shift = 32, 32, 0
        base = np.array([0.62, 0.6, 0.56], np.float32)
    else:  # 0.25 x 0.5 m bricks in running bond
        tw, th, shift = 32, 16, 16
        base = np.array([0.5, 0.5, 0.52], np.float32)
    row = yy // th
    xs = xx + (row % 2) * shift
    col = xs // tw
    ids = (row * 977 + col * 131) % 100003
    jit = _cell_random(rng, ids, 4096)[:, :, 0] - 0.5
    groutx = (xs % tw) < 2
    grouty = (yy % th) < 2
    img = base[None, None, :] * (1 + 0.25 * jit[:, :, None])
    img = img * (1 + 0.14 * _fbm(rng, s, 8, 512)[:, :, None])
    img[groutx | grouty] *= 0.55
    layer = np.zeros((s, s), np.float32)
    _draw_blobs(layer, rng, 90, 3, 30, lambda r: float(r.uniform(-0.15, 0.05)))
    _draw_blobs(layer, rng, 600, 1, 6, lambda r: float(r.uniform(-0.2, 0.12)))
    _draw_lines(layer, rng, 20, 30, 120, (1, 2), lambda r: float(-r.uniform(0.1, 0.2)))
    img = img + cv2.GaussianBlur(layer, (0, 0), 0.8)[:, :, None]
    return _to_u8(img)


def _tex_kerb(rng, style: str) -> np.ndarray:
    s = 512  # 128 texels / m, 4 m tile, 1 m stones
    base = 0.7 if style == "classic" else 0.58
    img = base * (1 + 0.12 * _fbm(rng, s, 8, 256))
    xx = np.indices((s, s))[1]
    img[(xx % 128) < 3] *= 0.5
    ids = xx // 128
    img *= 0.9 + 0.2 * _cell_random(rng, ids, 16)[:, :, 0]
    layer = np.zeros((s, s), np.float32)
    _draw_blobs(layer, rng, 120, 2, 12, lambda r: float(r.uniform(-0.2, 0.1)))
    return _to_u8(img + layer)


_PALETTES = {
    "classic": [
        (0.86, 0.78, 0.62),
        (0.80, 0.62, 0.48),
        (0.92, 0.88, 0.78),
        (0.72, 0.74, 0.66),
        (0.84, 0.70, 0.55),
        (0.70, 0.45, 0.35),
        (0.88, 0.84, 0.70),
    ],
    "modern": [
        (0.62, 0.64, 0.66),
        (0.55, 0.58, 0.62),
        (0.70, 0.70, 0.68),
        (0.45, 0.48, 0.52),
        (0.66, 0.62, 0.58),
        (0.52, 0.56, 0.60),
    ],
}


def _tex_facade(rng, style: str, variant: int) -> np.ndarray:
    """Facade texture: 16 m x 16 m at 64 texels / m, with a window grid of whole floors."""
    s = 1024
    yy, xx = np.indices((s, s))
    brick = style == "classic" and variant in (1, 3)
    if brick:  # 0.25 x 0.125 m bricks, running bond, per-brick colour
        row = yy // 8
        xs = xx + (row % 2) * 8
        ids = (row * 613 + (xs // 16) * 37) % 100003
        jit = _cell_random(rng, ids, 8192, 3) - 0.5
        img = 0.85 + 0.3 * jit
        img[((xs % 16) < 2) | ((yy % 8) < 1)] = 1.15
    elif style == "modern" and variant in (0, 2):  # concrete panels 2 m x 1.6 m
        ids = ((yy // 102) * 41 + (xx // 128) * 7) % 10007
        img = 0.9 + 0.2 * (_cell_random(rng, ids, 1024) - 0.5)
        img = np.repeat(img, 3, axis=2)
        img[((xx % 128) < 3) | ((yy % 102) < 3)] *= 0.82
    else:  # plaster
        img = np.ones((s, s, 3), np.float32)
    img = img * (1 + 0.08 * _fbm(rng, s, 4, 512)[:, :, None])
    stains = np.zeros((s, s), np.float32)
    _draw_blobs(stains, rng, 90, 6, 60, lambda r: float(r.uniform(-0.14, 0.08)))
    _draw_blobs(stains, rng, 500, 2, 14, lambda r: float(r.uniform(-0.2, 0.15)))
    _draw_lines(stains, rng, 60, 30, 300, (1, 3), lambda r: float(r.uniform(-0.2, 0.1)))
    for _ in range(120):  # rain streaks: vertical, of random length and darkness
        x, y = rng.uniform(0, s, 2)
        ln, wd = rng.uniform(20, 200), int(rng.integers(2, 9))
        val = float(-rng.uniform(0.05, 0.2))
        for dx, dy in _wrapped(s):
            p0 = (int(x + dx), int(y + dy))
            cv2.line(stains, p0, (p0[0] + int(wd // 3), int(p0[1] + ln)), val, wd)
    img = img + cv2.GaussianBlur(stains, (0, 0), 1.0)[:, :, None]

    floors = 5  # 3.2 m floors
    cols = int(rng.choice([5, 6, 8])) if style == "classic" else int(rng.choice([4, 8]))
    fh, cw = s / floors, s / cols
    if style == "classic":
        ww, wh = cw * rng.uniform(0.35, 0.5), fh * rng.uniform(0.4, 0.55)
    else:
        ww, wh = cw * rng.uniform(0.6, 0.85), fh * rng.uniform(0.55, 0.75)
    frame_col = np.array(rng.choice([0.95, 0.3, 0.75]) * np.ones(3), np.float32)
    glass_mask = np.zeros((s, s), np.float32)
    for fi in range(floors):
        for ci in range(cols):
            if rng.random() < 0.06:
                continue  # a blind window position
            x0 = ci * cw + (cw - ww) / 2
            y0 = fi * fh + fh * 0.25
            x1, y1 = x0 + ww, y0 + wh
            glass = np.array([0.18, 0.22, 0.28]) + rng.uniform(-0.06, 0.12, 3)
            if rng.random() < 0.4:  # curtains / lit room: a distinct colour per window
                glass = rng.uniform(0.3, 0.85, 3) * np.array([1.0, 0.9, 0.75])
            fr = int(rng.integers(3, 7))
            rx = rng.uniform(0.1, 0.8) * ww
            mullion = rng.random() < 0.7
            for dx, dy in _wrapped(s):
                p0 = (int(x0 + dx) - fr, int(y0 + dy) - fr)
                p1 = (int(x1 + dx) + fr, int(y1 + dy) + fr)
                cv2.rectangle(img, p0, p1, frame_col.tolist(), -1)
                g0 = (int(x0 + dx), int(y0 + dy))
                g1 = (int(x1 + dx), int(y1 + dy))
                cv2.rectangle(img, g0, g1, glass.tolist(), -1)
                cv2.rectangle(glass_mask, g0, g1, 1.0, -1)
                # reflection streak and a mullion, different per window
                r0 = int(x0 + dx + rx)
                cv2.line(img, (r0, g0[1]), (r0 - int(0.3 * ww), g1[1]), (glass * 1.6).tolist(), 3)
                if mullion:
                    mx = int(x0 + dx + ww / 2)
                    cv2.line(img, (mx, g0[1]), (mx, g1[1]), frame_col.tolist(), 2)
                if style == "classic":  # sill
                    cv2.rectangle(img, (p0[0] - 4, p1[1]), (p1[0] + 4, p1[1] + 6), (1.1,) * 3, -1)
    # what is seen in / reflected by each pane: a different random pattern in every window
    refl = 1 + 0.25 * _fbm(rng, s, 16, 512)
    blobs = np.zeros((s, s), np.float32)
    _draw_blobs(blobs, rng, 700, 3, 22, lambda r: float(r.uniform(-0.5, 0.6)))
    refl = np.clip(refl + cv2.GaussianBlur(blobs, (0, 0), 1.0), 0.3, 2.0)
    img *= (1 + glass_mask * (refl - 1))[:, :, None]
    # floor bands / cornices
    for fi in range(floors):
        y = int(fi * fh)
        img[y : y + (6 if style == "classic" else 10)] *= 0.8 if style == "classic" else 0.7
    return _to_u8(np.clip(img, 0, 1.3) / 1.3 * 1.15), cols


def _tex_car(rng) -> np.ndarray:
    s = 512  # 100 texels / m
    img = 0.85 + 0.04 * _fbm(rng, s, 4, 256)
    layer = np.zeros((s, s), np.float32)
    _draw_lines(layer, rng, 30, 60, 300, (1, 2), lambda r: float(-r.uniform(0.3, 0.5)), segs=1)
    _draw_blobs(layer, rng, 40, 3, 25, lambda r: float(r.uniform(-0.4, 0.15)))
    img = img + layer
    img = np.repeat(img[:, :, None], 3, axis=2)
    for _ in range(25):  # stickers, lights, badges
        c = rng.uniform(0, s, 2)
        wh = rng.uniform(6, 40, 2)
        col = rng.uniform(0, 1.2, 3).tolist()
        for dx, dy in _wrapped(s):
            p0 = (int(c[0] + dx), int(c[1] + dy))
            cv2.rectangle(img, p0, (int(p0[0] + wh[0]), int(p0[1] + wh[1])), col, -1)
    return _to_u8(np.clip(img, 0, 1))


def _tex_glass(rng) -> np.ndarray:
    s = 256
    img = 0.2 + 0.05 * _fbm(rng, s, 4, 128, channels=3) + np.array([0.0, 0.02, 0.06])
    layer = np.zeros((s, s, 3), np.float32)
    _draw_blobs(
        layer,
        rng,
        60,
        3,
        25,
        lambda r: (
            r.uniform(0.05, 0.3) * np.array([1, 1.05, 1.15]) + r.uniform(-0.04, 0.04, 3)
        ).tolist(),
    )
    return _to_u8(img + cv2.GaussianBlur(layer, (0, 0), 1.0))


def _tex_dark(rng) -> np.ndarray:
    s = 256
    img = 0.1 + 0.04 * _fbm(rng, s, 4, 128)
    layer = np.zeros((s, s), np.float32)
    _draw_blobs(layer, rng, 40, 3, 20, lambda r: float(r.uniform(0.0, 0.15)))
    return _to_u8(img + layer)


def _tex_metal(rng) -> np.ndarray:
    s = 256
    n = cv2.resize(_fbm(rng, s, 4, 128), (s, s))
    streak = cv2.resize(
        rng.random((1, 32), dtype=np.float32), (s, s), interpolation=cv2.INTER_CUBIC
    )
    img = 0.55 + 0.08 * n + 0.15 * (streak - 0.5)
    layer = np.zeros((s, s), np.float32)
    _draw_blobs(layer, rng, 25, 2, 12, lambda r: float(r.uniform(-0.3, 0.2)))
    return _to_u8(img + layer)


def _tex_bark(rng) -> np.ndarray:
    s = 256
    n = _value_noise(rng, s, 64)[:, :, 0]
    streaks = cv2.resize(n[:8], (s, s), interpolation=cv2.INTER_CUBIC)
    img = 0.32 + 0.25 * (streaks - 0.5) + 0.06 * _fbm(rng, s, 8, 128)
    return _to_u8(img[:, :, None] * np.array([1.0, 0.8, 0.6], np.float32))


def _tex_foliage(rng, style: str) -> np.ndarray:
    s = 512  # 64 texels / m
    base = np.array([0.28, 0.42, 0.18] if style == "classic" else [0.25, 0.35, 0.22], np.float32)
    img = base * (1 + 0.2 * _fbm(rng, s, 4, 256, channels=3))

    def leaf(r):
        return (base * r.uniform(0.4, 1.7) + r.uniform(-0.05, 0.05, 3)).tolist()

    _draw_blobs(img, rng, 900, 2, 14, leaf)
    _draw_blobs(
        img, rng, 250, 1, 4, lambda r: (np.array([0.06, 0.08, 0.04]) * r.uniform(0.5, 2)).tolist()
    )
    return _to_u8(img)


def _tex_sign(rng) -> np.ndarray:
    s = 256  # 256 texels / m
    img = np.ones((s, s, 3), np.float32) * rng.uniform(0.6, 1.0, 3)
    for _ in range(14):
        col = rng.uniform(0, 1, 3).tolist()
        c = rng.uniform(0, s, 2)
        r = rng.uniform(8, 40)
        kind = rng.integers(3)
        for dx, dy in _wrapped(s):
            cc = (int(c[0] + dx), int(c[1] + dy))
            if kind == 0:
                cv2.circle(img, cc, int(r), col, -1, cv2.LINE_AA)
            elif kind == 1:
                cv2.rectangle(img, cc, (int(cc[0] + r * 1.5), int(cc[1] + r * 0.4)), col, -1)
            else:
                tri = np.array([cc, (cc[0] + int(r), cc[1]), (cc[0] + int(r / 2), cc[1] + int(r))])
                cv2.fillPoly(img, [tri.astype(np.int32)], col, cv2.LINE_AA)
    return _to_u8(img)


@dataclass
class _Material:
    name: str
    pyramid: list[np.ndarray]  # level 0 = full size, each next level half
    scale: float  # texels per metre at level 0
    rotation: float = 0.0  # texture-coordinate rotation (rad), breaks visible periodicity
    # (axis, segment length, u step, v step) in metres: every segment of that length along
    # texture axis ``axis`` (0 = u, 1 = v) of each object reads the texture shifted by random
    # multiples of the steps (whole tiles / window cells, so the layout stays seamless), so that
    # a surface running along the street does not repeat with the texture's period
    shuffle: tuple[int, float, float, float] | None = None

    def __post_init__(self) -> None:
        # all levels side by side in one atlas, each with a 1-texel wrapped border so that
        # bilinear lookups wrap inside their level: one cv2.remap per level *pair* per material
        pads = [np.pad(lv, ((1, 1), (1, 1), (0, 0)), mode="wrap") for lv in self.pyramid]
        h = pads[0].shape[0]
        self.atlas = np.zeros((h, sum(pd.shape[1] for pd in pads), 3), np.uint8)
        offs, x = [], 0
        for pd in pads:
            self.atlas[: pd.shape[0], x : x + pd.shape[1]] = pd
            offs.append(x + 1)
            x += pd.shape[1]
        self.level_offset = np.array(offs, np.float32)
        self.level_size = np.array([lv.shape[0] for lv in self.pyramid], np.float32)


def _pyramid(img: np.ndarray, levels: int = 6) -> list[np.ndarray]:
    out = [np.ascontiguousarray(img)]
    for _ in range(levels - 1):
        cur = out[-1]
        if cur.shape[0] <= 8:
            break
        p = 4
        padded = np.pad(cur, ((p, p), (p, p), (0, 0)), mode="wrap")
        down = cv2.pyrDown(padded)
        out.append(np.ascontiguousarray(down[p // 2 : -p // 2, p // 2 : -p // 2]))
    return out


# material ids
ROAD, SIDEWALK, KERB, FACADE0 = 0, 1, 2, 3  # facades 3..6
CAR, GLASS, DARK, METAL, BARK, FOLIAGE, SIGN = 7, 8, 9, 10, 11, 12, 13


@functools.lru_cache(maxsize=4)
def _materials(style: str, seed: int) -> tuple[_Material, ...]:
    rng = np.random.default_rng([int(seed), 99, 0 if style == "classic" else 1])
    mats = [
        _Material("road", _pyramid(_tex_road(rng, style)), 64.0, 0.3),
        _Material("sidewalk", _pyramid(_tex_sidewalk(rng, style)), 64.0, 0.0, (1, 4.0, 0.5, 0.5)),
        _Material("kerb", _pyramid(_tex_kerb(rng, style)), 128.0, 0.0, (0, 4.0, 1.0, 0.5)),
    ]
    for v in range(4):
        tex, cols = _tex_facade(rng, style, v)
        mats.append(_Material(f"facade{v}", _pyramid(tex), 64.0, 0.0, (0, 16.0, 16.0 / cols, 3.2)))
    mats += [
        _Material("car", _pyramid(_tex_car(rng)), 100.0),
        _Material("glass", _pyramid(_tex_glass(rng)), 100.0),
        _Material("dark", _pyramid(_tex_dark(rng)), 100.0),
        _Material("metal", _pyramid(_tex_metal(rng)), 200.0),
        _Material("bark", _pyramid(_tex_bark(rng)), 128.0),
        _Material("foliage", _pyramid(_tex_foliage(rng, style)), 64.0),
        _Material("sign", _pyramid(_tex_sign(rng)), 256.0),
    ]
    return tuple(mats)


# ---------------------------------------------------------------------------------------------
# Scene geometry
# ---------------------------------------------------------------------------------------------

PLANE, BOX, CYLINDER, SPHERE = 0, 1, 2, 3
CAR_COLOURS = np.array(
    [
        [0.95, 0.95, 0.95],
        [0.7, 0.72, 0.75],
        [0.15, 0.15, 0.17],
        [0.75, 0.12, 0.1],
        [0.15, 0.25, 0.6],
        [0.2, 0.4, 0.25],
        [0.85, 0.75, 0.2],
        [0.45, 0.45, 0.47],
    ],
    np.float32,
)


@dataclass
class _Scene:
    params: SceneParams
    materials: tuple[_Material, ...]
    kind: np.ndarray  # (M,) int
    material: np.ndarray  # (M,) int
    tint: np.ndarray  # (M, 3) float32
    offset: np.ndarray  # (M, 2) texture offsets in metres
    lo: np.ndarray  # (M, 3) AABB
    hi: np.ndarray  # (M, 3)
    centre: np.ndarray  # (M, 3) cylinder / sphere centre
    radius: np.ndarray  # (M,)

    def __post_init__(self) -> None:
        self.lo32, self.hi32 = self.lo.astype(np.float32), self.hi.astype(np.float32)
        self.centre32 = self.centre.astype(np.float32)
        self.radius32 = self.radius.astype(np.float32)


class _Builder:
    def __init__(self) -> None:
        self.rows: list[tuple] = []

    def add(self, kind, material, tint, offset, lo, hi, centre=(0, 0, 0), radius=0.0):
        self.rows.append((kind, material, tint, offset, lo, hi, centre, radius))

    def box(self, material, lo, hi, tint=(1, 1, 1), offset=(0, 0)):
        self.add(BOX, material, tint, offset, lo, hi)

    def cylinder(self, material, x, z, r, y_top, y_bottom, tint=(1, 1, 1), offset=(0, 0)):
        self.add(
            CYLINDER,
            material,
            tint,
            offset,
            (x - r, y_top, z - r),
            (x + r, y_bottom, z + r),
            (x, 0.0, z),
            r,
        )

    def sphere(self, material, c, r, tint=(1, 1, 1), offset=(0, 0)):
        c = np.asarray(c, float)
        self.add(SPHERE, material, tint, offset, c - r, c + r, c, r)


def _build_scene(params: SceneParams, z_min: float, z_max: float) -> _Scene:
    """Procedural objects along ``z in [z_min, z_max]``; one RNG stream per category and side so
    that a longer scene extends a shorter one with the same seed."""
    p = params
    mats = _materials(p.texture_style, p.seed)
    b = _Builder()
    # ground "objects" (ids 0, 1, 2): road, sidewalk, kerb faces
    b.add(PLANE, ROAD, (1, 1, 1), (0, 0), (0, 0, 0), (0, 0, 0))
    b.add(PLANE, SIDEWALK, (1, 1, 1), (0, 0), (0, 0, 0), (0, 0, 0))
    b.add(PLANE, KERB, (1, 1, 1), (0, 0), (0, 0, 0), (0, 0, 0))
    hw, sw, kh = p.street_width / 2, p.sidewalk_width, p.kerb_height
    palette = np.array(_PALETTES[p.texture_style], np.float32)
    # a fixed grid, so that the objects do not depend on z_min within a 50 m cell
    start = math.floor(z_min / 50.0) * 50.0 - 50.0

    def stream(cat, side):
        return np.random.default_rng([p.seed, 1000 + cat, 0 if side < 0 else 1, int(start) + 10**6])

    for side in (-1, 1):
        # front row of buildings
        r = stream(0, side)
        z = start
        while z < z_max:
            length = r.uniform(*p.block_length_range)
            gap = r.choice([0.0, r.uniform(0.3, 2.0), r.uniform(3.0, 7.0)], p=[0.45, 0.35, 0.2])
            setback = r.uniform(0, p.facade_setback_max)
            height = r.uniform(*p.facade_height_range)
            x_in = hw + sw + setback
            lo = (x_in if side > 0 else -x_in - 12.0, -height, z)
            hi = (x_in + 12.0 if side > 0 else -x_in, -kh, z + length)
            tint = palette[r.integers(len(palette))] * r.uniform(0.85, 1.1)
            b.box(FACADE0 + int(r.integers(4)), lo, hi, tint, r.uniform(0, 16, 2))
            z += length + gap
        # back row (seen through the gaps), taller
        r = stream(1, side)
        z = start
        while z < z_max:
            length = r.uniform(15, 45)
            x_in = hw + sw + p.facade_setback_max + r.uniform(12, 25)
            height = r.uniform(p.facade_height_range[0] + 4, p.facade_height_range[1] + 12)
            lo = (x_in if side > 0 else -x_in - 15.0, -height, z)
            hi = (x_in + 15.0 if side > 0 else -x_in, -kh, z + length)
            tint = palette[r.integers(len(palette))] * r.uniform(0.7, 0.95)
            b.box(FACADE0 + int(r.integers(4)), lo, hi, tint, r.uniform(0, 16, 2))
            z += length + r.uniform(0, 4)
        # parked cars in the parking lane along the kerb
        r = stream(2, side)
        z = start + r.uniform(0, 10)
        mean_gap = 100.0 / max(p.num_cars, 1)
        while z < z_max:
            length, width = r.uniform(3.8, 4.9), r.uniform(1.65, 1.9)
            if p.num_cars > 0:
                x_out = hw - r.uniform(0.15, 0.4)
                x0, x1 = (x_out - width, x_out) if side > 0 else (-x_out, -x_out + width)
                col = CAR_COLOURS[r.integers(len(CAR_COLOURS))] * r.uniform(0.85, 1.05)
                off = r.uniform(0, 5, 2)
                b.box(DARK, (x0 + 0.1, -0.35, z + 0.5), (x1 - 0.1, 0.0, z + length - 0.5))
                b.box(CAR, (x0, -1.0 - r.uniform(0, 0.1), z), (x1, -0.3, z + length), col, off)
                cz0 = z + r.uniform(0.8, 1.4)
                b.box(
                    GLASS,
                    (x0 + 0.12, -1.45 - r.uniform(0, 0.2), cz0),
                    (x1 - 0.12, -0.98, z + length - r.uniform(0.7, 1.3)),
                    (1, 1, 1),
                    off,
                )
            z += length + max(0.5, r.exponential(mean_gap - 4.3))
        # poles (street lights / sign posts) near the kerb
        r = stream(3, side)
        z = start + r.uniform(0, 20)
        while z < z_max and p.num_poles > 0:
            x = side * (hw + r.uniform(0.3, 0.7))
            rad = r.uniform(0.05, 0.12)
            top = -r.uniform(3.0, 8.0)
            b.cylinder(METAL, x, z, rad, top, -kh, r.uniform(0.7, 1.1, 3), r.uniform(0, 2, 2))
            if r.random() < 0.5:  # sign board facing the traffic
                w = r.uniform(0.5, 0.9)
                y0 = top + r.uniform(0.2, 1.0)
                b.box(
                    SIGN,
                    (x - w / 2, y0, z - rad - 0.04),
                    (x + w / 2, y0 + w, z - rad),
                    (1, 1, 1),
                    r.uniform(0, 1, 2),
                )
            z += r.uniform(0.4, 1.6) * 100.0 / p.num_poles
        # trees on the sidewalk
        r = stream(4, side)
        z = start + r.uniform(0, 20)
        while z < z_max and p.num_trees > 0:
            x = side * (hw + sw * r.uniform(0.45, 0.75))
            trunk_h = r.uniform(2.2, 3.5)
            crown = r.uniform(1.3, 2.4)
            b.cylinder(
                BARK,
                x,
                z,
                r.uniform(0.1, 0.2),
                -trunk_h - crown * 0.5,
                -kh,
                (1, 1, 1),
                r.uniform(0, 2, 2),
            )
            tint = np.array([1, 1, 1]) * r.uniform(0.8, 1.2) + r.uniform(-0.1, 0.1, 3)
            b.sphere(FOLIAGE, (x, -trunk_h - crown * 0.8, z), crown, tint, r.uniform(0, 8, 2))
            z += r.uniform(0.4, 1.6) * 100.0 / p.num_trees

    rows = b.rows
    return _Scene(
        params=p,
        materials=mats,
        kind=np.array([x[0] for x in rows], np.int32),
        material=np.array([x[1] for x in rows], np.int32),
        tint=np.array([x[2] for x in rows], np.float32),
        offset=np.array([x[3] for x in rows], np.float32),
        lo=np.array([x[4] for x in rows], np.float64),
        hi=np.array([x[5] for x in rows], np.float64),
        centre=np.array([x[6] for x in rows], np.float64),
        radius=np.array([x[7] for x in rows], np.float64),
    )


# ---------------------------------------------------------------------------------------------
# Camera path
# ---------------------------------------------------------------------------------------------


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def camera_pose(params: SceneParams, z: float) -> tuple[np.ndarray, np.ndarray]:
    """World-from-camera rotation and camera centre at path position ``z`` (metres)."""
    p = params
    w = 2 * math.pi / p.yaw_period
    phase = (p.seed % 97) * 0.37
    lat_amp = p.yaw_amplitude / w
    x = p.lane_offset + lat_amp * math.sin(w * z + phase)
    heading = math.atan(p.yaw_amplitude * math.cos(w * z + phase))
    yaw = heading + p.yaw_jitter * math.sin(0.23 * z + 1.3 * phase)
    pitch = p.pitch + 0.003 * math.sin(0.41 * z + phase)
    height = p.camera_height + 0.01 * math.sin(0.7 * z + phase)
    R_wc = _rot_y(yaw) @ _rot_x(-pitch)  # positive pitch looks down (y is down)
    return R_wc, np.array([x, -height, z])


def scene_intrinsics(params: SceneParams, width: int, height: int) -> Intrinsics:
    f = params.focal_scale * width
    return Intrinsics(f, f, params.cx_frac * width, params.cy_frac * height, width, height)


# ---------------------------------------------------------------------------------------------
# Ray casting
# ---------------------------------------------------------------------------------------------

_NEAR = 0.05
_FACE_CURVED = 6
_BOX_EDGES = [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5),
              (2, 6), (3, 7)]  # fmt: skip


def _screen_rects(scene: _Scene, R_wc, C, K, W, H, max_depth):
    """Pixel rectangles ``(oid, v0, v1, u0, u1)`` of the visible objects' AABBs."""
    lo, hi = scene.lo[3:], scene.hi[3:]
    # cheap pre-cull on the distance along the street
    dz = np.maximum(lo[:, 2] - C[2], C[2] - hi[:, 2])
    cand = np.flatnonzero(dz < max_depth)
    lo, hi = lo[cand], hi[cand]
    bits = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], bool)
    corners = np.where(bits[None], hi[:, None, :], lo[:, None, :])  # (n, 8, 3)
    pc = (corners - C) @ R_wc  # camera coordinates
    z = pc[..., 2]
    zmax, zmin = z.max(1), z.min(1)
    vis = (zmax > _NEAR) & (zmin < max_depth)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = fx * pc[..., 0] / z + cx
        v = fy * pc[..., 1] / z + cy
    umin, umax, vmin, vmax = u.min(1), u.max(1), v.min(1), v.max(1)
    for k in np.flatnonzero(vis & (zmin <= _NEAR)):  # clip these boxes against the near plane
        pts = pc[k]
        keep = [pts[z[k] > _NEAR]]
        for a, bb in _BOX_EDGES:
            za, zb = z[k, a], z[k, bb]
            if (za - _NEAR) * (zb - _NEAR) < 0:
                s = (_NEAR - za) / (zb - za)
                keep.append((pts[a] + s * (pts[bb] - pts[a]))[None])
        pts = np.concatenate(keep)
        uu, vv = fx * pts[:, 0] / pts[:, 2] + cx, fy * pts[:, 1] / pts[:, 2] + cy
        umin[k], umax[k], vmin[k], vmax[k] = uu.min(), uu.max(), vv.min(), vv.max()
    vis &= (umax >= 0) & (umin < W) & (vmax >= 0) & (vmin < H)
    k = np.flatnonzero(vis)
    u0 = np.clip(np.floor(umin[k]), 0, W).astype(int)
    u1 = np.clip(np.ceil(umax[k]) + 1, 0, W).astype(int)
    v0 = np.clip(np.floor(vmin[k]), 0, H).astype(int)
    v1 = np.clip(np.ceil(vmax[k]) + 1, 0, H).astype(int)
    ok = (u0 < u1) & (v0 < v1)
    oid, near = cand[k][ok] + 3, zmin[k][ok]
    order = np.argsort(near, kind="stable")  # front to back: occluded objects get skipped
    cols = (oid, near, v0[ok], v1[ok], u0[ok], u1[ok])
    return list(zip(*(x[order].tolist() for x in cols), strict=True))


_BATCH_AREA = 3000  # objects covering at most this many pixels are ray cast in one batch


def _intersect(scene: _Scene, kind: int, oid, rays, Cx, Cy, Cz):
    """Ray / object hits for one object (scalar ``oid``) or per-pair arrays ``oid``.

    Returns ``(t, hit, face)``: depth along the ray (``D_cam`` has z = 1), validity, face code.
    """
    dx, dy, dz, ix, iy, iz = rays
    if kind == BOX:
        lo, hi = scene.lo32[oid], scene.hi32[oid]
        a, b = (lo[..., 0] - Cx) * ix, (hi[..., 0] - Cx) * ix
        txn, txf = np.minimum(a, b), np.maximum(a, b)
        a, b = (lo[..., 1] - Cy) * iy, (hi[..., 1] - Cy) * iy
        tyn, tyf = np.minimum(a, b), np.maximum(a, b)
        a, b = (lo[..., 2] - Cz) * iz, (hi[..., 2] - Cz) * iz
        tzn, tzf = np.minimum(a, b), np.maximum(a, b)
        tn = np.maximum(np.maximum(txn, tyn), tzn)
        tf = np.minimum(np.minimum(txf, tyf), tzf)
        hit = (tn <= tf) & (tn > _NEAR)
        ax = np.where((txn >= tyn) & (txn >= tzn), 0, np.where(tyn >= tzn, 1, 2))
        d_ax = np.where(ax == 0, dx, np.where(ax == 1, dy, dz))
        face = (2 * ax + (d_ax < 0)).astype(np.int8)  # a ray going +x enters the -x face
        return tn, hit, face
    c = scene.centre32[oid]
    r2 = scene.radius32[oid] ** 2
    ox, oy, oz = Cx - c[..., 0], Cy - c[..., 1], Cz - c[..., 2]
    if kind == CYLINDER:
        a = dx * dx + dz * dz
        bh = dx * ox + dz * oz
        cc = ox * ox + oz * oz - r2
    else:
        a = dx * dx + dy * dy + dz * dz
        bh = dx * ox + dy * oy + dz * oz
        cc = ox * ox + oy * oy + oz * oz - r2
    disc = bh * bh - a * cc
    with np.errstate(invalid="ignore"):
        t = (-bh - np.sqrt(disc)) / a
    hit = (disc > 0) & (t > _NEAR)
    if kind == CYLINDER:
        y = Cy + t * dy
        hit &= (y >= scene.lo32[oid, 1]) & (y <= scene.hi32[oid, 1])
    return t, hit, np.int8(_FACE_CURVED)


def _cast_batch(scene: _Scene, rects: np.ndarray, rays, C, T, OID, FACE) -> None:
    """Ray cast many small objects at once: (object, pixel) pairs, then a scatter-min."""
    W = T.shape[1]
    Tf, Of, Ff = T.ravel(), OID.ravel(), FACE.ravel()
    oid = rects[:, 0].astype(np.int64)
    v0, v1, u0, u1 = (rects[:, k].astype(np.int64) for k in (2, 3, 4, 5))
    kinds = scene.kind[oid]
    found = []
    for kind in (BOX, CYLINDER, SPHERE):
        sel = np.flatnonzero(kinds == kind)
        if sel.size == 0:
            continue
        w, h = u1[sel] - u0[sel], v1[sel] - v0[sel]
        area = w * h
        rep = np.repeat(np.arange(sel.size), area)
        local = np.arange(rep.size) - np.repeat(np.cumsum(area) - area, area)
        wr = w[rep]
        pix = (v0[sel][rep] + local // wr) * W + u0[sel][rep] + local % wr
        o = oid[sel][rep]
        pr = [r.ravel()[pix] for r in rays]
        t, hit, face = _intersect(scene, kind, o, pr, *C)
        hit &= t < Tf[pix]
        face = (
            face[hit]
            if isinstance(face, np.ndarray) and face.ndim
            else np.full(int(hit.sum()), face, np.int8)
        )
        found.append((pix[hit], t[hit], o[hit], face))
    if not found:
        return
    pix, t, o, face = (np.concatenate(x) for x in zip(*found, strict=True))
    np.minimum.at(Tf, pix, t)
    win = t == Tf[pix]
    Of[pix[win]] = o[win]
    Ff[pix[win]] = face[win]


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
        t_road = np.where(down, -Cy * iDy, np.inf)
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


def _shade(scene, intr, T, OID, FACE, hitm, Dx, Dy, Dz, C):
    p = scene.params
    H, W = T.shape
    f32 = np.float32
    dnorm = np.sqrt(Dx * Dx + Dy * Dy + Dz * Dz)
    # sky: vertical gradient on the ray elevation (at infinity: rotation-consistent)
    elev = np.clip(-Dy / dnorm * 4.0, 0, 1)[..., None]
    img = (1 - elev) * np.array(p.sky_horizon, f32) + elev * np.array(p.sky_top, f32)
    img = img.astype(f32)

    idx = np.flatnonzero(hitm)
    if idx.size == 0:
        return img
    t = T.ravel()[idx]
    dx, dy, dz = Dx.ravel()[idx], Dy.ravel()[idx], Dz.ravel()[idx]
    Cf = np.asarray(C, f32)
    px, py, pz = Cf[0] + t * dx, Cf[1] + t * dy, Cf[2] + t * dz
    oid = OID.ravel()[idx]
    face = FACE.ravel()[idx]
    # normals
    nx = np.zeros_like(t)
    ny = np.zeros_like(t)
    nz = np.zeros_like(t)
    sgn = np.where(face % 2 == 0, f32(-1), f32(1))  # even: ray went +axis, normal -axis
    ax = face // 2
    nx[ax == 0] = sgn[ax == 0]
    ny[ax == 1] = sgn[ax == 1]
    nz[ax == 2] = sgn[ax == 2]
    u = np.where(ax == 0, pz, px)
    v = np.where(ax == 1, pz, py)
    curved = face == _FACE_CURVED
    if curved.any():
        o = oid[curved]
        cen = scene.centre[o].astype(f32)
        rad = scene.radius[o].astype(f32)
        qx, qz = px[curved] - cen[:, 0], pz[curved] - cen[:, 2]
        is_cyl = scene.kind[o] == CYLINDER
        qy = np.where(is_cyl, 0, py[curved] - cen[:, 1])
        n = np.sqrt(qx * qx + qy * qy + qz * qz) + 1e-9
        nx[curved], ny[curved], nz[curved] = qx / n, qy / n, qz / n
        u[curved] = np.arctan2(qx, qz) * rad
        v[curved] = np.where(is_cyl, py[curved], np.arcsin(np.clip(qy / n, -1, 1)) * rad)
    # Lambert + ambient
    sun = np.asarray(p.sun_direction, f32)
    lam = np.maximum(nx * sun[0] + ny * sun[1] + nz * sun[2], 0)
    shade = p.ambient + (1 - p.ambient) * p.sun_strength * lam
    # texture lookups with trilinear mip-mapping
    mat = scene.material[oid]
    u = u + scene.offset[oid, 0]
    v = v + scene.offset[oid, 1]
    dlen = np.sqrt(dx * dx + dy * dy + dz * dz)
    rng_dist = t * dlen  # distance along the ray
    cosi = np.abs(nx * dx + ny * dy + nz * dz) / dlen
    # pixel footprint (metres): isotropic filtering between the minor and major axes of the
    # footprint ellipse, biased towards the sharp side
    foot_m = rng_dist / intr.fx / np.sqrt(np.sqrt(np.maximum(cosi, 0.02))) * np.float32(0.75)
    albedo = np.empty((idx.size, 3), f32)
    for m in np.flatnonzero(np.bincount(mat, minlength=len(scene.materials))):
        sel = np.flatnonzero(mat == m)
        mt = scene.materials[m]
        us, vs = u[sel], v[sel]
        if mt.shuffle is not None:
            us, vs = _shuffle(mt, us, vs, oid[sel])
        albedo[sel] = _sample(mt, us, vs, foot_m[sel])
    albedo *= scene.tint[oid]
    # lane markings on the road (anti-aliased over the pixel footprint)
    road = np.flatnonzero(oid == 0)
    if road.size:
        x, z, fm = px[road], pz[road], foot_m[road] + 1e-4
        hw = p.street_width / 2

        def band(d, half):
            return np.clip((half - np.abs(d)) / fm + 0.5, 0, 1)

        dash = np.clip((np.minimum(np.mod(z, 9.0), 9.0 - np.mod(z, 9.0)) - 1.5) / fm + 0.5, 0, 1)
        cover = np.maximum(band(x, 0.06) * dash, band(np.abs(x) - (hw - 2.4), 0.06))[:, None]
        paint = np.clip(0.5 + 0.9 * albedo[road], 0, 1)  # worn paint keeps the asphalt's texture
        albedo[road] = albedo[road] * (1 - cover) + paint * cover
    col = albedo * shade[:, None]
    haze = np.exp(-rng_dist / p.haze_distance)[:, None]
    col = col * haze + np.asarray(p.haze_color, f32) * (1 - haze)
    img.reshape(-1, 3)[idx] = col
    return img


def _shuffle(mat: _Material, u, v, oid):
    """Shift texture coordinates per (object, segment) by hashed multiples of the steps."""
    axis, seg_len, qu, qv = mat.shuffle
    tile = mat.pyramid[0].shape[0] / mat.scale  # metres
    seg = np.floor((u if axis == 0 else v) / seg_len).astype(np.int64)
    h = (seg * 73856093) ^ (oid.astype(np.int64) * 19349663)
    h = ((h ^ (h >> 13)) * 1274126177) & 0x7FFFFFFF
    h = h ^ (h >> 16)
    nu, nv = max(int(round(tile / qu)), 1), max(int(round(tile / qv)), 1)
    du = (h % nu).astype(np.float32) * np.float32(qu)
    dv = ((h // nu) % nv).astype(np.float32) * np.float32(qv)
    return u + du, v + dv


def _sample(mat: _Material, u, v, foot_m) -> np.ndarray:
    """Bilinear + linear-between-levels sampling of a wrapped texture pyramid; float RGB 0..1."""
    if mat.rotation:
        c, s = math.cos(mat.rotation), math.sin(mat.rotation)
        u, v = c * u + s * v, -s * u + c * v
    x0 = u * mat.scale
    y0 = v * mat.scale
    nlev = len(mat.pyramid)
    lev = np.clip(np.log2(np.maximum(foot_m * mat.scale, 1e-6)), 0, nlev - 1 - 1e-3)
    l0 = lev.astype(np.int32)
    frac = (lev - l0)[:, None]
    a = _remap_atlas(mat, x0, y0, l0)
    b = _remap_atlas(mat, x0, y0, l0 + 1)
    return (a + (b - a) * frac) * np.float32(1 / 255)


_CHUNK = 4096


def _remap_atlas(mat: _Material, x: np.ndarray, y: np.ndarray, level: np.ndarray) -> np.ndarray:
    n = x.size
    scale = np.ldexp(np.float32(1), -level).astype(np.float32)
    size = mat.level_size[level]
    chunk = min(_CHUNK, n)  # cv2.remap wants maps smaller than 32767 in each dimension
    rows = (n + chunk - 1) // chunk
    mx = np.zeros(rows * chunk, np.float32)
    my = np.zeros(rows * chunk, np.float32)
    mx[:n] = np.mod(x * scale, size) + mat.level_offset[level]
    my[:n] = np.mod(y * scale, size) + 1.0
    out = cv2.remap(
        mat.atlas,
        mx.reshape(rows, chunk),
        my.reshape(rows, chunk),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return out.reshape(-1, 3)[:n].astype(np.float32)


# ---------------------------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------------------------


@dataclass
class SyntheticSequence:
    """A rendered drive: images, exact depths and poses, shared intrinsics, 10 Hz stamps."""

    images: list[np.ndarray]  # H x W x 3 uint8 RGB
    depths: list[np.ndarray]  # H x W float32 metres, 0 = no depth (sky / beyond max_depth)
    cam_from_world: list[np.ndarray]  # 4x4 float64, x_cam = R x_world + t
    intrinsics: Intrinsics
    stamps: list[float]  # seconds, 10 Hz
    params: SceneParams

    def __len__(self) -> int:
        return len(self.images)


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
    if width < 8 or height < 8:
        raise InputError(f"image size too small: {width}x{height}")
    intr = scene_intrinsics(params, int(width), int(height))
    z_end = start_offset + (num_frames - 1) * params.speed
    scene = _build_scene(params, start_offset - 40.0, z_end + params.max_depth * 1.5 + 20.0)
    rng = np.random.default_rng([int(seed), 4242])
    images, depths, poses, stamps = [], [], [], []
    for i in range(num_frames):
        R_wc, C = camera_pose(params, start_offset + i * params.speed)
        img, depth = _render(scene, R_wc, C, intr)
        images.append(_finish(img, params, rng, blur_sigma, noise_std))
        depths.append(depth)
        T = np.eye(4)
        T[:3, :3] = R_wc.T
        T[:3, 3] = -R_wc.T @ C
        poses.append(T)
        stamps.append(float(start_stamp + i / FRAME_RATE))
    return SyntheticSequence(images, depths, poses, intr, stamps, params)


def make_sequence(
    seed: int = 0, domain: str = "A", num_frames: int = 10, width: int = 1242, height: int = 375
) -> SyntheticSequence:
    """Convenience: sample the scene of ``seed`` in ``domain`` and render ``num_frames`` frames."""
    return render_sequence(sample_scene_params(seed, domain), num_frames, width, height, seed=seed)
