"""The focal length of an uncalibrated camera, estimated by SfM window after window.

Intrinsics assumed from a field of view (``Intrinsics.from_fov``: f = (W / 2) / tan(hfov / 2),
the principal point at the image centre) are a starting point only: each window's bundle
adjustment refines one focal length (a SIMPLE_PINHOLE camera, ``SfmConfig.refine_intrinsics``),
and :class:`FocalCalibration` keeps what the windows found. A single short window of forward
driving constrains f poorly (docs/decisions.md, "A ROS citizen on any camera"), so the
estimate is the median of the windows' focal lengths so far, and it is *settled* once a window
moved it by
less than :data:`SETTLED_CHANGE` and the last :data:`AGREEING` windows' focal lengths agree with
it within :data:`AGREEMENT` (a median that stands still between windows that disagree is not
settled: on a forward drive with little rotation f is barely observable, see
docs/decisions.md "A ROS citizen on any camera"): from then on the focal length is held fixed (the
paper's fixed-K SfM), as for a calibrated camera. Until then every window starts from the
assumed focal length and the frames keep it: a median of windows that disagree is no better
than the assumption (on a drive that barely turns it can be worse), so it is reported, not used.

States (the ``intrinsics.source`` of /diagnostics): ``assumed`` (no window refined f yet),
``refining``, ``settled``.
"""

from __future__ import annotations

import dataclasses
import statistics
from dataclasses import dataclass, field

from sfm_ttr_ros.core.frames import Intrinsics
from sfm_ttr_ros.core.sfm.result import SfmResult
from sfm_ttr_ros.core.sfm.sfm_config import SfmConfig

SETTLED_CHANGE = 0.01  # relative change of the estimate between two windows: settled below
#: a window's focal length further than this factor from the assumed one is not kept (a
#: bundle adjustment that collapsed: 62 px for 361 px measured on a generated drive)
PLAUSIBLE_FACTOR = 2.0
#: settled only when the last AGREEING kept windows' focal lengths lie within AGREEMENT
#: (relative) of the estimate
AGREEING, AGREEMENT = 2, 0.05
ASSUMED, REFINING, SETTLED = "assumed", "refining", "settled"


@dataclass
class FocalCalibration:
    """The focal length estimate of assumed intrinsics across windows (module docstring).
    Worker thread only, except :attr:`state` and :attr:`focal` (read for diagnostics)."""

    #: each refined window's focal length (px), for the image size :attr:`size`
    estimates: list[float] = field(default_factory=list)
    size: tuple[int, int] | None = None
    assumed: float | None = None  # the assumed focal length (px) of that size
    state: str = ASSUMED
    focal: float | None = None  # the settled estimate, carried over (None: the assumed one)
    median: float | None = None  # the median of the windows' focal lengths so far (reported)

    @property
    def settled(self) -> bool:
        return self.state == SETTLED

    def focal_for(self, size: tuple[int, int]) -> float | None:
        """The focal length estimated so far for assumed intrinsics of a ``size`` = (width,
        height) image; None before any window refined it (any thread)."""
        focal = self.focal
        return focal if focal is not None and tuple(size) == self.size else None

    def start(self, assumed: Intrinsics) -> Intrinsics:
        """The intrinsics a window of ``assumed`` intrinsics starts from: the carried focal
        length with the assumed principal point; another image size starts anew."""
        size = (assumed.width, assumed.height)
        if size != self.size:
            self.estimates, self.size, self.state, self.focal = [], size, ASSUMED, None
            self.median = None
            self.assumed = 0.5 * (assumed.fx + assumed.fy)
        if self.focal is None:
            return assumed
        return Intrinsics(self.focal, self.focal, assumed.cx, assumed.cy, *size)

    def update(self, refined: Intrinsics) -> None:
        """A window's bundle adjustment refined the focal length to ``refined``: the estimate
        becomes the median of the windows' so far; settled when it moved by less than
        :data:`SETTLED_CHANGE` (relative) from the previous window's estimate and the last
        :data:`AGREEING` windows' lie within :data:`AGREEMENT` of it. A focal length more than
        :data:`PLAUSIBLE_FACTOR` from the assumed one is left out."""
        f = 0.5 * (refined.fx + refined.fy)
        if self.assumed is not None and not (self.assumed / PLAUSIBLE_FACTOR <= f
                                             <= self.assumed * PLAUSIBLE_FACTOR):
            return
        self.estimates.append(f)
        before, self.median = self.median, float(statistics.median(self.estimates))
        recent = self.estimates[-AGREEING:]
        agree = len(recent) == AGREEING and all(abs(e - self.median) <= AGREEMENT * self.median
                                                 for e in recent)
        settled = (before is not None and agree
                   and abs(self.median - before) < SETTLED_CHANGE * before)
        self.state = SETTLED if settled else REFINING
        if settled:
            self.focal = self.median


class SelfCalibration(FocalCalibration):
    """:class:`FocalCalibration` applied to the windows of a stream: which intrinsics a window
    starts from and whether its SfM refines the focal length (``refining``)."""

    refining: bool = False

    def prepare_window(self, frames, intrinsics: Intrinsics, source, config: SfmConfig
                       ) -> Intrinsics:
        """The intrinsics the window of ``frames`` starts from, with ``source`` (the stream's
        SfM source) set to refine the focal length or not. Frames of assumed intrinsics
        (``Frame.assumed_intrinsics``) start from the carried estimate and refine it until it
        settled (the streaming source maps such windows on their own meanwhile:
        :class:`~sfm_ttr_ros.core.sfm.source.StreamingSfmSource`); every other window maps as
        ``config`` says."""
        calibrating = len(frames) > 0 and all(f.assumed_intrinsics for f in frames)
        if calibrating:
            intrinsics = self.start(intrinsics)
        self.refining = calibrating and not self.settled
        wanted = dataclasses.replace(config, refine_intrinsics=True) if self.refining else config
        if source.config != wanted:
            source.set_config(wanted)
        return intrinsics

    def window_done(self, result: SfmResult) -> Intrinsics | None:
        """The refined intrinsics of a window that refined them (the estimate updated), else
        None."""
        if not (self.refining and result.ok and result.intrinsics is not None):
            return None
        self.update(result.intrinsics)
        return result.intrinsics
