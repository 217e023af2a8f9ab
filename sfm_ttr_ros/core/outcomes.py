"""What happened to a window or a frame, as typed keys.

Where a window stops, a check refuses it or the stream passes a frame on without refinement, the
code names the outcome with a member of :class:`Unrefined`; a frame that is never published gets
a :class:`Dropped`, a live frame that is not served a :class:`LiveSkipped`. Each is a
``StrEnum``: its value is the counter key of ``/diagnostics`` (``unrefined.sfm_failed``,
``dropped.overflow``, ``live.skipped.overflow``) and of the reports. The sentence that travels
beside it (``WindowResult.reason``, a log line) is for people only: nothing parses it, so
rewording a message never changes what is counted.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum


class _Outcome(StrEnum):
    """A counted key with a sentence for people (``description``)."""

    @property
    def description(self) -> str:
        return _DESCRIPTIONS[self]


class Unrefined(_Outcome):
    """Why a frame went out on the windowed output without refinement."""

    # -- the window's own outcome (core/pipeline.py)
    SFM_FAILED = "sfm_failed"
    TOO_FEW_POINTS = "too_few_points"
    CANCELLED = "cancelled"
    DISABLED = "disabled"
    ROLLED_BACK = "rolled_back"
    WINDOW_ERROR = "window_error"
    # -- a window check refused it (core/checks/)
    CHECK_REPROJECTION = "check_reprojection"
    CHECK_PARALLAX = "check_parallax"
    CHECK_SCALE_JUMP = "check_scale_jump"
    CHECK_UNSUPPORTED_CHANGE = "check_unsupported_change"
    # -- the stream passed the frame on (core/stream/)
    NOT_KEYFRAME = "not_keyframe"
    STALE = "stale"
    OVERLOAD = "overload"
    RESOLUTION_CHANGE = "resolution_change"
    INTRINSICS_CHANGE = "intrinsics_change"
    INTRINSICS_MISMATCH = "intrinsics_mismatch"
    STAMP_JUMP_BACK = "stamp_jump_back"
    END_OF_STREAM = "end_of_stream"
    WORKER_FAULT = "worker_fault"
    NO_INTRINSICS = "no_intrinsics"


class Dropped(_Outcome):
    """Why a received frame was never published on the windowed output."""

    OVERFLOW = "overflow"
    DUPLICATE_STAMP = "duplicate_stamp"
    BAD_IMAGE = "bad_image"
    NO_INTRINSICS = "no_intrinsics"
    PREDICTION_ERROR = "prediction_error"


class LiveSkipped(_Outcome):
    """Why a frame got no live depth."""

    OVERFLOW = "overflow"
    PREDICTION_ERROR = "prediction_error"
    PUBLISH_ERROR = "publish_error"
    STOPPED = "stopped"


@dataclass(frozen=True)
class Stop:
    """Why a window stops before its weights are accepted: the key that is counted and the
    sentence for people (with the figures that made it stop)."""

    key: Unrefined
    text: str


CHECKS = frozenset({Unrefined.CHECK_REPROJECTION, Unrefined.CHECK_PARALLAX,
                    Unrefined.CHECK_SCALE_JUMP, Unrefined.CHECK_UNSUPPORTED_CHANGE})

_UNREFINED = {
    Unrefined.SFM_FAILED: "SfM failed",
    Unrefined.TOO_FEW_POINTS: "too few supervision points",
    Unrefined.CANCELLED: "refinement cancelled",
    Unrefined.DISABLED: "refinement disabled (refinement.steps = 0)",
    Unrefined.ROLLED_BACK: "refinement rolled back (non-finite or exploding loss)",
    Unrefined.WINDOW_ERROR: "window failed with an error",
    Unrefined.CHECK_REPROJECTION: "sanity check: mean reprojection error too high",
    Unrefined.CHECK_PARALLAX: "sanity check: too little parallax (camera path short against "
                              "the depth)",
    Unrefined.CHECK_SCALE_JUMP: "sanity check: scale jumped against the previous window",
    Unrefined.CHECK_UNSUPPORTED_CHANGE: "refined weights rejected: depth changed where SfM has "
                                        "no points",
    Unrefined.NOT_KEYFRAME: "not a keyframe",
    Unrefined.STALE: "skipped behind: the frames queued after it span the next window",
    Unrefined.OVERLOAD: "overload: refinement skipped",
    Unrefined.RESOLUTION_CHANGE: "image resolution changed",
    Unrefined.INTRINSICS_CHANGE: "intrinsics changed",
    Unrefined.INTRINSICS_MISMATCH: "intrinsics are for another image size",
    Unrefined.STAMP_JUMP_BACK: "stamp went back: window reset",
    Unrefined.END_OF_STREAM: "end of stream with a single frame",
    Unrefined.WORKER_FAULT: "a fault in the window worker: the frames it held went out as they "
                            "were",
    Unrefined.NO_INTRINSICS: "no intrinsics came within the idle period",
}
_DROPPED = {
    Dropped.OVERFLOW: "input queue full: oldest pending frame dropped",
    Dropped.DUPLICATE_STAMP: "same stamp as the previous frame",
    Dropped.BAD_IMAGE: "image could not be converted",
    Dropped.NO_INTRINSICS: "held too long without intrinsics",
    Dropped.PREDICTION_ERROR: "the network failed on the frame",
}
_LIVE_SKIPPED = {
    LiveSkipped.OVERFLOW: "live queue full: oldest frame skipped",
    LiveSkipped.PREDICTION_ERROR: "live prediction failed",
    LiveSkipped.PUBLISH_ERROR: "publishing the live depth failed",
    LiveSkipped.STOPPED: "server stopped before the frame was served",
}
_DESCRIPTIONS: dict[_Outcome, str] = {**_UNREFINED, **_DROPPED, **_LIVE_SKIPPED}
