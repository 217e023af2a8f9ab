"""The streaming SfM front end: a keyframe's features when it is admitted, its matches.

Stage 1 of SfM-TTR (Izquierdo & Civera, CVPR 2023, Sec. 3.1) split in time: the work that
:class:`~sfm_ttr_ros.core.sfm.reconstruction.SfmReconstructor` does for a whole window after
its last frame (SIFT, sequential matching, two-view verification) is done here one frame at a
time, as each keyframe arrives. A window's SfM then only maps
(:mod:`sfm_ttr_ros.core.sfm.streaming_map`).

The settings are the batch reconstructor's (one :class:`SfmConfig`): SIFT on the image
downscaled to ``max_image_size`` (keypoints back in full-resolution pixels, COLMAP's
convention: pixel centres at +0.5), ``max_num_features``, ``first_octave``; COLMAP's SIFT
matcher (:func:`sift_matches`: its brute-force rule in numpy, the same matches ~7x faster than
``pycolmap.FeatureMatcher`` pair by pair) against the previous ``overlap`` frames (sequential
matching), each pair verified by pycolmap's two-view geometry on the one PINHOLE camera with
the known intrinsics (calibrated: the focal length is a prior). Everything lives in Python (no
database): the store drops a frame once it has left every future window (older than the last
``overlap`` frames and not pinned by the map).
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from dataclasses import dataclass, field

import cv2
import numpy as np

from sfm_ttr_ros.core.frames import Frame, Intrinsics, check_window, image_digest
from sfm_ttr_ros.core.sfm.reconstruction import quiet_pycolmap
from sfm_ttr_ros.core.sfm.sfm_config import MIN_PAIR_INLIERS, SfmConfig

log = logging.getLogger(__name__)

CAMERA_ID = 1  # the stream's one camera (and its trivial rig) in every map cache
GREY_WEIGHTS = np.array([0.2126, 0.7152, 0.0722])  # RGB -> grey as COLMAP reads images


@dataclass
class FrameFeatures:
    """One admitted keyframe: SIFT keypoints (full-res, COLMAP convention) and descriptors."""

    name: str
    image_id: int  # also its frame id in every map cache: stable over the stream
    xy: np.ndarray  # N x 2 float64
    descriptors: object  # pycolmap.FeatureDescriptors
    digest: bytes


@dataclass
class AdmitTimings:
    """What admitting one keyframe cost (seconds) and found."""

    name: str
    extract: float = 0.0
    match: float = 0.0
    verify: float = 0.0
    keypoints: int = 0
    pairs: int = 0  # pairs matched (the previous `overlap` frames still held)
    verified: int = 0  # pairs kept (>= MIN_PAIR_INLIERS inliers)

    @property
    def total(self) -> float:
        return self.extract + self.match + self.verify


@dataclass
class StreamFrontend:
    """Per-stream features and verified pairs, built as keyframes are admitted.

    ``pinned`` names are kept whatever their age (the map's frames and the open window);
    ``generation`` counts resets (other intrinsics, a name back with other pixels), after which
    the map must start afresh.
    """

    config: SfmConfig = field(default_factory=SfmConfig)
    features: OrderedDict[str, FrameFeatures] = field(default_factory=OrderedDict)
    pairs: dict[tuple[int, int], object] = field(default_factory=dict)  # TwoViewGeometry
    pinned: set[str] = field(default_factory=set)
    generation: int = 0
    intrinsics: Intrinsics | None = None
    frames_dropped: int = 0
    frames_extracted: int = 0  # SIFT runs, a frame that came back with other pixels included

    def __post_init__(self) -> None:
        import pycolmap

        quiet_pycolmap(self.config.verbose)
        cfg = self.config
        ext = pycolmap.FeatureExtractionOptions()
        ext.num_threads = cfg.num_threads
        ext.sift.max_num_features = cfg.max_num_features
        ext.sift.first_octave = cfg.first_octave
        self._extractor = pycolmap.FeatureExtractor.create(ext, pycolmap.Device.cpu)
        self._sift_matching = pycolmap.FeatureMatchingOptions().sift  # the batch matcher's
        self._verify = pycolmap.TwoViewGeometryOptions()
        self._next_id = 1
        self.camera = None

    # -- stream ------------------------------------------------------------------------------
    def admit(self, frame: Frame, intrinsics: Intrinsics) -> AdmitTimings:
        """Extract ``frame``'s features, match them against the previous ``overlap`` frames
        held and keep the verified pairs. A frame already held with the same pixels costs
        nothing; raises :class:`InputError` for a bad frame or intrinsics."""
        check_window([frame], intrinsics)
        digest = image_digest(frame.image)
        held = self.features.get(frame.name)
        if held is not None and held.digest == digest and intrinsics == self.intrinsics:
            return AdmitTimings(frame.name, keypoints=len(held.xy))
        if intrinsics != self.intrinsics or held is not None:
            if self.features:
                log.info("front end reset: %s", "other intrinsics" if held is None
                         else f"frame {frame.name} came back with other pixels")
            self.reset(intrinsics)
        timings = AdmitTimings(frame.name)
        t0 = time.perf_counter()
        new = self._extract(frame, digest)
        self.frames_extracted += 1
        timings.extract = time.perf_counter() - t0
        timings.keypoints = len(new.xy)
        previous = list(self.features.values())[-self.config.overlap:]
        self.features[frame.name] = new
        for old in previous:
            self._match_pair(old, new, timings)
        self.prune()
        return timings

    def reset(self, intrinsics: Intrinsics) -> None:
        """Forget every frame and pair; a new camera for ``intrinsics``."""
        import pycolmap

        self.features.clear()
        self.pairs.clear()
        self.pinned.clear()
        self.generation += 1
        self.intrinsics = intrinsics
        i = intrinsics
        # COLMAP puts pixel centres at +0.5; Intrinsics use OpenCV's integer centres.
        self.camera = pycolmap.Camera(model="PINHOLE", width=i.width, height=i.height,
                                      params=[i.fx, i.fy, i.cx + 0.5, i.cy + 0.5],
                                      camera_id=CAMERA_ID)
        self.camera.has_prior_focal_length = True  # else BA lets the focal length drift

    def prune(self) -> None:
        """Drop the frames that left every future window: older than the last ``overlap``
        frames (the next frame's match partners) and not pinned."""
        recent = set(list(self.features)[-self.config.overlap:])
        gone = [n for n in self.features if n not in recent and n not in self.pinned]
        for name in gone:
            iid = self.features.pop(name).image_id
            self.pairs = {k: v for k, v in self.pairs.items() if iid not in k}
        self.frames_dropped += len(gone)

    def ids(self, names) -> dict[str, int]:
        """Image ids of the held frames among ``names``."""
        return {n: self.features[n].image_id for n in names if n in self.features}

    # -- steps -------------------------------------------------------------------------------
    def _extract(self, frame: Frame, digest: bytes) -> FrameFeatures:
        """SIFT on the grey image (COLMAP's reader's BT.709 weights: OpenCV's 0.299 / 0.587 /
        0.114 made the mapper settle on wrong reconstructions of the test drive) downscaled as
        COLMAP's image reader does (longest side ``max_image_size``), keypoints scaled back to
        full resolution."""
        import pycolmap

        grey = np.rint(frame.image @ GREY_WEIGHTS).astype(np.uint8)
        h, w = grey.shape
        size = self.config.max_image_size
        if 0 < size < max(h, w):
            s = size / max(h, w)
            nw, nh = max(1, round(w * s)), max(1, round(h * s))
            grey = cv2.resize(grey, (nw, nh), interpolation=cv2.INTER_AREA)
        else:
            nw, nh = w, h
        kps, descs = self._extractor.extract_from_uint8_array(grey)
        xy = pycolmap.keypoints_to_matrix(kps)[:, :2].astype(np.float64)
        xy *= (w / nw, h / nh)  # COLMAP's keypoint rescale to the full image
        fid = self._next_id
        self._next_id += 1
        return FrameFeatures(frame.name, fid, xy, descs, digest)

    def _match_pair(self, a: FrameFeatures, b: FrameFeatures, timings: AdmitTimings) -> None:
        """COLMAP's SIFT matcher, then the calibrated two-view verification (Sec. 3.1)."""
        import pycolmap

        timings.pairs += 1
        if len(a.xy) == 0 or len(b.xy) == 0:
            return
        t0 = time.perf_counter()
        sift = self._sift_matching
        matches = sift_matches(a.descriptors.data, b.descriptors.data, sift.max_ratio,
                               sift.max_distance, sift.cross_check)
        timings.match += time.perf_counter() - t0
        if len(matches) < MIN_PAIR_INLIERS:
            return
        t0 = time.perf_counter()
        # RANSAC draws from COLMAP's per-thread generator: seeded, the same in any process
        pycolmap.set_random_seed(int(self.config.seed))
        tvg = pycolmap.estimate_two_view_geometry(self.camera, a.xy, self.camera, b.xy,
                                                  matches, self._verify)
        timings.verify += time.perf_counter() - t0
        inliers = tvg.inlier_matches
        if inliers is not None and len(inliers) >= MIN_PAIR_INLIERS:
            self.pairs[(a.image_id, b.image_id)] = tvg
            timings.verified += 1



SIFT_DOT_NORM = 1.0 / (512 * 512)  # COLMAP's uint8 SIFT descriptors: unit length at 512


def _best_one_way(dots: np.ndarray, max_ratio: float, max_distance: float):
    """COLMAP's one-way rule (``FindBestMatchesOneWayBruteForce``): the best neighbour by dot
    product, kept if its angle acos(dot) is within ``max_distance`` and below ``max_ratio``
    times the second best's (Lowe 2004, Sec. 7.1)."""
    best = dots.argmax(1)
    if dots.shape[1] > 1:
        top2 = -np.partition(-dots, 1, axis=1)[:, :2]
    else:
        top2 = np.concatenate([dots, np.zeros_like(dots)], 1)
    best_angle = np.arccos(np.minimum(SIFT_DOT_NORM * top2[:, 0], 1.0))
    second_angle = np.arccos(np.minimum(SIFT_DOT_NORM * top2[:, 1], 1.0))
    ok = (top2[:, 0] > 0) & (best_angle <= max_distance) & (best_angle < max_ratio * second_angle)
    return best, ok


def sift_matches(desc1: np.ndarray, desc2: np.ndarray, max_ratio: float = 0.8,
                 max_distance: float = 0.7, cross_check: bool = True) -> np.ndarray:
    """COLMAP's brute-force SIFT matching of two uint8 descriptor sets (N x 128): the one-way
    rule of :func:`_best_one_way` both ways and, with ``cross_check``, only mutual matches.
    (M, 2) uint32 indices (into desc1, into desc2), in desc1's order. Dot products of uint8
    descriptors are exact in float32 (at most 128 * 255^2 < 2^24)."""
    if len(desc1) == 0 or len(desc2) == 0:
        return np.zeros((0, 2), np.uint32)
    dots = desc1.astype(np.float32) @ desc2.astype(np.float32).T
    best12, ok12 = _best_one_way(dots, max_ratio, max_distance)
    keep = ok12
    if cross_check:
        best21, ok21 = _best_one_way(dots.T, max_ratio, max_distance)
        keep = ok12 & ok21[best12] & (best21[best12] == np.arange(len(desc1)))
    i1 = np.flatnonzero(keep)
    return np.stack([i1, best12[i1]], 1).astype(np.uint32)
