"""The per-frame rules the window worker applies before the keyframe rule (docs/node.md, "How
frames flow", rules 2, 3 and 5, and "Intrinsics"): stamps, stale frames, released images,
intrinsics. Pure: each rule reads the frame and what the worker last saw, and returns a
:class:`Verdict` (None: the rule has nothing to say) that the worker applies."""

from __future__ import annotations

from dataclasses import dataclass

from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.outcomes import Dropped, Unrefined

#: The end of the warning of a rule that publishes the pending keyframes and starts anew.
_RESTART = "pending frame(s) published unrefined and a new window started"


@dataclass(frozen=True)
class Verdict:
    """What a rule says about a frame, applied in this order: the pending keyframes published
    unrefined under ``flush``, a new window started (``reset``: the keyframe rule starts from
    scratch), the frame itself dropped under ``drop`` or published unrefined under
    ``unrefined``, then ``warning`` / ``info`` written (after the frames are carried out: a log
    that fails loses no frame). With neither ``drop`` nor ``unrefined``, the frame goes on to
    the next rule. ``reason`` is the text counted beside the keys. A line has its severity in
    its field, never chosen at run time: rclpy's logger refuses one call site logging at two
    severities."""

    reason: str = ""
    drop: Dropped | None = None
    flush: Unrefined | None = None
    unrefined: Unrefined | None = None
    reset: bool = False
    warning: str = ""
    info: str = ""
    throttle: str = ""  # set: ``warning`` is written at most once per period per key

    @property
    def final(self) -> bool:
        """Whether the frame ends here (dropped or published unrefined)."""
        return self.drop is not None or self.unrefined is not None


def stamp_rule(stamp: float, last: float | None, pending: int) -> Verdict | None:
    """The same stamp as the previous frame: a duplicated message, dropped. An earlier one
    (a bag restarted, a clock reset): the ``pending`` keyframes are published unrefined and a
    new window starts with the frame."""
    if last is None or not stamp <= last:
        return None
    if stamp == last:
        return Verdict(f"frame with the same stamp as the previous one ({stamp:.9f}) rejected",
                       drop=Dropped.DUPLICATE_STAMP)
    return Verdict("stamp went back: window reset", flush=Unrefined.STAMP_JUMP_BACK, reset=True,
                   warning=f"stamp went back from {last:.6f} to {stamp:.6f} s: {pending} "
                           f"{_RESTART}")


def stale_verdict(policy: str) -> Verdict:
    """A frame the keyframe rule found stale (:meth:`~.keyframes.KeyframeSelector.is_stale`,
    which starts the keyframes anew itself): it and the keyframes collected before it are
    published unrefined."""
    why = f"stale: the frames queued after it span the next window (keyframe_policy {policy})"
    return Verdict(why, flush=Unrefined.STALE, unrefined=Unrefined.STALE)


def image_rule(frame: Frame, intrinsics: Intrinsics, released: bool) -> Verdict | None:
    """A frame whose image the backlog bound ``released`` cannot join a window: the window
    being filled is published unrefined (overload) and so is the frame. A frame whose
    intrinsics are for another image size is published unrefined and kept out of the
    windows."""
    if released:
        reason = ("overload: image released by the backlog bound (overload_pending + "
                  "window_size images kept); served live")
        return Verdict(reason, flush=Unrefined.OVERLOAD, unrefined=Unrefined.OVERLOAD,
                       reset=True, warning=reason, throttle="overload")
    if frame.size != (intrinsics.width, intrinsics.height):
        return Verdict(f"intrinsics are for {intrinsics.width}x{intrinsics.height}, the image "
                       f"is {frame.size[0]}x{frame.size[1]}",
                       unrefined=Unrefined.INTRINSICS_MISMATCH)
    return None


def intrinsics_rule(new: Intrinsics, current: Intrinsics | None, current_fallback: bool,
                    new_fallback: bool, pending: int) -> Verdict | None:
    """A change of image size or intrinsics from the ``current`` ones: the ``pending``
    keyframes are published unrefined and a new window starts with the frame. Not when the
    first received intrinsics replace the fallback's for an image of the same size: the
    pending frames take them (logged), since the fallback only stood in for the CameraInfo."""
    if current is None or new == current:
        return None
    size_changed = (new.width, new.height) != (current.width, current.height)
    if current_fallback and not new_fallback and not size_changed:
        return Verdict(info=f"intrinsics received: {new} replace the fallback {current} for the "
                            f"{pending} pending frame(s)")
    key = Unrefined.RESOLUTION_CHANGE if size_changed else Unrefined.INTRINSICS_CHANGE
    what = (f"image size changed from {current.width}x{current.height} to "
            f"{new.width}x{new.height}" if size_changed else
            f"intrinsics changed from {current} to {new}")
    return Verdict(what, flush=key, reset=True, warning=f"{what}: {pending} {_RESTART}")
