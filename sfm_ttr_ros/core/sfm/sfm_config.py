"""The SfM stage's options (Sec. 3.1: one fixed PINHOLE camera, SIFT, sequential matching,
incremental mapping) and the values pycolmap is known to refuse."""

from __future__ import annotations

from dataclasses import dataclass

from sfm_ttr_ros.core.errors import InputError

MIN_MAX_IMAGE_SIZE = 16  # smallest SIFT downscale accepted (1 crashes pycolmap 4.2.1)
FEATURE_BACKENDS = ("colmap", "torch")  # sfm.features
SFM_MODES = ("batch", "streaming")  # sfm.mode
#: a verified pair with fewer inliers is not kept (the streaming front end) nor counted by
#: the batch mapper's prechecks
MIN_PAIR_INLIERS = 15
RETRY_HISTORY = 10  # reconstructions of the stream whose median error sfm.retry_above_ratio scales


@dataclass
class SfmConfig:
    """Options of the SfM stage (defaults: measured on KITTI-like data, see BENCHMARKS.md)."""

    max_image_size: int = 640  # SIFT runs on images downscaled to this longest side; <=0: full
    max_num_features: int = 8192
    first_octave: int = 0  # -1: COLMAP default (upsampled first octave); 0: ~3x faster
    num_threads: int = 2
    # sequential matching: each frame with the next `overlap` frames (COLMAP's 10: the paper's
    # profiles; 5 measured better on hololens_000 and half the matching: docs/decisions.md)
    overlap: int = 5
    init_min_tri_angle: float = 1.0  # degrees; COLMAP's 16 rejects consecutive driving frames
    init_min_num_inliers: int = 50
    init_max_forward_motion: float = 1.0  # COLMAP's 0.95 rejects forward motion
    min_tri_angle: float = 0.5  # filter / triangulation angle in degrees
    max_reproj_error: float = 4.0  # px, COLMAP's filter
    refine_intrinsics: bool = False  # hold the known intrinsics fixed (paper: better than not)
    min_registered: int = 2  # fewer registered frames than this: the window failed
    min_points: int = 20  # fewer 3D points than this: the window failed
    min_parallax_px: float = 1.0  # cheap pre-check on matched keypoint motion (full-res px)
    # The mapper, run again with the next seed while the best reconstruction so far has a mean
    # reprojection error above retry_above_error px (0: every attempt runs), keeps the best
    # (most frames registered, then the lowest error): see core/sfm/mapping.py.
    mapping_attempts: int = 2
    retry_above_error: float = 0.8
    # ... or above this many times the median error of the stream's last RETRY_HISTORY
    # reconstructions (a camera whose reconstructions fit better than 0.8 px); 0: off
    retry_above_ratio: float = 1.3
    seed: int = 0
    verbose: bool = False
    # "colmap": pycolmap's SIFT and sequential matcher on the CPU (the reference); "torch": the
    # weight-free torch SIFT of core/sfm/features/sift_torch.py and mutual nearest-neighbour + ratio
    # matching on the accelerator when there is one, the matches verified by pycolmap
    features: str = "colmap"
    # "batch": each window's SfM after its last frame (features, matching, a fresh mapping of
    # the window: core/sfm/reconstruction.py); "streaming": each keyframe's features, matches
    # and registration into one map carried across windows as the stream takes it, a window
    # then only maps what is left (core/sfm/streaming_map.py; pycolmap's SIFT only)
    mode: str = "streaming"

    def __post_init__(self) -> None:
        # Values that reach pycolmap options known to end the process or to fail every window
        # (measured with pycolmap 4.2.1: max_image_size 1 segfaults in SIFT extraction,
        # init_min_tri_angle 0 fails the mapper's options check). Loop detection, which aborts
        # offline, is never enabled (core/sfm/extraction.py) and no option reaches it.
        if 0 < int(self.max_image_size) < MIN_MAX_IMAGE_SIZE:
            raise InputError(f"sfm.max_image_size must be 0 (full size) or >= "
                             f"{MIN_MAX_IMAGE_SIZE}, got {self.max_image_size}")
        if not float(self.init_min_tri_angle) > 0:
            raise InputError(f"sfm.init_min_tri_angle must be > 0, got "
                             f"{self.init_min_tri_angle}")
        if self.features not in FEATURE_BACKENDS:
            raise InputError(f"sfm.features must be one of {list(FEATURE_BACKENDS)}, got "
                             f"{self.features!r}")
        if self.mode not in SFM_MODES:
            raise InputError(f"sfm.mode must be one of {list(SFM_MODES)}, got {self.mode!r}")
        if self.mode == "streaming" and self.features != "colmap":
            raise InputError("sfm.mode streaming extracts pycolmap's SIFT as each keyframe "
                             f"arrives: it needs sfm.features colmap, got {self.features!r} "
                             "(torch features: set sfm.mode batch too)")
        if int(self.mapping_attempts) < 1:
            raise InputError(f"sfm.mapping_attempts must be >= 1, got {self.mapping_attempts}")
        for name in ("retry_above_error", "retry_above_ratio"):
            if not float(getattr(self, name)) >= 0:
                raise InputError(f"sfm.{name} must be >= 0, got {getattr(self, name)}")
