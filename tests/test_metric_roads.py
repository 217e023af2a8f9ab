"""The camera-height metric on generated roads with real edges (domain C: a cambered road of
plain asphalt, a stone wall behind a raised sidewalk, a raised tram track bed, the bonnet in
view): per window, the estimate within 3 % of the truth, where the plane with the most points
under the camera read it 1.3-3.5x off (core/metric/ground.py). Real SfM on small images."""

from __future__ import annotations

import numpy as np
import pytest
from test_metric import street

from sfm_ttr_ros.core.metric.ground import ground_plane
from sfm_ttr_ros.core.metric.metric_config import MetricConfig
from sfm_ttr_ros.tools.ground_check import true_metres_per_unit

WIDTH, HEIGHT = 621, 188
#: (seed, first frame) of 15-frame windows, SfM on one thread (deterministic): the second on a
#: road whose crown lies 1.6 m beside the camera (read 0.949 with a corridor of 2.5 camera
#: heights). Measured (2026-11-27, 24 windows of seeds 0-6, 621 x 188): the unconstrained plane
#: 0.32-1.03 of the truth (5 windows 1.3-3.5x off), the road's 0.943-1.057 (16 of 20 within
#: 3 %) or refused (4)
WINDOWS = ((1, 15), (5, 30))
UNCONSTRAINED = {"max_slope_deg": 89.0, "max_roll_deg": 89.0, "corridor": 1e9}


@pytest.fixture(scope="module")
def windows(one_thread):
    from sfm_ttr_ros.core.frames import Frame
    from sfm_ttr_ros.core.sfm.reconstruction import SfmReconstructor
    from sfm_ttr_ros.core.sfm.sfm_config import SfmConfig
    from sfm_ttr_ros.data.synthetic import render_sequence, sample_scene_params

    out = []
    # SIFT from the upsampled octave, as the figures above were measured
    with SfmReconstructor(SfmConfig(num_threads=1, first_octave=-1)) as rec:
        for seed, first in WINDOWS:
            params = sample_scene_params(seed, "C")
            seq = render_sequence(params, first + 15, WIDTH, HEIGHT, seed=seed)
            frames = [Frame(i, seq.images[i], stamp=seq.stamps[i])
                      for i in range(first, first + 15)]
            sfm = rec.reconstruct(frames, seq.intrinsics)
            index = {f.name: f.index for f in frames}
            registered = sorted(sfm.frames, key=index.get)
            assert sfm.ok and len(registered) >= 10, sfm.reason
            truth = true_metres_per_unit(sfm, registered, seq.cam_from_world, index)
            out.append((params, sfm, registered, truth))
    return out


def estimate_over_truth(window, **overrides) -> float:
    params, sfm, registered, truth = window
    cfg = MetricConfig(source="camera_height", camera_height=params.camera_height, **overrides)
    plane = ground_plane(sfm, registered, cfg)
    return cfg.camera_height / plane.height / truth


@pytest.mark.slow
def test_the_camera_height_holds_on_roads_with_real_edges(windows):
    ratios = [estimate_over_truth(w) for w in windows]
    print("estimate / truth per window:", [f"{r:.3f}" for r in ratios])
    assert all(abs(r - 1) <= 0.03 for r in ratios), ratios


def test_a_slope_through_the_road_and_its_edge_is_not_the_ground():
    """What the unconstrained plane picked on those roads: few points on plain asphalt under
    the track, many on a slope rolled 15° through it and the raised bed beside it (and lifted
    off the road). The road's plane: square to the travel, rolled with the cameras, near the
    track."""
    sfm, reg = street(ground_points=150, seed=3)  # camera 1.65 m over y = 0, driving along z
    rng = np.random.default_rng(4)
    x = rng.uniform(-9.0, -2.5, 400)  # left of the corridor, the bed and the wall's foot
    z = rng.uniform(5.0, 30.0, 400)
    slope = np.c_[x, 0.6 + np.tan(np.radians(15)) * x, z] / 0.5  # rises to the left
    sfm.points_xyz = np.vstack([sfm.points_xyz, slope])
    road = ground_plane(sfm, reg, MetricConfig(source="camera_height"))
    assert road.height == pytest.approx(1.65 / 0.5, rel=0.03), road.reason
    wrong = ground_plane(sfm, reg, MetricConfig(source="camera_height", **UNCONSTRAINED))
    assert not wrong.height == pytest.approx(1.65 / 0.5, rel=0.10), wrong
