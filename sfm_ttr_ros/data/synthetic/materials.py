"""Materials: a texture's mip-map pyramid packed into one atlas, its scale in texels per
metre, and its lookup (:func:`_sample`: trilinear, wrapped; :func:`_shuffle`: per-segment
offsets that break the tile period). :func:`_materials` builds the 14 materials of a style
(cached); the material ids below index that tuple."""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from sfm_ttr_ros.data.synthetic.textures import (
    _tex_bark,
    _tex_car,
    _tex_dark,
    _tex_facade,
    _tex_foliage,
    _tex_glass,
    _tex_kerb,
    _tex_metal,
    _tex_road,
    _tex_sidewalk,
    _tex_sign,
)


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


def flattened(mat: _Material, contrast: float) -> _Material:
    """``mat`` with its texture's contrast scaled by ``contrast`` about each level's mean (plain
    asphalt: few features for SIFT); the same material when ``contrast`` is 1."""
    if contrast == 1.0:
        return mat
    levels = []
    for lv in mat.pyramid:
        f = lv.astype(np.float32)
        mean = f.mean(axis=(0, 1), keepdims=True)
        levels.append(np.clip(mean + (f - mean) * contrast + 0.5, 0, 255).astype(np.uint8))
    return dataclasses.replace(mat, pyramid=levels)


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
