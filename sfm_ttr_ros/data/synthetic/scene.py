"""Scene parameters of a synthetic drive (:class:`SceneParams`, drawn per domain and seed by
:func:`sample_scene_params`) and the camera path through it (:func:`camera_pose`,
:func:`scene_intrinsics`). Conventions: see :mod:`sfm_ttr_ros.data.synthetic`."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Intrinsics
from sfm_ttr_ros.data.poses import rot_x, rot_y, rot_z

DOMAINS = ("A", "B", "C")
KITTI_START_STAMP = 1317042145.964389  # 2011-09-26 13:02:25.964389 UTC, a KITTI-like epoch
FRAME_RATE = 10.0  # Hz, like KITTI


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
    # road edges (domain C; the defaults leave A and B as they were): the road's cross slope
    # from its crown at x = 0 (the camera rolls with its lane), the asphalt's texture contrast
    # (1 = as drawn), a stone wall of this height at the right sidewalk's outer edge (0 =
    # none), a raised track bed of this width on the left instead of a sidewalk (0 = none), its
    # top this high over the road, and the car's bonnet in view (this long ahead of the camera,
    # its top this far below it; 0 = none)
    camber: float = 0.0
    road_contrast: float = 1.0
    wall_height: float = 0.0
    tram_bed_width: float = 0.0
    tram_bed_height: float = 0.0
    bonnet_length: float = 0.0
    bonnet_drop: float = 0.5


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

    Domain C (a town road with real edges, :func:`_road_edges`): domain A's camera and light on
    a cambered 9.5-11.5 m road (cross slope 2-3 %) of plain asphalt (texture contrast 0.25-0.4) with
    its lane markings, a 1.8-3 m stone wall at the back of a 1.5-2.5 m raised sidewalk on the
    right, a raised tram track bed (5.5-7 m, rails) on the left, parked cars on the right only,
    and the car's bonnet in the bottom of the view.
    """
    if domain not in DOMAINS:
        raise InputError(f"unknown synthetic domain {domain!r}; expected one of {DOMAINS}")
    if domain == "C":
        return _road_edges(seed)
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


def _road_edges(seed: int) -> SceneParams:
    """Domain C (:func:`sample_scene_params`): domain A's scene of ``seed`` with the road edges
    drawn from a stream of its own."""
    rng = np.random.default_rng([int(seed), 2, 7])
    u = rng.uniform
    street, kerb = u(9.5, 11.5), u(0.12, 0.16)
    return dataclasses.replace(
        sample_scene_params(seed, "A"), domain="C", street_width=street,
        sidewalk_width=u(1.5, 2.5), kerb_height=kerb, facade_setback_max=u(1.0, 3.0),
        lane_offset=street / 2 - 2.2 - u(1.4, 1.8), camber=u(0.02, 0.03),
        road_contrast=u(0.25, 0.4), wall_height=u(1.8, 3.0), tram_bed_width=u(5.5, 7.0),
        tram_bed_height=kerb + u(0.03, 0.1), bonnet_length=u(1.9, 2.3),
        bonnet_drop=u(0.45, 0.55), num_trees=0)


def road_level(params: SceneParams, x: float) -> float:
    """The road surface's ``y`` at ``x`` (0 at the kerbs; up to camber x half-width higher at
    the crown, y down)."""
    hw = params.street_width / 2
    return -params.camber * max(hw - abs(x), 0.0)


# ---------------------------------------------------------------------------------------------
# Camera path
# ---------------------------------------------------------------------------------------------


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
    if p.camber:  # over its lane of a cambered road: the car rolls with the cross slope
        roll = math.atan(p.camber) * (1.0 if x >= 0 else -1.0)
        R_wc = rot_y(yaw) @ rot_z(roll) @ rot_x(-pitch)
        return R_wc, np.array([x, road_level(p, x) - height, z])
    R_wc = rot_y(yaw) @ rot_x(-pitch)  # positive pitch looks down (y is down)
    return R_wc, np.array([x, -height, z])


def scene_intrinsics(params: SceneParams, width: int, height: int) -> Intrinsics:
    f = params.focal_scale * width
    return Intrinsics(f, f, params.cx_frac * width, params.cy_frac * height, width, height)
