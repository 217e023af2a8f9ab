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
wider-angle camera, more yaw wobble, flatter contrast); ``"C"`` is a town road with real edges
(A's camera on a cambered road of plain asphalt, a stone wall behind a raised sidewalk on the
right, a raised tram track bed on the left, the car's bonnet in view): what makes a ground plane
under the camera pick the wrong points (:mod:`sfm_ttr_ros.core.metric.ground`).

Hard drives (:mod:`.scenario`): segments of ordinary driving, turning on the spot,
a standing camera, cars crossing ahead, a vehicle ahead moving with the camera, a sudden
exposure change, turning while creeping, creeping straight and a truck ahead moving with the
camera, one label per frame (:func:`make_hard_sequence`, :data:`DEFAULT_HARD_SEGMENTS`).

Modules, one job each: :mod:`.scene` (parameters, domains, camera path),
:mod:`.textures` (procedural textures), :mod:`.materials` (mip-mapped atlases and their
lookup), :mod:`.geometry` (the street's objects), :mod:`.raycast` (intersections),
:mod:`.shading`, :mod:`.render` (frames and drives; :func:`street_frames` a long drive one
frame at a time), :mod:`.scenario` (segment drives).
"""

from __future__ import annotations

from sfm_ttr_ros.data.synthetic.materials import _materials
from sfm_ttr_ros.data.synthetic.render import (
    SyntheticSequence,
    make_sequence,
    render_frames,
    render_sequence,
    street_frames,
)
from sfm_ttr_ros.data.synthetic.scenario import (
    DEFAULT_HARD_SEGMENTS,
    SEGMENT_KINDS,
    DrivePlan,
    Segment,
    Vehicle,
    as_segments,
    make_hard_sequence,
    plan_drive,
    render_hard_drive,
    replace_segments,
)
from sfm_ttr_ros.data.synthetic.scene import (
    DOMAINS,
    FRAME_RATE,
    KITTI_START_STAMP,
    SceneParams,
    camera_pose,
    sample_scene_params,
    scene_intrinsics,
)

# the private name is the texture test's (tests/test_synthetic.py)
__all__ = [
    "DEFAULT_HARD_SEGMENTS",
    "DOMAINS",
    "FRAME_RATE",
    "KITTI_START_STAMP",
    "SEGMENT_KINDS",
    "DrivePlan",
    "SceneParams",
    "Segment",
    "SyntheticSequence",
    "Vehicle",
    "_materials",
    "as_segments",
    "camera_pose",
    "make_hard_sequence",
    "make_sequence",
    "plan_drive",
    "render_frames",
    "render_hard_drive",
    "replace_segments",
    "render_sequence",
    "sample_scene_params",
    "scene_intrinsics",
    "street_frames",
]
