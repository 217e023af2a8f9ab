"""Scene geometry: the procedural objects of a street (buildings, parked cars, poles, signs,
trees) as rows of one table (:class:`_Scene`: kind, material, tint, AABB, centre, radius),
built along a stretch of the path by :func:`_build_scene`; :func:`_with_objects` appends one
frame's extra (moving) objects to a built scene."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sfm_ttr_ros.data.synthetic.materials import (
    BARK,
    CAR,
    DARK,
    FACADE0,
    FOLIAGE,
    GLASS,
    KERB,
    METAL,
    ROAD,
    SIDEWALK,
    SIGN,
    _Material,
    _materials,
    flattened,
)
from sfm_ttr_ros.data.synthetic.scene import SceneParams
from sfm_ttr_ros.data.synthetic.textures import _PALETTES

PLANE, BOX, CYLINDER, SPHERE = 0, 1, 2, 3
_FACE_CURVED = 6  # face code of a cylinder / sphere hit (0..5: box faces)
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
    # (M, 3) texture anchor: how far a moving object has moved since its texture was laid out
    # (shading subtracts it, so the texture moves with the object); None = all static
    anchor: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.lo32, self.hi32 = self.lo.astype(np.float32), self.hi.astype(np.float32)
        self.centre32 = self.centre.astype(np.float32)
        self.radius32 = self.radius.astype(np.float32)


def _car_shape(rng: np.random.Generator) -> tuple[float, float, float, float]:
    """A car's random proportions, drawn in this order: body top (y), cabin inset at the front,
    cabin top (y), cabin inset at the back (metres)."""
    body_top = -1.0 - rng.uniform(0, 0.1)
    front = rng.uniform(0.8, 1.4)
    cabin_top = -1.45 - rng.uniform(0, 0.2)
    return body_top, front, cabin_top, rng.uniform(0.7, 1.3)


class _Builder:
    def __init__(self) -> None:
        self.rows: list[tuple] = []

    def add(self, kind, material, tint, offset, lo, hi, centre=(0, 0, 0), radius=0.0,
            anchor=(0.0, 0.0, 0.0)):
        self.rows.append((kind, material, tint, offset, lo, hi, centre, radius, anchor))

    def box(self, material, lo, hi, tint=(1, 1, 1), offset=(0, 0), anchor=(0.0, 0.0, 0.0)):
        self.add(BOX, material, tint, offset, lo, hi, anchor=anchor)

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

    def car(self, x0, x1, z0, z1, colour, offset, shape, along_x=False, height=1.0,
            anchor=(0.0, 0.0, 0.0)):
        """A car standing on the road (``y = 0``) over the footprint ``[x0, x1] x [z0, z1]``:
        dark undercarriage, body (``CAR``, tinted ``colour``) and glass cabin, three boxes.
        ``shape`` from :func:`_car_shape`; its front / back insets run along the car's length,
        which is ``z`` (parked cars) or ``x`` (``along_x``: a car crossing the street).
        ``height`` scales every y (a van: > 1)."""
        body_top, front, cabin_top, back = shape

        def inset(side, lo_len, hi_len):  # -> (x0, x1, z0, z1)
            if along_x:
                return x0 + lo_len, x1 - hi_len, z0 + side, z1 - side
            return x0 + side, x1 - side, z0 + lo_len, z1 - hi_len

        a0, a1, b0, b1 = inset(0.1, 0.5, 0.5)
        self.box(DARK, (a0, -0.35 * height, b0), (a1, 0.0, b1), anchor=anchor)
        self.box(CAR, (x0, body_top * height, z0), (x1, -0.3 * height, z1), colour, offset,
                 anchor)
        a0, a1, b0, b1 = inset(0.12, front, back)
        self.box(GLASS, (a0, cabin_top * height, b0), (a1, -0.98 * height, b1), (1, 1, 1),
                 offset, anchor)

    def arrays(self) -> dict[str, np.ndarray]:
        """The rows as :class:`_Scene`'s columns (``anchor`` only if an object has one)."""
        rows = self.rows
        cols = {
            "kind": np.array([x[0] for x in rows], np.int32),
            "material": np.array([x[1] for x in rows], np.int32),
            "tint": np.array([x[2] for x in rows], np.float32),
            "offset": np.array([x[3] for x in rows], np.float32),
            "lo": np.array([x[4] for x in rows], np.float64),
            "hi": np.array([x[5] for x in rows], np.float64),
            "centre": np.array([x[6] for x in rows], np.float64),
            "radius": np.array([x[7] for x in rows], np.float64),
        }
        anchor = np.array([x[8] for x in rows], np.float32).reshape(-1, 3)
        cols["anchor"] = anchor if anchor.any() else None
        return cols


def _with_objects(scene: _Scene, extra: _Builder) -> _Scene:
    """``scene`` plus the objects of ``extra`` (one frame's moving objects), appended after the
    scene's own (whose ids stay the same); ``scene`` itself is left untouched."""
    if not extra.rows:
        return scene
    add = extra.arrays()
    cols = {}
    for name, col in add.items():
        if name == "anchor":
            if col is None and scene.anchor is None:
                cols[name] = None
                continue
            old = scene.anchor if scene.anchor is not None else np.zeros((len(scene.kind), 3))
            col = col if col is not None else np.zeros((len(extra.rows), 3))
            cols[name] = np.concatenate([old, col]).astype(np.float32)
        else:
            cols[name] = np.concatenate([getattr(scene, name), col])
    return _Scene(params=scene.params, materials=scene.materials, **cols)


WALL_THICKNESS = 0.4  # m, domain C's stone wall
RAIL_GAUGE, RAIL_WIDTH, RAIL_HEIGHT = 1.435, 0.07, 0.06  # m, a tram track's


def bonnet(params: SceneParams, C: np.ndarray, C0: np.ndarray) -> _Builder | None:
    """The car's bonnet in front of a camera at ``C`` (a box carried with it, its texture with
    it since ``C0``, the drive's first centre): ``bonnet_length`` ahead, its top
    ``bonnet_drop`` below the camera; None when the scene has none."""
    if not params.bonnet_length:
        return None
    b = _Builder()
    top = C[1] + params.bonnet_drop
    b.box(CAR, (C[0] - 0.85, top, C[2] + 0.2), (C[0] + 0.85, top + 0.5, C[2] +
                                                   params.bonnet_length),
          (0.4, 0.41, 0.44), (0.0, 0.0), tuple(float(x) for x in C - C0))
    return b


def _road_edges(b: _Builder, p: SceneParams, z0: float, z1: float) -> None:
    """Domain C's edges over ``z in [z0, z1]``: the stone wall at the back of the right
    sidewalk, the raised track bed left of the road with its two tracks (rails on sleeper-less
    ballast: granite-like kerb stones), nothing when the scene has none."""
    hw = p.street_width / 2
    if p.wall_height:
        x = hw + p.sidewalk_width
        b.box(KERB, (x, -p.wall_height, z0), (x + WALL_THICKNESS, -p.kerb_height, z1),
              (0.8, 0.78, 0.72), (0.3, 0.0))
    if p.tram_bed_width:
        top, w = -p.tram_bed_height, p.tram_bed_width
        b.box(SIDEWALK, (-hw - w, top, z0), (-hw, 0.0, z1), (0.62, 0.6, 0.56), (1.7, 0.4))
        for centre in (-hw - w * 0.3, -hw - w * 0.7):
            for rail in (-RAIL_GAUGE / 2, RAIL_GAUGE / 2):
                x = centre + rail
                b.box(METAL, (x - RAIL_WIDTH / 2, top - RAIL_HEIGHT, z0),
                      (x + RAIL_WIDTH / 2, top, z1), (0.8, 0.8, 0.85))


def _build_scene(params: SceneParams, z_min: float, z_max: float) -> _Scene:
    """Procedural objects along ``z in [z_min, z_max]``; one RNG stream per category and side so
    that a longer scene extends a shorter one with the same seed."""
    p = params
    mats = _materials(p.texture_style, p.seed)
    mats = (flattened(mats[ROAD], p.road_contrast), *mats[ROAD + 1:])
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

    _road_edges(b, p, start, z_max)
    for side in (-1, 1):
        # front row of buildings (behind a track bed, a wall)
        edge = hw + sw + (p.tram_bed_width if side < 0 else (WALL_THICKNESS if p.wall_height
                                                             else 0.0))
        r = stream(0, side)
        z = start
        while z < z_max:
            length = r.uniform(*p.block_length_range)
            gap = r.choice([0.0, r.uniform(0.3, 2.0), r.uniform(3.0, 7.0)], p=[0.45, 0.35, 0.2])
            setback = r.uniform(0, p.facade_setback_max)
            height = r.uniform(*p.facade_height_range)
            x_in = edge + setback
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
            x_in = edge + p.facade_setback_max + r.uniform(12, 25)
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
            if p.num_cars > 0 and not (side < 0 and p.tram_bed_width):  # none on the bed
                x_out = hw - r.uniform(0.15, 0.4)
                x0, x1 = (x_out - width, x_out) if side > 0 else (-x_out, -x_out + width)
                col = CAR_COLOURS[r.integers(len(CAR_COLOURS))] * r.uniform(0.85, 1.05)
                off = r.uniform(0, 5, 2)
                b.car(x0, x1, z, z + length, col, off, _car_shape(r))
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

    return _Scene(params=p, materials=mats, **b.arrays())
