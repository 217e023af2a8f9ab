"""A sequence to run SfM-TTR over: a KITTI raw drive, or a folder of images with a K file,
each optionally with ground-truth depth PNGs."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Frame, Intrinsics, list_images, load_rgb
from sfm_ttr_ros.data.poses import POSES_FILE, read_frame_poses


@dataclass
class ImageSequence:
    """Frames of one camera with known intrinsics; ``gt_paths`` maps frame name → GT PNG;
    ``poses`` (N x 4 x 4 camera-to-world, metres) when the sequence has a ``poses.txt``: an
    odometry source for the metric scale (core/metric/odometry_track.py)."""

    name: str
    image_paths: list[Path]
    intrinsics: Intrinsics
    stamps: list[float]
    gt_paths: dict[str, Path] = field(default_factory=dict)
    gt_scale: float = 256.0
    poses: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.image_paths)

    @property
    def names(self) -> list[str]:
        return [p.stem for p in self.image_paths]

    def frame(self, i: int) -> Frame:
        image = load_rgb(self.image_paths[i])
        if image.shape[1] != self.intrinsics.width or image.shape[0] != self.intrinsics.height:
            raise InputError(
                f"{self.image_paths[i]} is {image.shape[1]}x{image.shape[0]}, the sequence's "
                f"intrinsics are for {self.intrinsics.width}x{self.intrinsics.height}")
        return Frame(index=i, image=image, stamp=self.stamps[i], name=self.image_paths[i].stem)

    def frames(self, start: int = 0, stop: int | None = None) -> list[Frame]:
        return [self.frame(i) for i in range(start, len(self) if stop is None else stop)]

    def gt(self, name: str) -> np.ndarray | None:
        """Ground-truth depth in metres (0 = none), or None when the frame has no GT file."""
        from sfm_ttr_ros.data.kitti import read_depth_png

        path = self.gt_paths.get(name)
        return None if path is None else read_depth_png(path, self.gt_scale)


def open_kitti(raw_root: str | Path, drive: str, gt_root: str | Path | None = None,
               camera: str = "02") -> ImageSequence:
    """A KITTI raw drive (``camera`` 02 = left colour camera, 03 = right) with improved GT
    when given."""
    from sfm_ttr_ros.data.kitti import KittiDrive

    kd = KittiDrive(raw_root, drive, gt_root=gt_root, camera=camera)
    paths = [Path(kd.image_path(i)) for i in range(len(kd.frame_names))]
    gt = {}
    for i, name in enumerate(kd.frame_names):
        p = kd.gt_path(i)
        if p is not None:
            gt[name] = Path(p)
    _, poses = kd.poses()  # poses.txt, or a real drive's GPS/IMU (the distance travelled)
    return ImageSequence(drive, paths, kd.intrinsics, list(kd.stamps), gt, 256.0, poses)


def open_image_folder(images: str | Path, intrinsics: str | Path,
                      gt_depth: str | Path | None = None, gt_scale: float = 256.0,
                      fps: float = 10.0) -> ImageSequence:
    """Sorted images of a folder, a K file (3x3 or fx fy cx cy), GT PNGs of the same stems."""
    paths = list_images(images)
    first = load_rgb(paths[0])
    intr = Intrinsics.from_file(intrinsics, first.shape[1], first.shape[0])
    gt: dict[str, Path] = {}
    if gt_depth is not None:
        gdir = Path(gt_depth)
        if not gdir.is_dir():
            raise InputError(f"GT depth folder not found: {gdir}")
        for p in paths:
            q = gdir / f"{p.stem}.png"
            if q.is_file():
                gt[p.stem] = q
    stamps = [i / fps for i in range(len(paths))]
    return ImageSequence(Path(images).resolve().parent.name or "images", paths, intr, stamps,
                         gt, float(gt_scale), read_frame_poses(
                             Path(images).parent / POSES_FILE, len(paths)))
