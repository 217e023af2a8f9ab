"""Where a reconstructor keeps its window's COLMAP data across the windows of a stream.

One folder per generation (``ws0``, ``ws1``, ...) holding ``images/`` (written for extraction,
deleted once the keypoints are in) and ``database.db`` (features, matches, two-view
geometries), with what the database holds: its frames in insertion order, the digest of the
pixels each was extracted from, and its one camera. A new generation starts from an empty
database (:meth:`SfmWorkspace.reset`).
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path


class SfmWorkspace:
    """The folder (a temporary one unless given) and the database's frames."""

    def __init__(self, root: str | Path | None = None):
        self.own = root is None  # a temporary folder: removed by close()
        self.root = Path(root or tempfile.mkdtemp(prefix="sfm_ttr_"))
        self.generation = 0
        self.names: list[str] = []  # frames in the database, in insertion order
        self.digests: dict[str, bytes] = {}  # name -> digest of the pixels it was extracted from
        self.camera_id: int | None = None

    @property
    def path(self) -> Path:
        return self.root / f"ws{self.generation}"

    @property
    def database_path(self) -> Path:
        return self.path / "database.db"

    @property
    def image_dir(self) -> Path:
        return self.path / "images"

    def reset(self) -> None:
        """A new, empty database in the next generation's folder."""
        shutil.rmtree(self.path, ignore_errors=True)
        self.generation += 1
        self.names = []
        self.digests = {}
        self.camera_id = None

    def full(self, keep: set[str], max_cached_frames: int) -> bool:
        """Whether the database holds more than ``max_cached_frames`` frames, some of them
        outside ``keep`` (then a fresh one bounds it)."""
        return len(self.names) > max_cached_frames and not keep.issuperset(self.names)

    def close(self) -> None:
        if self.own:
            shutil.rmtree(self.root, ignore_errors=True)
