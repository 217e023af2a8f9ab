"""Undistortion of a distorted camera's images (core/undistort.py): a synthetic lens with known
K and D images dots where projectPoints puts them; once rectified, each dot lies where the
pinhole camera of the rectified image projects its ray, within a pixel."""

from __future__ import annotations

import numpy as np
import pytest
from distorted_camera import (
    EQUIDISTANT,
    PLUMB_BOB,
    SIZE,
    K,
    directions,
    distorted_pixels,
    dot_centres,
    dots_image,
    pinhole_pixels,
)

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.undistort import (
    Distortion,
    Rectifier,
    RectifierCache,
    UnknownDistortionModel,
)

IDENTITY = tuple(np.eye(3).ravel())
NO_P = (0.0,) * 12


def _distortion(model: str, D, P=NO_P) -> Distortion:
    return Distortion(model, tuple(D), tuple(K.ravel()), IDENTITY, tuple(P), *SIZE)


@pytest.mark.parametrize("model, D", [("plumb_bob", PLUMB_BOB), ("equidistant", EQUIDISTANT),
                                      ("rational_polynomial", PLUMB_BOB + (0.01, 0.0, 0.0))])
def test_rectified_dots_lie_at_the_pinhole_projection(model, D):
    rays = directions()
    raw = dots_image(distorted_pixels(rays, model, D))
    rectifier = Rectifier(_distortion(model, D))
    expected = pinhole_pixels(rays, rectifier.K)
    found = dot_centres(rectifier.remap(raw), expected)
    assert np.max(np.linalg.norm(found - expected, axis=1)) < 1.0
    # the raw image does not: the lens moved the outer dots by pixels
    raw_found = dot_centres(raw, distorted_pixels(rays, model, D))
    assert np.max(np.linalg.norm(raw_found - pinhole_pixels(rays, K), axis=1)) > 3.0


def test_without_p_the_rectified_image_keeps_only_valid_pixels():
    """alpha 0: no black border (a white raw image stays white, bar the bilinear edge)."""
    rectifier = Rectifier(_distortion("plumb_bob", PLUMB_BOB))
    out = rectifier.remap(np.full((SIZE[1], SIZE[0], 3), 255, np.uint8))
    assert out[1:-1, 1:-1].min() > 200


def test_with_p_the_rectified_image_has_p_s_intrinsics():
    K_rect = np.array([[240.0, 0, 158.0], [0, 240.0, 121.0], [0, 0, 1]])  # noqa: N806
    P = np.hstack([K_rect, [[-12.0], [0.0], [0.0]]])
    rectifier = Rectifier(_distortion("plumb_bob", PLUMB_BOB, P.ravel()))
    np.testing.assert_array_equal(rectifier.K, K_rect)
    rays = directions()
    found = dot_centres(rectifier.remap(dots_image(distorted_pixels(rays, "plumb_bob",
                                                                    PLUMB_BOB))),
                        pinhole_pixels(rays, K_rect))
    assert np.max(np.linalg.norm(found - pinhole_pixels(rays, K_rect), axis=1)) < 1.0


def test_the_maps_are_built_once_per_distinct_camera():
    cache = RectifierCache()
    a, b = _distortion("plumb_bob", PLUMB_BOB), _distortion("equidistant", EQUIDISTANT)
    assert cache.get(a) is cache.get(_distortion("plumb_bob", PLUMB_BOB))
    assert cache.get(b) is not cache.get(a)
    assert cache.built == 2


def test_an_unknown_model_or_a_wrong_count_is_refused():
    with pytest.raises(UnknownDistortionModel, match="double_sphere"):
        Rectifier(_distortion("double_sphere", (0.1, 0.2)))
    with pytest.raises(InputError, match="equidistant"):
        Rectifier(_distortion("equidistant", PLUMB_BOB))
