"""The torch SIFT features (core/sfm/features/sift_torch.py) and their matches
(core/sfm/features/matching_torch.py) in a COLMAP database, as hloc does with its own features:
images imported with pycolmap (one camera with the known intrinsics), keypoints and descriptors
written per image, raw matches per pair of sequential frames, the pairs verified by pycolmap's
geometric verification (calibrated two-view geometry: essential / fundamental / homography RANSAC,
COLMAP's defaults), so that pycolmap's
incremental mapper then runs on the database exactly as after its own SIFT.

Descriptors stay on the feature device for the frames that later frames are matched with (the
last ``overlap`` frames); older ones are read back from the database when needed.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from sfm_ttr_ros.core.sfm.features.matching_torch import MatchConfig, match_mutual_ratio
from sfm_ttr_ros.core.sfm.features.sift_torch import (
    SiftFeatures,
    TorchSiftConfig,
    detect_and_describe,
)


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
    accumulates the seconds of the last :meth:`extract` / :meth:`match` calls by step."""

    def __init__(self, database_path: Path, device: str | None = None,
                 sift: TorchSiftConfig | None = None, matching: MatchConfig | None = None,
                 keep: int = 12):
        self.database_path = Path(database_path)
        self.device = device or default_device()
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
        feats: list[tuple[str, SiftFeatures, float]] = []
        for name, image in images:
            small, f = downscale(image, max_image_size)
            sf = detect_and_describe(small, self.sift, self.device)
            feats.append((name, sf, f))
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
        done = 0
        with pycolmap.Database.open(self.database_path) as db:
            ids = {img.name: int(img.image_id) for img in db.read_all_images()}
            for i, a in enumerate(names):
                for b in names[i + 1:i + 1 + overlap]:
                    if (a, b) in self._matched:
                        continue
                    if check is not None:
                        check()
                    fa, fb = self._features(db, a, ids[a]), self._features(db, b, ids[b])
                    m = match_mutual_ratio(fa.descriptors, fb.descriptors, self.matching)
                    db.write_matches(ids[a], ids[b], m.astype(np.uint32))
                    self._matched.add((a, b))
                    done += 1
        t1 = time.perf_counter()
        if done:
            verifier = pycolmap.GeometricVerifierOptions()
            verifier.num_threads = int(num_threads)
            pycolmap.geometric_verification(self.database_path, verifier_options=verifier,
                                            cancellation_token=token)
        self.timings = {"match": t1 - t0, "verify": time.perf_counter() - t1}
        return done
