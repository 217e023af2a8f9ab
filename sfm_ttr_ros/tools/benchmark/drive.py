"""The generated drives the speed measurement runs over (:mod:`.speed`), read as the benchmark
reads a sequence (``frame(i)``, ``gt(name)``, ``names``, ``intrinsics``, ``stamps``), so that
the benchmark's runners take them as they take a KITTI drive:

* :class:`GeneratedDrive`: a drive of :func:`~sfm_ttr_ros.data.synthetic.render_sequence` held
  in memory with its exact depths, rendered once and cached as an .npz (:func:`load_drive`);
* :class:`StreetStream`: a long drive rendered one frame at a time as it is read
  (:func:`~sfm_ttr_ros.data.synthetic.street_frames`), nothing of it kept, no ground truth."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Frame, Intrinsics

log = logging.getLogger("sfm_ttr_ros.tools.benchmark")


def _names(n: int) -> list[str]:
    return [f"{i:06d}" for i in range(n)]


@dataclass
class GeneratedDrive:
    """A rendered drive: images (uint8 RGB), exact depths (metres, 0 = none), 10 Hz stamps."""

    images: np.ndarray  # N x H x W x 3 uint8
    depths: np.ndarray  # N x H x W float32
    intrinsics: Intrinsics
    stamps: np.ndarray  # N float64
    info: dict[str, Any] = field(default_factory=dict)
    poses = None  # no odometry

    def __len__(self) -> int:
        return int(self.images.shape[0])

    @property
    def names(self) -> list[str]:
        return _names(len(self))

    def frame(self, i: int) -> Frame:
        return Frame(index=i, image=self.images[i], stamp=float(self.stamps[i]),
                     name=f"{i:06d}")

    def gt(self, name: str) -> np.ndarray:
        return self.depths[int(name)]


class StreetStream:
    """``frames`` frames of the street of ``params`` rendered one at a time, in order, as they
    are read (a long stream's memory is the stream's own, not the drive's)."""

    poses = None

    def __init__(self, params, frames: int, width: int, height: int, seed: int):
        from sfm_ttr_ros.data.synthetic import scene_intrinsics, street_frames

        self.intrinsics = scene_intrinsics(params, int(width), int(height))
        self._frames = street_frames(params, frames, width, height, seed=seed)
        self._n = frames
        self._next = 0
        self.stamps: list[float] = []

    def __len__(self) -> int:
        return self._n

    @property
    def names(self) -> list[str]:
        return _names(self._n)

    def frame(self, i: int) -> Frame:
        if i != self._next:
            raise InputError(f"a street stream is read in order: frame {i} asked, "
                             f"{self._next} next")
        image, _, stamp = next(self._frames)
        self._next += 1
        self.stamps.append(stamp)
        return Frame(index=i, image=image, stamp=stamp, name=f"{i:06d}")

    def gt(self, name: str) -> None:
        return None


def _cache_name(domain: str, seed: int, frames: int, width: int, height: int) -> str:
    return f"drive_{domain}_s{seed}_{width}x{height}_n{frames}.npz"


def _from_cache(cache: Path, info: dict[str, Any], progress) -> GeneratedDrive | None:
    """A cached drive of the same scene and size with at least ``info['frames']`` frames (its
    first frames are the same frames), or None."""
    frames = info["frames"]
    prefix = f"drive_{info['domain']}_s{info['seed']}_{info['width']}x{info['height']}_n"
    for p in sorted(cache.glob(prefix + "*.npz")):
        try:
            n = int(p.stem.rsplit("_n", 1)[1])
        except ValueError:
            continue
        if n < frames:
            continue
        try:
            with np.load(p) as z:
                k = z["intrinsics"]
                drive = GeneratedDrive(
                    z["images"][:frames].copy(), z["depths"][:frames].copy(),
                    Intrinsics(*(float(v) for v in k[:4]), int(k[4]), int(k[5])),
                    z["stamps"][:frames].copy(), {**info, "cache": str(p)})
        except Exception as exc:  # a broken cache file: render again
            log.warning("ignoring unreadable cache %s: %s", p, exc)
            continue
        if progress:
            progress(f"drive {info['domain']}/{info['seed']}: {frames} frames from {p}")
        return drive
    return None


def load_drive(domain: str = "B", seed: int = 3, frames: int = 60, width: int = 1242,
               height: int = 375, cache_dir: str | Path | None = None,
               progress: Callable[[str], None] | None = None) -> GeneratedDrive:
    """The first ``frames`` frames of the drive of scene ``seed`` in ``domain``; rendered once
    and cached in ``cache_dir`` as an .npz (a cached longer drive of the same scene and size is
    reused). ``cache_dir`` None or "": no cache."""
    from sfm_ttr_ros.data.synthetic import render_sequence, sample_scene_params

    if frames < 2:
        raise InputError(f"need at least 2 frames, got {frames}")
    info = {"domain": domain, "seed": int(seed), "frames": int(frames), "width": int(width),
            "height": int(height)}
    cache = Path(cache_dir) if cache_dir not in (None, "") else None
    if cache is not None and cache.is_dir():
        found = _from_cache(cache, info, progress)
        if found is not None:
            return found
    if progress:
        progress(f"rendering drive {domain}/{seed}: {frames} frames of {width}x{height}")
    t0 = time.perf_counter()
    seq = render_sequence(sample_scene_params(seed, domain), frames, width, height, seed=seed)
    k = seq.intrinsics
    drive = GeneratedDrive(np.stack(seq.images), np.stack(seq.depths).astype(np.float32), k,
                           np.asarray(seq.stamps, np.float64), dict(info))
    drive.info["render_seconds"] = round(time.perf_counter() - t0, 1)
    if cache is not None:
        cache.mkdir(parents=True, exist_ok=True)
        path = cache / _cache_name(domain, seed, frames, width, height)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, images=drive.images, depths=drive.depths, stamps=drive.stamps,
                 intrinsics=np.array([k.fx, k.fy, k.cx, k.cy, k.width, k.height], np.float64))
        os.replace(tmp, path)
        drive.info["cache"] = str(path)
    return drive
