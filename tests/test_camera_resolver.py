"""The node's per-frame intrinsics rule, ROS-free (sfm_ttr_ros.ros.camera; README "Intrinsics")."""

from __future__ import annotations

import numpy as np
import pytest

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.ros.camera import (
    KEEP_BY_STAMP,
    FallbackIntrinsics,
    IntrinsicsResolver,
)

W, H = 320, 96
CAM_A = Intrinsics(200.0, 201.0, 160.0, 48.0, W, H)
CAM_B = Intrinsics(300.0, 301.0, 150.0, 40.0, W, H)
S = 1_000_000_000  # ns per second


def frame(i: int, width: int = W, height: int = H) -> Frame:
    return Frame(index=i, image=np.zeros((height, width, 3), np.uint8), stamp=float(i))


def indices(pairs) -> list[int]:
    return [f.index for f, _ in pairs]


def test_exact_stamp_wins_over_the_latest_and_none_stamp_gets_the_latest():
    r = IntrinsicsResolver()
    assert r.add_intrinsics(CAM_A, 1 * S).ready == []
    r.add_intrinsics(CAM_B, 2 * S)
    assert r.latest == CAM_B
    (f, intr), = r.add_frame(frame(1), 1 * S).ready
    assert f.index == 1 and intr == CAM_A
    assert r.add_frame(frame(2), 2 * S).ready[0][1] == CAM_B
    assert r.add_frame(frame(3), 3 * S).ready[0][1] == CAM_B  # no CameraInfo at 3 s: latest
    assert r.add_frame(frame(4), None).ready[0][1] == CAM_B
    assert r.held == 0


def test_only_the_last_64_stamps_are_kept():
    r = IntrinsicsResolver()
    cams = [Intrinsics(100.0 + i, 100.0, 160.0, 48.0, W, H) for i in range(KEEP_BY_STAMP + 1)]
    for i, cam in enumerate(cams):
        r.add_intrinsics(cam, i)
    assert r.intrinsics_for((W, H), 0) == cams[-1]  # forgotten: the latest instead
    assert r.intrinsics_for((W, H), 1) == cams[1]
    # a CameraInfo repeated with a known stamp is the newest again, not evicted next
    r.add_intrinsics(cams[1], 1)
    r.add_intrinsics(CAM_B, 10_000)
    assert r.intrinsics_for((W, H), 1) == cams[1]
    assert r.intrinsics_for((W, H), 2) == CAM_B  # stamp 2 was the oldest: evicted


def test_fallback_uses_the_image_centre_for_zero_cx_cy_and_yields_to_camera_info():
    params = {"fx": 0.0, "fy": 0.0, "cx": 0.0, "cy": 0.0}
    r = IntrinsicsResolver(lambda: FallbackIntrinsics(**params))
    assert r.add_frame(frame(0), 0).ready == [] and r.held == 1
    params.update(fx=250.0)  # fy still unset: no fallback
    assert r.release().ready == [] and r.held == 1
    params.update(fy=260.0)
    (f, intr), = r.release().ready
    assert f.index == 0 and r.held == 0
    assert (intr.fx, intr.fy, intr.cx, intr.cy) == (250.0, 260.0, (W - 1) / 2, (H - 1) / 2)
    assert (intr.width, intr.height) == (W, H)
    # the fallback is sized after each frame
    intr_small = r.add_frame(frame(1, 160, 48), 1).ready[0][1]
    assert (intr_small.cx, intr_small.cy, intr_small.width) == (79.5, 23.5, 160)
    params.update(cx=10.0, cy=20.0)
    assert r.intrinsics_for((W, H), None).cx == 10.0
    assert r.intrinsics_for((W, H), None).cy == 20.0
    assert f.fallback_intrinsics  # marked: the stream lets received intrinsics replace them
    r.add_intrinsics(CAM_A, 5 * S)  # any CameraInfo beats the fallback from now on
    (f, intr), = r.add_frame(frame(2), 6 * S).ready
    assert intr == CAM_A and not f.fallback_intrinsics


def test_frames_without_intrinsics_are_held_bounded_and_released_oldest_first():
    r = IntrinsicsResolver(max_held=3)
    for i in range(3):
        out = r.add_frame(frame(i), i * S)
        assert out.ready == [] and out.dropped == []
    out = r.add_frame(frame(3), 3 * S)
    assert [f.index for f in out.dropped] == [0] and out.ready == []
    out = r.add_frame(frame(4), 4 * S)
    assert [f.index for f in out.dropped] == [1]
    assert r.held == 3
    # a CameraInfo for frame 3's stamp: every held frame is released, oldest first, each with
    # the intrinsics its stamp selects (exact stamp, else the latest)
    out = r.add_intrinsics(CAM_B, 3 * S)
    assert indices(out.ready) == [2, 3, 4] and out.dropped == []
    assert all(intr == CAM_B for _, intr in out.ready)
    assert r.held == 0


def test_a_new_frame_follows_the_frames_held_before_it():
    params = {"fx": 0.0}
    r = IntrinsicsResolver(lambda: FallbackIntrinsics(params["fx"], params["fx"]), max_held=5)
    r.add_frame(frame(0), 0)
    r.add_frame(frame(1), 1)
    params["fx"] = 100.0  # set between frames: the next frame releases the held ones first
    out = r.add_frame(frame(2), 2)
    assert indices(out.ready) == [0, 1, 2] and out.dropped == []


def test_intrinsics_for_another_size_are_left_to_the_stream():
    r = IntrinsicsResolver()
    r.add_intrinsics(CAM_A, 0)
    (f, intr), = r.add_frame(frame(1, 160, 48), 1).ready
    assert f.size == (160, 48) and intr == CAM_A  # the stream publishes it unrefined


def test_bad_bounds_are_refused():
    with pytest.raises(InputError, match="max_held"):
        IntrinsicsResolver(max_held=0)
    with pytest.raises(InputError, match="keep_by_stamp"):
        IntrinsicsResolver(keep_by_stamp=0)
