"""Which intrinsics each frame of a live stream gets (the node's rule, ROS-free).

For each frame, the first that applies:

1. the intrinsics received with the frame's exact stamp (the last ``keep_by_stamp`` = 64 kept);
2. the latest intrinsics received;
3. the fallback fx, fy (both > 0; cx, cy = 0 mean the image centre, ``(size - 1) / 2``): the
   frame is marked (``Frame.fallback_intrinsics``), and the stream lets the first received
   intrinsics of the same image size replace them for the frames it still holds;
4. intrinsics assumed from the horizontal field of view ``assumed_hfov_deg`` (> 0), once the
   camera said it is uncalibrated (a CameraInfo with K all zero: :meth:`camera_uncalibrated`):
   f = (W / 2) / tan(hfov / 2), the principal point at the image centre, the frame marked
   (``Frame.assumed_intrinsics``: SfM refines the focal length window after window,
   core/sfm/self_calibration.py; a received calibration replaces them as the fallback's). The
   frames get the assumed intrinsics; what is published beside their depth carries the
   estimate so far (``assumed_focal``);
5. none: the frame is HELD, at most ``max_held`` of them (beyond that the oldest is dropped,
   reason :data:`NO_INTRINSICS`), and released oldest first as soon as intrinsics are known;
   a frame held for the idle period without any (:meth:`IntrinsicsResolver.expire`) is passed
   on without intrinsics: published unrefined (``unrefined.no_intrinsics``), never kept.

Each decision is also a :class:`CameraSource` (the intrinsics, the message they were read from,
whether they are the fallback's): set on the frame (``Frame.camera``) when it is released, and
looked up for any stamp by :meth:`IntrinsicsResolver.camera_for`, so that the node publishes
beside each depth image the CameraInfo of the camera that took it.

A distorted camera (a CameraInfo with D != 0 whose images are not declared rectified by
``camera_info_use_projection`` true) has its frames undistorted where they get their
intrinsics (:meth:`IntrinsicsResolver.rectified` on arrival, so that live serving and the
window share the one remapped image; or when a held frame is released): a copy of the frame
with the rectified image (``Frame.rectified``), whose intrinsics are the rectified image's
(core/undistort.py, the maps built once per distinct CameraInfo by :class:`CameraInfoReader`),
its depth published beside a CameraInfo with D = 0 and that K (:meth:`CameraSource.message_for`).
A frame served live before its camera was known keeps its raw image there, and the received
CameraInfo beside that depth.

Intrinsics for another image size than the frame's are returned as they are: the stream
publishes such a frame unrefined (``intrinsics_mismatch``). A fallback principal point that lies
outside the frame (``cx``, ``cy`` set for a larger image, e.g. KITTI's on a 416x128 frame, or a
live ``cx`` of 5000) is the same case: the fallback gives intrinsics for the smallest image that
contains that principal point, i.e. for another image size, so the frame is published unrefined
(``intrinsics_mismatch``) instead of raising. A fallback that cannot make intrinsics at all
(fx, fy unset, or an error reading it) holds the frame (rule 5). Stamps are integer nanoseconds
(or None when the frame has none: only rules 2-5 apply); converting messages is msg_adapters'
job.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from msg_adapters.camera_info import (
    camera_info_distortion,
    camera_info_to_intrinsics,
    rectified_camera_info,
)
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.outcomes import Dropped
from sfm_ttr_ros.core.undistort import (
    Distortion,
    Rectifier,
    RectifierCache,
    UnknownDistortionModel,
)

NO_INTRINSICS = Dropped.NO_INTRINSICS  # a held frame pushed out by a newer one
KEEP_BY_STAMP = 64


@dataclass(frozen=True)
class FallbackIntrinsics:
    """Intrinsics to use while none were received: unset unless fx and fy are both > 0."""

    fx: float = 0.0
    fy: float = 0.0
    cx: float = 0.0  # 0 = image centre
    cy: float = 0.0

    def for_size(self, width: int, height: int) -> Intrinsics | None:
        """Intrinsics for a ``width`` x ``height`` image, or None when fx / fy are unset.

        When (cx, cy) lies outside that image (pixel centres at integers: the image spans
        [-0.5, size - 0.5]), the result is for the smallest image holding it, i.e. NOT the
        frame's size: callers compare sizes and treat it as ``intrinsics_mismatch``."""
        if not (self.fx > 0 and self.fy > 0):
            return None
        cx = float(self.cx) or (width - 1) / 2.0
        cy = float(self.cy) or (height - 1) / 2.0
        w = max(int(width), math.ceil(cx + 0.5))
        h = max(int(height), math.ceil(cy + 0.5))
        return Intrinsics(float(self.fx), float(self.fy), cx, cy, w, h)


@dataclass(frozen=True)
class CameraSource:
    """Where a frame's intrinsics came from: ``message`` is what was received with them (the
    CameraInfo, opaque here) or None for the fallback's (``fallback`` True) and the assumed
    ones (``assumed`` True)."""

    intrinsics: Intrinsics
    message: object | None = None
    fallback: bool = False
    assumed: bool = False  # from a field of view (rule 4): SfM refines their focal length
    # a distorted camera: its frames are undistorted by ``rectifier``, ``intrinsics`` and
    # ``rectified_message`` are those of the rectified images
    rectifier: Rectifier | None = None
    rectified_message: object | None = None

    def message_for(self, rectified: bool) -> object | None:
        """The CameraInfo beside a frame's depth: the rectified images' for a ``rectified``
        frame of a distorted camera, else the one received."""
        if rectified and self.rectified_message is not None:
            return self.rectified_message
        return self.message

    @property
    def stand_in(self) -> bool:
        """The fallback's or assumed intrinsics: a received calibration replaces them."""
        return self.fallback or self.assumed


@dataclass
class Resolved:
    """What a call hands over: frames now ready with their intrinsics (oldest first) and held
    frames dropped to respect the bound (oldest first, reason :data:`NO_INTRINSICS`)."""

    ready: list[tuple[Frame, Intrinsics]] = field(default_factory=list)
    dropped: list[Frame] = field(default_factory=list)


class IntrinsicsResolver:
    """The per-frame intrinsics rule (module docstring). Thread-safe.

    ``fallback`` and ``assumed_hfov_deg`` (0: no intrinsics are assumed): called at every
    decision, so live parameter changes apply at once. ``assumed_focal``: the focal length
    estimated so far for assumed intrinsics of a (width, height) image (None: the assumed
    one), for what is published. ``max_held``: bound of the held frames (>= 1).
    """

    def __init__(self, fallback: Callable[[], FallbackIntrinsics] = FallbackIntrinsics,
                 max_held: int = 100, keep_by_stamp: int = KEEP_BY_STAMP, *,
                 assumed_hfov_deg: Callable[[], float] = lambda: 0.0,
                 assumed_focal: Callable[[tuple[int, int]], float | None] = lambda size: None):
        if int(max_held) < 1 or int(keep_by_stamp) < 1:
            raise InputError(f"max_held and keep_by_stamp must be >= 1, got {max_held}, "
                             f"{keep_by_stamp}")
        self._fallback = fallback
        self._hfov, self._focal = assumed_hfov_deg, assumed_focal
        self._uncalibrated = False  # a CameraInfo said the camera is not calibrated (rule 4)
        self.max_held = int(max_held)
        self._keep = int(keep_by_stamp)
        self._by_stamp: collections.OrderedDict[int, CameraSource] = collections.OrderedDict()
        self._latest: CameraSource | None = None
        # (frame, stamp_ns, when it was held: time.monotonic())
        self._held: collections.deque[tuple[Frame, int | None, float]] = collections.deque()
        self._lock = threading.Lock()

    @property
    def latest(self) -> Intrinsics | None:
        """The intrinsics received last (None before any)."""
        latest = self._latest
        return None if latest is None else latest.intrinsics

    @property
    def held(self) -> int:
        """How many frames wait for intrinsics."""
        return len(self._held)

    def intrinsics_for(self, size: tuple[int, int], stamp_ns: int | None) -> Intrinsics | None:
        """The intrinsics of a ``size`` = (width, height) frame stamped ``stamp_ns`` (rules 1-3),
        or None (the frame would be held)."""
        source = self.camera_for(size, stamp_ns)
        return None if source is None else source.intrinsics

    def camera_for(self, size: tuple[int, int], stamp_ns: int | None) -> CameraSource | None:
        """Rules 1-4 for a ``size`` = (width, height) image stamped ``stamp_ns``, with the
        message the intrinsics came from (assumed ones: with the focal length estimated so
        far); None when nothing is known yet (thread-safe)."""
        with self._lock:
            source = self._resolve(size, stamp_ns)
        focal = self._focal(size) if source is not None and source.assumed else None
        if focal is None:
            return source
        i = source.intrinsics
        return CameraSource(Intrinsics(focal, focal, i.cx, i.cy, i.width, i.height),
                            assumed=True)

    def kind(self, assumed_state: str) -> str:
        """Where the intrinsics come from now (``intrinsics.source`` on /diagnostics):
        ``camera_info``, ``fallback``, ``assumed_state`` (the focal length's: assumed,
        refining, settled) or ``none``."""
        if self._latest is not None:
            return "camera_info"
        if self._fallback().fx > 0:
            return "fallback"
        return assumed_state if self._uncalibrated and self._hfov() > 0 else "none"

    def camera_uncalibrated(self) -> Resolved:
        """A CameraInfo said the camera is not calibrated (K all zero): rule 4 applies from now
        on; held frames released."""
        with self._lock:
            self._uncalibrated = True
            return Resolved(ready=self._release())

    def window_camera(self, frame: Frame, stamp_ns: int | None) -> CameraSource | None:
        """The camera of a frame out of its window: the CameraInfo its intrinsics were read
        from; for a frame that had the fallback's, a CameraInfo received since (the camera's own
        description: the stream takes the first one in place of the fallback too), else the
        fallback it had."""
        given = frame.camera if isinstance(frame.camera, CameraSource) else None
        if given is not None and not given.stand_in:
            return given
        now = self.camera_for(frame.size, stamp_ns)
        if now is not None and (given is None or not now.fallback):
            return now
        return given

    def _resolve(self, size: tuple[int, int], stamp_ns: int | None) -> CameraSource | None:
        if stamp_ns is not None:
            source = self._by_stamp.get(int(stamp_ns))
            if source is not None:
                return source
        if self._latest is not None:
            return self._latest
        try:
            intr = self._fallback().for_size(*size)
        except InputError:  # a fallback that cannot describe any image: as if unset (held)
            return None
        if intr is not None:
            return CameraSource(intr, None, fallback=True)
        hfov = float(self._hfov())
        if self._uncalibrated and 0 < hfov < 180:
            return CameraSource(Intrinsics.from_fov(*size, hfov), assumed=True)
        return None

    def rectified(self, frame: Frame, stamp_ns: int | None) -> Frame:
        """``frame`` with its image undistorted when its camera as known now is a distorted
        one (a copy, ``Frame.rectified``), else ``frame`` itself (module docstring)."""
        with self._lock:
            source = self._resolve(frame.size, stamp_ns)
        return _rectify(frame, source)

    def add_intrinsics(self, intr: Intrinsics, stamp_ns: int, message: object = None) -> Resolved:
        """Intrinsics received for ``stamp_ns`` (read from ``message``, a CameraInfo):
        remembered, held frames released."""
        return self.add_camera(CameraSource(intr, message), stamp_ns)

    def add_camera(self, source: CameraSource, stamp_ns: int) -> Resolved:
        """A camera received for ``stamp_ns`` (:meth:`CameraInfoReader.read`): remembered,
        held frames released (undistorted when it is a distorted camera)."""
        with self._lock:
            self._latest = source
            self._by_stamp[int(stamp_ns)] = source
            self._by_stamp.move_to_end(int(stamp_ns))
            while len(self._by_stamp) > self._keep:
                self._by_stamp.popitem(last=False)
            return Resolved(ready=self._release())

    def add_frame(self, frame: Frame, stamp_ns: int | None) -> Resolved:
        """A frame arrives: ready at once (with the frames held before it) or held."""
        with self._lock:
            self._held.append((frame, None if stamp_ns is None else int(stamp_ns),
                               time.monotonic()))
            out = Resolved(ready=self._release())
            while len(self._held) > self.max_held:
                out.dropped.append(self._held.popleft()[0])
            return out

    def expire(self, held_s: float) -> list[Frame]:
        """The frames held ``held_s`` seconds or longer (oldest first), no longer held: no
        intrinsics came for them within the idle period (``held_s`` <= 0: none)."""
        out: list[Frame] = []
        with self._lock:
            while held_s > 0 and self._held and time.monotonic() - self._held[0][2] >= held_s:
                out.append(self._held.popleft()[0])
        return out

    def release(self) -> Resolved:
        """Release the held frames that now have intrinsics (e.g. fallback just set)."""
        with self._lock:
            return Resolved(ready=self._release())

    def _release(self) -> list[tuple[Frame, Intrinsics]]:
        ready = []
        while self._held:
            frame, stamp_ns, _ = self._held[0]
            source = self._resolve(frame.size, stamp_ns)
            if source is None:
                break
            frame = _rectify(frame, source)
            frame.fallback_intrinsics, frame.camera = source.stand_in, source
            frame.assumed_intrinsics = source.assumed
            self._held.popleft()
            ready.append((frame, source.intrinsics))
        return ready


def _rectify(frame: Frame, source: CameraSource | None) -> Frame:
    """A copy of ``frame`` with its image undistorted by ``source``'s rectifier, when it has
    one for the frame's size and the frame is not rectified yet; else ``frame``."""
    rectifier = None if source is None else source.rectifier
    if rectifier is None or frame.rectified or frame.size != rectifier.size:
        return frame
    return dataclasses.replace(frame, image=rectifier.remap(frame.image), rectified=True,
                               served_live=False)


class CameraInfoReader:
    """Each CameraInfo read into the :class:`CameraSource` of its camera: its pinhole
    intrinsics (msg_adapters) and, for a distorted camera, the rectifier of its images (built
    once per distinct camera, :class:`~sfm_ttr_ros.core.undistort.RectifierCache`) with the
    intrinsics and CameraInfo of the rectified images. A lens model that cannot be undistorted
    is refused: counted (``on_refused``) and logged at WARN (``logger``) once per distinct
    CameraInfo, pointing at image_proc's rectified ``image_rect``."""

    def __init__(self, logger, on_refused: Callable[[], None]):
        self.rectifiers = RectifierCache()
        self._logger, self._on_refused = logger, on_refused
        self._refused: set[Distortion] = set()

    def read(self, msg, use_projection: bool | None) -> CameraSource | None:
        """The camera ``msg`` describes (``use_projection``: the node's
        ``camera_info_use_projection``; True declares the images rectified: never
        undistorted), or None when refused. Raises what msg_adapters raises for a CameraInfo
        that cannot be read (``UncalibratedCameraInfo`` for K all zero)."""
        intr = camera_info_to_intrinsics(msg, use_projection)
        distortion = None if use_projection else camera_info_distortion(msg)
        if distortion is None:
            return CameraSource(intr, msg)
        try:
            rectifier = self.rectifiers.get(distortion)
        except UnknownDistortionModel as exc:
            self._on_refused()
            if distortion not in self._refused:
                self._refused.add(distortion)
                self._logger.warning(
                    f"CameraInfo refused: {exc}; subscribe to rectified images instead "
                    "(image_proc's image_rect) with camera_info_use_projection true")
            return None
        return CameraSource(Intrinsics.from_K(rectifier.K, *rectifier.size), msg,
                            rectifier=rectifier,
                            rectified_message=rectified_camera_info(distortion, rectifier.K))


def intrinsics_values(resolver: IntrinsicsResolver, focal) -> dict[str, object]:
    """The ``intrinsics.*`` values of /diagnostics: ``intrinsics.source`` (camera_info,
    fallback, assumed, refining, settled or none) and, for assumed intrinsics refined by SfM
    (``focal``: core/sfm/self_calibration.py), ``intrinsics.focal_px``, the estimate so far."""
    source = resolver.kind(focal.state)
    values: dict[str, object] = {"intrinsics.source": source}
    if source in ("refining", "settled") and focal.median is not None:
        values["intrinsics.focal_px"] = round(float(focal.median), 2)
    return values


def uncalibrated_note(exc: Exception, settings) -> str:
    """The line logged for an uncalibrated camera's CameraInfo (``settings``: the node's)."""
    if settings.fallback is not None:
        return f"{exc}: fallback_intrinsics used"
    if settings.assumed_hfov_deg > 0:
        return (f"{exc}: intrinsics assumed from a {settings.assumed_hfov_deg:g} deg horizontal "
                "field of view, the focal length refined by SfM (intrinsics.source on "
                "/diagnostics)")
    return f"{exc}: frames wait (assumed_hfov_deg is 0, fallback_intrinsics unset)"
