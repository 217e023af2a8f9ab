"""Indoor rooms and corridors, seen by a hand-held or head-worn camera: the street renderer's
ray caster and shading on a scene of boxes (a closed room: floor, ceiling and four walls as
slabs; cabinets, shelves, tables, boxes, pillars standing in it), for the embedded network's
training set (scripts/train_default_model.py). Conventions as in :mod:`sfm_ttr_ros.data.synthetic`
(metres, y down, the street's ground plane at y = 0 hidden under the room's floor slab).

:func:`sample_room` draws one room from a seed; :func:`room_poses` hand-held camera poses in it
(height, yaw, pitch and roll spread, small steps between frames); :func:`render_room` renders
them with exact depth.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from sfm_ttr_ros.data.poses import rot_x, rot_y, rot_z
from sfm_ttr_ros.data.synthetic.geometry import PLANE, _Builder, _Scene
from sfm_ttr_ros.data.synthetic.materials import (
    BARK,
    CAR,
    DARK,
    FACADE0,
    GLASS,
    KERB,
    METAL,
    ROAD,
    SIDEWALK,
    _materials,
)
from sfm_ttr_ros.data.synthetic.render import SyntheticSequence, render_frames
from sfm_ttr_ros.data.synthetic.scene import SceneParams

SLAB = 0.2  # m, thickness of floor, ceiling and walls
#: materials a room's surfaces are drawn with (tinted per surface)
FLOOR_MATERIALS = (SIDEWALK, KERB, ROAD, BARK, FACADE0 + 3)
WALL_MATERIALS = (FACADE0, FACADE0 + 1, FACADE0 + 2, FACADE0 + 3, SIDEWALK, KERB)
FURNITURE_MATERIALS = (BARK, CAR, DARK, METAL, GLASS, FACADE0 + 2, KERB)
ROOM_X0 = 20.0  # the room's left wall: off the street's lane markings (x = 0)


@dataclasses.dataclass
class Room:
    """One room: its inner extent (x0..x1, z0..z1, floor y = 0, ceiling y = -height), the scene
    parameters its light and textures come from, and the furniture's footprints (for poses
    that keep clear of them)."""

    params: SceneParams
    x0: float
    x1: float
    z0: float
    z1: float
    height: float
    footprints: list[tuple[float, float, float, float]]  # (x0, x1, z0, z1)


def sample_room(seed: int) -> tuple[Room, _Builder]:
    """A room or corridor from ``seed``: 2–9 m wide, 3–25 m long, 2.4–3.4 m high, its
    surfaces textured and tinted at random, 3–14 pieces of furniture along its walls and in it
    (things on its tables, up to 5 small ones on its floor),
    indoor light (high ambient, a weak directional term)."""
    rng = np.random.default_rng([int(seed), 31337])
    corridor = rng.random() < 0.3
    width = rng.uniform(1.8, 3.0) if corridor else rng.uniform(3.0, 9.0)
    length = rng.uniform(10.0, 25.0) if corridor else rng.uniform(3.0, 12.0)
    height = rng.uniform(2.4, 3.4)
    style = "classic" if rng.random() < 0.5 else "modern"
    sun = rng.normal(size=3)
    sun[1] = -abs(sun[1])  # light from above
    params = SceneParams(
        seed=int(seed), domain="I", texture_style=style,
        sun_direction=tuple(float(v) for v in sun / np.linalg.norm(sun)),
        ambient=float(rng.uniform(0.45, 0.8)), sun_strength=float(rng.uniform(0.3, 0.9)),
        exposure=float(rng.uniform(0.8, 1.4)), gamma=float(rng.uniform(0.85, 1.2)),
        haze_distance=1e6, street_width=2 * ROOM_X0 - 4.0, max_depth=200.0)
    x0, x1, z0, z1 = ROOM_X0, ROOM_X0 + width, 0.0, length
    b = _Builder()
    for mat in (ROAD, 0, 0):  # the street's three ground rows (ids 0..2), hidden by the floor
        b.add(PLANE, mat, (1, 1, 1), (0, 0), (0, 0, 0), (0, 0, 0))

    def tint(light: bool) -> np.ndarray:
        base = rng.uniform(0.75, 1.05) if light else rng.uniform(0.35, 0.9)
        return np.clip(base + rng.uniform(-0.12, 0.12, 3), 0.1, 1.2)

    def mat_of(choices) -> int:
        return int(choices[rng.integers(len(choices))])

    e = SLAB
    b.box(mat_of(FLOOR_MATERIALS), (x0 - e, -0.01, z0 - e), (x1 + e, e, z1 + e), tint(False),
          rng.uniform(0, 8, 2))
    b.box(mat_of(WALL_MATERIALS), (x0 - e, -height - e, z0 - e), (x1 + e, -height, z1 + e),
          tint(True), rng.uniform(0, 8, 2))
    wall = mat_of(WALL_MATERIALS)
    wall_tint = tint(True)
    for lo, hi in (((x0 - e, -height, z0 - e), (x0, 0.0, z1 + e)),
                   ((x1, -height, z0 - e), (x1 + e, 0.0, z1 + e)),
                   ((x0 - e, -height, z0 - e), (x1 + e, 0.0, z0)),
                   ((x0 - e, -height, z1), (x1 + e, 0.0, z1 + e))):
        same = rng.random() < 0.7
        b.box(wall if same else mat_of(WALL_MATERIALS), lo, hi,
              wall_tint if same else tint(True), rng.uniform(0, 8, 2))
    footprints: list[tuple[float, float, float, float]] = []
    for _ in range(int(rng.integers(0, 6))):  # small things on the floor (bags, bins, boxes)
        sw, sd, sh = rng.uniform(0.15, 0.6), rng.uniform(0.15, 0.6), rng.uniform(0.1, 0.6)
        sx, sz = rng.uniform(x0, x1 - sw), rng.uniform(z0, z1 - sd)
        footprints.append((sx, sx + sw, sz, sz + sd))
        b.box(mat_of(FURNITURE_MATERIALS), (sx, -sh, sz), (sx + sw, 0.0, sz + sd), tint(False),
              rng.uniform(0, 4, 2))
    n = int(rng.integers(3, 15 if not corridor else 8))
    for _ in range(n):
        kind = rng.choice(["cabinet", "table", "box", "pillar", "shelf"],
                          p=[0.3, 0.2, 0.25, 0.1, 0.15])
        along_wall = kind in ("cabinet", "shelf") or rng.random() < 0.5
        w = rng.uniform(0.4, 2.0) if kind != "pillar" else rng.uniform(0.15, 0.4)
        d = rng.uniform(0.3, 0.9) if kind != "table" else rng.uniform(0.6, 1.4)
        h = {"cabinet": rng.uniform(0.7, 2.2), "table": rng.uniform(0.65, 0.8),
             "box": rng.uniform(0.2, 1.2), "pillar": height, "shelf": rng.uniform(1.2, 2.3)}[kind]
        if along_wall:
            side = int(rng.integers(4))
            if side < 2:  # against the left / right wall, running along z
                fz = rng.uniform(z0, max(z0, z1 - w))
                fx = x0 if side == 0 else x1 - d
                fp = (fx, fx + d, fz, fz + w)
            else:
                fx = rng.uniform(x0, max(x0, x1 - w))
                fz = z0 if side == 2 else z1 - d
                fp = (fx, fx + w, fz, fz + d)
        else:
            fx = rng.uniform(x0 + 0.3, max(x0 + 0.3, x1 - w - 0.3))
            fz = rng.uniform(z0 + 0.3, max(z0 + 0.3, z1 - d - 0.3))
            fp = (fx, fx + w, fz, fz + d)
        fx0, fx1, fz0, fz1 = (min(max(v, lo), hi) for v, lo, hi in
                              zip(fp, (x0, x0, z0, z0), (x1, x1, z1, z1), strict=True))
        if fx1 - fx0 < 0.1 or fz1 - fz0 < 0.1:
            continue
        footprints.append((fx0, fx1, fz0, fz1))
        m, t, off = mat_of(FURNITURE_MATERIALS), tint(False), rng.uniform(0, 4, 2)
        if kind == "table":
            top = 0.04
            b.box(m, (fx0, -h, fz0), (fx1, -h + top, fz1), t, off)
            leg = 0.05
            for lx, lz in ((fx0, fz0), (fx1 - leg, fz0), (fx0, fz1 - leg), (fx1 - leg, fz1 - leg)):
                b.box(METAL, (lx, -h + top, lz), (lx + leg, -0.0, lz + leg), (0.6, 0.6, 0.6))
            for _ in range(int(rng.integers(0, 5))):  # things on the table
                sw, sd, sh = rng.uniform(0.05, 0.4), rng.uniform(0.05, 0.3), rng.uniform(0.03, 0.35)
                sx = rng.uniform(fx0, max(fx0, fx1 - sw))
                sz = rng.uniform(fz0, max(fz0, fz1 - sd))
                b.box(mat_of(FURNITURE_MATERIALS), (sx, -h - sh, sz), (sx + sw, -h, sz + sd),
                      tint(False), rng.uniform(0, 4, 2))
        elif kind == "pillar" and rng.random() < 0.5:
            r = (fx1 - fx0) / 2
            b.cylinder(m, (fx0 + fx1) / 2, (fz0 + fz1) / 2, r, -h, 0.0, t, off)
        elif kind == "shelf":
            b.box(m, (fx0, -h, fz0), (fx1, 0.0, fz1), t, off)
            for k in range(1, int(h / 0.4)):  # the shelf boards' front edges, items on them
                y = -k * 0.4
                b.box(DARK, (fx0 + 0.05, y - 0.3, fz0 + 0.02), (fx1 - 0.05, y, fz1 - 0.02),
                      tint(False), rng.uniform(0, 4, 2))
        else:
            b.box(m, (fx0, -h, fz0), (fx1, 0.0, fz1), t, off)
    room = Room(params, x0, x1, z0, z1, height, footprints)
    return room, b


def room_poses(room: Room, num_frames: int, rng: np.random.Generator,
               step: float = 0.15) -> list[tuple[np.ndarray, np.ndarray]]:
    """Hand-held poses in ``room``: a start clear of the furniture 1.1–1.9 m above the floor,
    then a random walk (``step`` m per frame) looking around (yaw anywhere, pitch −0.25…0.7 rad
    down, roll ±0.15 rad), every camera at least 0.35 m inside the walls."""
    m = 0.35

    def clear(x: float, z: float) -> bool:
        return all(not (a - m < x < b + m and c - m < z < d + m)
                   for a, b, c, d in room.footprints)

    x = z = 0.0
    for _ in range(50):
        x = rng.uniform(room.x0 + m, room.x1 - m)
        z = rng.uniform(room.z0 + m, room.z1 - m)
        if clear(x, z):
            break
    y = -rng.uniform(1.1, 1.9)
    yaw, pitch, roll = rng.uniform(-math.pi, math.pi), rng.uniform(-0.25, 0.7), rng.normal(0, 0.06)
    poses = []
    for _ in range(num_frames):
        R_wc = rot_y(yaw) @ rot_z(roll) @ rot_x(-pitch)
        poses.append((R_wc, np.array([x, y, z])))
        x = float(np.clip(x + rng.normal(0, step), room.x0 + m, room.x1 - m))
        z = float(np.clip(z + rng.normal(0, step), room.z0 + m, room.z1 - m))
        y = float(np.clip(y + rng.normal(0, 0.03), -1.95, -1.0))
        yaw += rng.normal(0, 0.25)
        pitch = float(np.clip(pitch + rng.normal(0, 0.12), -0.3, 0.8))
        roll = float(np.clip(roll + rng.normal(0, 0.04), -0.2, 0.2))
    return poses


def render_room(seed: int, num_frames: int, width: int, height: int, focal_scale: float,
                blur_sigma: float = 0.0, noise_std: float = 0.0) -> SyntheticSequence:
    """``num_frames`` frames of the room of ``seed`` at ``width`` x ``height`` (fx = fy =
    ``focal_scale`` x width, principal point centred), exact depth."""
    room, builder = sample_room(seed)
    params = dataclasses.replace(room.params, focal_scale=float(focal_scale), cx_frac=0.5,
                                 cy_frac=0.5)
    rng = np.random.default_rng([int(seed), 2718])
    poses = room_poses(room, num_frames, rng)
    scene = _Scene(params=params, materials=_materials(params.texture_style, params.seed),
                   **builder.arrays())
    return render_frames(params, poses, width, height, seed, blur_sigma=blur_sigma,
                         noise_std=noise_std, scene=scene)

