"""The per-frame admission rules: each rule's verdict on stamps, stale frames, released images
and intrinsics, read without a stream."""

from __future__ import annotations

import numpy as np

from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.outcomes import Dropped, Unrefined
from sfm_ttr_ros.core.stream.admission import (
    image_rule,
    intrinsics_rule,
    stale_verdict,
    stamp_rule,
)

INTR = Intrinsics(50.0, 50.0, 3.5, 2.5, 8, 6)


def test_stamps_forward_pass_a_repeated_one_is_dropped_an_earlier_one_restarts():
    assert stamp_rule(1.0, None, 3) is None and stamp_rule(1.1, 1.0, 3) is None
    assert stamp_rule(float("nan"), 1.0, 3) is None  # not comparable: no rule applies
    dup = stamp_rule(1.0, 1.0, 3)
    assert dup.drop == Dropped.DUPLICATE_STAMP and dup.final and dup.flush is None
    assert dup.reason == "frame with the same stamp as the previous one (1.000000000) rejected"
    back = stamp_rule(0.5, 1.0, 3)
    assert back.flush == Unrefined.STAMP_JUMP_BACK and back.reset and not back.final
    assert back.warning == ("stamp went back from 1.000000 to 0.500000 s: 3 pending frame(s) "
                        "published unrefined and a new window started")


def test_a_stale_frame_goes_out_with_the_window_being_filled():
    v = stale_verdict("newest")
    assert v.flush == v.unrefined == Unrefined.STALE and v.final and not v.reset
    assert "keyframe_policy newest" in v.reason


def test_a_released_image_or_a_size_the_intrinsics_do_not_fit_keeps_the_frame_out():
    frame = Frame(0, np.zeros((6, 8, 3), np.uint8))
    assert image_rule(frame, INTR, released=False) is None
    released = image_rule(frame, INTR, released=True)
    assert released.flush == released.unrefined == Unrefined.OVERLOAD and released.reset
    assert released.throttle == "overload" and released.warning == released.reason
    other = Intrinsics(50.0, 50.0, 3.5, 2.5, 16, 12)
    mismatch = image_rule(frame, other, released=False)
    assert mismatch.unrefined == Unrefined.INTRINSICS_MISMATCH and mismatch.flush is None
    assert mismatch.reason == "intrinsics are for 16x12, the image is 8x6"


def test_new_intrinsics_restart_the_window_unless_they_replace_the_fallback():
    other_k = Intrinsics(60.0, 60.0, 3.5, 2.5, 8, 6)
    other_size = Intrinsics(50.0, 50.0, 7.5, 5.5, 16, 12)
    assert intrinsics_rule(INTR, None, False, False, 2) is None
    assert intrinsics_rule(INTR, INTR, True, False, 2) is None
    took = intrinsics_rule(other_k, INTR, True, False, 2)  # the CameraInfo replaces the fallback
    assert took.flush is None and not took.reset and not took.warning
    assert took.info.endswith("for the 2 pending frame(s)")
    changed = intrinsics_rule(other_k, INTR, False, False, 2)
    assert changed.flush == Unrefined.INTRINSICS_CHANGE and changed.reset and not changed.final
    # a frame on the fallback itself, or another image size: a change all the same
    assert intrinsics_rule(other_k, INTR, True, True, 2).flush == Unrefined.INTRINSICS_CHANGE
    resized = intrinsics_rule(other_size, INTR, True, False, 2)
    assert resized.flush == Unrefined.RESOLUTION_CHANGE
    assert resized.reason == "image size changed from 8x6 to 16x12"
