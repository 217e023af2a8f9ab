"""Procedural, seamless (periodic) textures: multi-scale value noise and the per-material
images (asphalt, paving, kerb, facades with window grids, car paint, glass, metal, bark,
foliage, signs). Each ``_tex_*`` returns an H x W x 3 uint8 tile drawn from ``rng``."""

from __future__ import annotations

import cv2
import numpy as np


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
