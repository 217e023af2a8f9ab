"""The torch SIFT features (core/sfm/features/sift_torch.py) and their matches
(core/sfm/features/matching_torch.py) in a COLMAP database, as hloc does with its own features:
images imported with pycolmap (one camera with the known intrinsics), keypoints and descriptors
written per image, raw matches per pair of sequential frames, the pairs verified by pycolmap's
geometric verification (calibrated two-view geometry: essential / fundamental / homography RANSAC,
COLMAP's defaults), so that pycolmap's
incremental mapper then runs on the database exactly as after its own SIFT.

Descriptors stay on the feature device for the frames that later frames are matched with (the
last ``overlap`` frames); older ones are read back from the database when needed.

On CUDA a window's frames of one size are extracted as one batch (their scale spaces built at
once: :func:`~sfm_ttr_ros.core.sfm.features.sift_torch.detect_and_describe_batch`, images copied
from pinned memory), and its new pairs are matched back to back on the device and read back
once (:func:`~sfm_ttr_ros.core.sfm.features.matching_torch.mutual_ratio_candidates`): fewer
host round trips. On the CPU one frame at a time (compute-bound there: a batch buys nothing).
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from sfm_ttr_ros.core.sfm.features.matching_torch import (
    MatchConfig,
    matches_from_candidates,
    mutual_ratio_candidates,
)
from sfm_ttr_ros.core.sfm.features.sift_torch import (
    SiftFeatures,
    TorchSiftConfig,
    detect_and_describe_batch,
)

#: Frames per extraction batch on CUDA (a window: 10-15 frames) and on the CPU.
CUDA_FEATURE_BATCH = 16
CPU_FEATURE_BATCH = 1


def default_device() -> str:
    """``cuda`` when torch sees a GPU, else ``cpu``."""
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def downscale(image: np.ndarray, max_image_size: int) -> tuple[np.ndarray, float]:
    """The image resized so that its longest side is at most ``max_image_size`` (<= 0: as it
    is), and the factor (new / old). Area interpolation, as an antialiased downscale."""
    h, w = image.shape[:2]
    if max_image_size <= 0 or max(h, w) <= max_image_size:
        return image, 1.0
    f = max_image_size / max(h, w)
    size = (max(1, round(w * f)), max(1, round(h * f)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA), size[0] / w


@dataclass
class _Cached:
    keypoints: object  # torch (N, 4), full-resolution COLMAP pixels
    descriptors: object  # torch (N, 128), unit length


class TorchFeatureDatabase:
    """Torch features and matches of the frames of one COLMAP database (one per
    :class:`~sfm_ttr_ros.core.sfm.reconstruction.SfmReconstructor` generation). ``timings``
    accumulates the seconds of the last :meth:`extract` / :meth:`match` calls by step.
    ``batch``: frames of one size extracted together (default :data:`CUDA_FEATURE_BATCH` on
    CUDA, :data:`CPU_FEATURE_BATCH` on the CPU)."""

    def __init__(self, database_path: Path, device: str | None = None,
                 sift: TorchSiftConfig | None = None, matching: MatchConfig | None = None,
                 keep: int = 12, batch: int | None = None):
        self.database_path = Path(database_path)
        self.device = device or default_device()
        cuda = str(self.device).startswith("cuda")
        self.batch = max(1, int(batch or (CUDA_FEATURE_BATCH if cuda else CPU_FEATURE_BATCH)))
        self.sift = sift or TorchSiftConfig()
        self.matching = matching or MatchConfig()
        self.keep = max(2, int(keep))
        self._cache: OrderedDict[str, _Cached] = OrderedDict()
        self._matched: set[tuple[str, str]] = set()
        self.timings: dict[str, float] = {}

    # -- extraction ------------------------------------------------------------------------
    def extract(self, images: Sequence[tuple[str, np.ndarray]], max_image_size: int) -> None:
        """Features of ``(image name in the database, RGB image)`` pairs (already imported
        into the database) written as keypoints (x, y, scale, orientation) and uint8 SIFT
        descriptors."""
        import pycolmap

        t0 = time.perf_counter()
        small = [(name, *downscale(image, max_image_size)) for name, image in images]
        feats: list[tuple[str, SiftFeatures, float]] = []
        for group in _runs(small, self.batch):
            found = detect_and_describe_batch([im for _, im, _ in group], self.sift, self.device)
            feats += [(name, sf, f) for (name, _, f), sf in zip(group, found, strict=True)]
        self._sync()
        t1 = time.perf_counter()
        with pycolmap.Database.open(self.database_path) as db:
            ids = {img.name: int(img.image_id) for img in db.read_all_images()}
            for name, sf, f in feats:
                kp = sf.keypoints.clone()
                kp[:, :3] /= f  # x, y, scale in full-resolution pixels
                db.write_keypoints(ids[name], kp.cpu().numpy().astype(np.float32))
                db.write_descriptors(ids[name], pycolmap.FeatureDescriptors(
                    pycolmap.FeatureExtractorType.SIFT, sf.descriptors_uint8()))
                self._remember(name, _Cached(kp, sf.descriptors))
        self.timings = {"detect_describe": t1 - t0, "write": time.perf_counter() - t1}

    def _remember(self, name: str, item: _Cached) -> None:
        self._cache[name] = item
        self._cache.move_to_end(name)
        while len(self._cache) > self.keep:
            self._cache.popitem(last=False)

    def _features(self, db, name: str, image_id: int) -> _Cached:
        if name in self._cache:
            return self._cache[name]
        import torch

        kp = torch.from_numpy(np.asarray(db.read_keypoints(image_id), np.float32))
        raw = db.read_descriptors(image_id)
        d = np.asarray(getattr(raw, "data", raw), np.float32)
        d = torch.from_numpy(d)
        d = d / d.norm(dim=1, keepdim=True).clamp_min(1e-12)
        return _Cached(kp.to(self.device), d.to(self.device))

    def _sync(self) -> None:
        if self.device.startswith("cuda"):
            import torch

            torch.cuda.synchronize()

    # -- matching and verification -----------------------------------------------------------
    def match(self, names: Sequence[str], overlap: int, num_threads: int = 2,
              token=None, check=None) -> int:
        """Match every pair of ``names`` (database image names, in stream order) at most
        ``overlap`` apart that is not matched yet (sequential matching) and write the raw
        matches; then pycolmap's geometric verification (``pycolmap.geometric_verification``:
        calibrated two-view geometry per pair, COLMAP's defaults, ``num_threads`` threads; pairs
        verified before are skipped) writes each new pair's two-view geometry. ``check()`` runs
        between pairs (cancellation). Returns the number of pairs matched."""
        import pycolmap

        t0 = time.perf_counter()
        with pycolmap.Database.open(self.database_path) as db:
            ids = {img.name: int(img.image_id) for img in db.read_all_images()}
            pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:i + 1 + overlap]
                     if (a, b) not in self._matched]
            candidates = []
            for a, b in pairs:
                if check is not None:
                    check()
                fa, fb = self._features(db, a, ids[a]), self._features(db, b, ids[b])
                candidates.append(mutual_ratio_candidates(fa.descriptors, fb.descriptors,
                                                          self.matching)
                                  if len(fa.descriptors) and len(fb.descriptors) >= 2 else None)
            for (a, b), m in zip(pairs, _read_matches(candidates), strict=True):
                db.write_matches(ids[a], ids[b], m.astype(np.uint32))
                self._matched.add((a, b))
        done = len(pairs)
        t1 = time.perf_counter()
        if done:
            verifier = pycolmap.GeometricVerifierOptions()
            verifier.num_threads = int(num_threads)
            pycolmap.geometric_verification(self.database_path, verifier_options=verifier,
                                            cancellation_token=token)
        self.timings = {"match": t1 - t0, "verify": time.perf_counter() - t1}
        return done


def _runs(items: list[tuple[str, np.ndarray, float]], batch: int):
    """Consecutive runs of at most ``batch`` (name, image, factor) items of one image size."""
    run: list[tuple[str, np.ndarray, float]] = []
    for item in items:
        if run and (len(run) == batch or run[0][1].shape != item[1].shape):
            yield run
            run = []
        run.append(item)
    if run:
        yield run


def _read_matches(candidates: list) -> list[np.ndarray]:
    """Every pair's (M, 2) matches from its device candidates (None: no match possible), the
    device read once for all pairs."""
    import torch

    real = [c for c in candidates if c is not None]
    if real:
        best = torch.cat([b for b, _ in real]).cpu().numpy()
        keep = torch.cat([k for _, k in real]).cpu().numpy()
        sizes = np.cumsum([len(b) for b, _ in real])[:-1]
        parts = iter(zip(np.split(best, sizes), np.split(keep, sizes), strict=True))
    none = np.zeros((0, 2), np.int64)
    return [none if c is None else matches_from_candidates(*next(parts)) for c in candidates]
