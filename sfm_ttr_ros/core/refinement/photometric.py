"""Monodepth2's self-supervised photometric loss, with the camera poses taken from SfM.

This is the loss of photometric test-time refinement (Ph-TTR, the baseline SfM-TTR is compared
with: Izquierdo & Civera, CVPR 2023, Sec. 5-6 and Fig. 4) and the photometric half of the hybrid
SfM + photometric refinement. Notation: target frame t, source frames s (the window's
neighbours t-1, t+1 by default), depth D_t of the target in the network's units, intrinsics K
in pixels AT THE NETWORK'S INPUT SIZE, T_{s<-t} the rigid transform of target-camera points into
source-camera points.

Warp (Monodepth2 layers.py BackprojectDepth / Project3D), for every target pixel p:

    P = D_t(p) · K⁻¹ p̃,   q̃ = K (R_{s<-t} P + t_{s<-t}),   I_{s→t}(p) = I_s(q / (q_z + 1e-7))

sampled bilinearly with "border" padding after normalising x by (W − 1) and y by (H − 1), i.e.
the ``align_corners=True`` convention with pixel centres at integers (the repository's
convention, see :class:`~sfm_ttr_ros.core.frames.Intrinsics`).

Per-pixel error (Monodepth2 trainer.py compute_reprojection_loss), α = 0.85:

    pe(a, b) = α · mean_RGB( clamp((1 − SSIM(a, b)) / 2, 0, 1) ) + (1 − α) · mean_RGB |a − b|

with SSIM on 3 x 3 averages of reflection-padded images, C1 = 0.01², C2 = 0.03².

Photometric term: the per-pixel minimum over the sources, L_p = mean_p min_s pe(I_t, I_{s→t}).
With auto-masking the identity errors pe(I_t, I_s) (un-warped source, plus N(0, 1)·1e-5 noise to
break ties) join that minimum: pixels that a raw source already explains (static camera, objects
moving with the camera) fall back to an identity error and get no depth gradient.

Smoothness (Monodepth2 layers.py get_smooth_loss), on the disparity d* = d / mean(d):

    L_s = mean |∂x d*| · exp(−mean_RGB |∂x I_t|) + mean |∂y d*| · exp(−mean_RGB |∂y I_t|)

Several output scales (Monodepth2's default): each scale's disparity is upsampled (bilinear) to
the full input size before it becomes depth and is warped; the smoothness term uses the scale's
native-resolution disparity and the target resized to it, weighted by w_s / 2^scale; the total
is the mean over the scales: L = 1/|S| Σ_scale (L_p + w_s / 2^scale · L_s), w_s = 1e-3.

Where this differs from Ph-TTR as ManyDepth (Watson et al., CVPR 2021) and McCraith et al.
(2020) run it: they refine a pose network together with the depth encoder, so the poses are
learnt, drift with the depth network's scale and cost a second network per step. Here the poses
are the window's SfM poses (no pose network): they are fixed, consistent across the window,
brought into the network's depth units with the window's alignment scale ŝ (the same ŝ that
scales the SfM depth targets of SfM-TTR), and a step costs only the depth network. Frames SfM
did not register have no pose and give no photometric term.

Where this differs from Monodepth2's training: no colour or flip augmentation (the network sees
the test image as it is), multi-scale only when the decoder has several disparity heads (the
networks here run scale 0 only by default: ``decoder.output_scales = (0,)``; ask for more with
``scales``), smoothness on the network's own disparity (its sigmoid output when the decoder
returns Monodepth2's dict, else 1 / depth), and intrinsics in pixels at the network's input size
(:func:`network_intrinsics`) rather than Monodepth2's normalised KITTI K.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Intrinsics
from sfm_ttr_ros.core.models.base import DepthModel

ALPHA = 0.85  # weight of the SSIM term in pe (Monodepth2)
SSIM_C1 = 0.01 ** 2
SSIM_C2 = 0.03 ** 2
SMOOTHNESS_WEIGHT = 1e-3  # Monodepth2's disparity_smoothness
IDENTITY_NOISE = 1e-5  # std of the tie-breaking noise added to the identity errors
PROJECTION_EPS = 1e-7  # added to z before the perspective division (Monodepth2)
SOURCE_OFFSETS = (-1, 1)  # the window's neighbours t-1, t+1 (Monodepth2's frame_ids [0, -1, 1])


@dataclass(frozen=True)
class PhotometricConfig:
    """The photometric loss's settings (Monodepth2's defaults).

    ``source_offsets``: which window neighbours of the target are sources (frame index
    offsets, non-zero). ``scales``: the decoder's output scales used (0 = full resolution).
    ``seed``: of the auto-masking noise (deterministic losses)."""

    alpha: float = ALPHA
    automask: bool = True
    smoothness_weight: float = SMOOTHNESS_WEIGHT
    source_offsets: tuple[int, ...] = SOURCE_OFFSETS
    scales: tuple[int, ...] = (0,)
    seed: int = 0

    def __post_init__(self) -> None:
        if not (isinstance(self.alpha, (int, float)) and 0.0 <= self.alpha <= 1.0):
            raise InputError(f"photometric alpha must lie in [0, 1], got {self.alpha!r}")
        if not (isinstance(self.smoothness_weight, (int, float))
                and math.isfinite(self.smoothness_weight) and self.smoothness_weight >= 0):
            raise InputError(f"smoothness_weight must be a number >= 0, got "
                             f"{self.smoothness_weight!r}")
        offsets = tuple(int(o) for o in self.source_offsets)
        if not offsets or 0 in offsets or len(set(offsets)) != len(offsets):
            raise InputError(f"source_offsets must be distinct non-zero frame offsets, got "
                             f"{self.source_offsets!r}")
        scales = tuple(int(s) for s in self.scales)
        if not scales or min(scales) < 0 or len(set(scales)) != len(scales):
            raise InputError(f"scales must be distinct output scales >= 0, got {self.scales!r}")
        object.__setattr__(self, "source_offsets", offsets)
        object.__setattr__(self, "scales", scales)


def parse_offsets(text: str | Iterable[int]) -> tuple[int, ...]:
    """Source offsets from the parameter text ``"-1,1"`` (comma- or space-separated integers;
    a sequence of integers is taken as it is). :class:`InputError` when a piece is no integer;
    :class:`PhotometricConfig` checks the rest (non-zero, distinct)."""
    if isinstance(text, str):
        pieces = [p for p in text.replace(",", " ").split() if p]
        try:
            return tuple(int(p) for p in pieces)
        except ValueError:
            raise InputError(f"source offsets must be integers separated by commas, e.g. "
                             f"\"-1,1\"; got {text!r}") from None
    return tuple(int(o) for o in text)


@dataclass
class PhotometricMaps:
    """Per-pixel by-products of :func:`photometric_loss` (N x 1 x H x W each), for tests and
    figures. ``source_index``: the winning warped source (0 … S−1), −1 where an identity error
    won (auto-masked) or where no source was valid."""

    min_error: torch.Tensor  # the min map whose mean is the loss (inf where no term was valid)
    identity_mask: torch.Tensor  # bool, True where auto-masking removed the pixel
    source_index: torch.Tensor  # int64


@dataclass
class ScaleOutput:
    """One decoder output scale: ``depth`` N x 1 x H x W at the full input size (for the warp),
    ``disp`` N x 1 x h x w the disparity at the scale's own resolution (for the smoothness)."""

    scale: int
    depth: torch.Tensor
    disp: torch.Tensor


@dataclass
class PhotometricFrame:
    """Everything a refinement step needs for one target frame's photometric term, prepared
    once per window: network-size images in [0, 1] (1 x 3 x h x w), poses T_{s<-t} in
    network depth units, K at the network's input size, the identity errors (auto-masking)."""

    name: str
    target: torch.Tensor
    sources: list[torch.Tensor]
    source_names: list[str]
    poses: list[np.ndarray]
    K: np.ndarray
    identity: torch.Tensor | None
    ssim_target: SsimTarget | None = None  # the target's share of every step's SSIM
    # K, K⁻¹ and the poses as float32 tensors on the target's device, made once: a step then
    # neither copies them to the device nor inverts K (which syncs with the host on CUDA)
    K_device: torch.Tensor = field(init=False, repr=False)
    K_inv: torch.Tensor = field(init=False, repr=False)
    poses_device: list[torch.Tensor] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        def on_device(a) -> torch.Tensor:
            return torch.as_tensor(np.asarray(a)).to(device=self.target.device,
                                                     dtype=self.target.dtype)

        self.K_device = on_device(self.K)
        self.K_inv = torch.linalg.inv(self.K_device)
        self.poses_device = [on_device(T) for T in self.poses]


@dataclass
class PhotometricTerms:
    """``total`` = mean over scales of (photometric + w_s / 2^scale · smoothness); the two
    parts are those means too (for logging)."""

    total: torch.Tensor
    photometric: torch.Tensor
    smoothness: torch.Tensor


# -- per-pixel errors ---------------------------------------------------------------------------

@dataclass(frozen=True)
class SsimTarget:
    """The fixed image's share of :func:`ssim_term`: the image reflection-padded by 1, its 3 x 3
    mean μ_y and variance σ_y². A refinement compares the same target with a new warped source
    at every step: computed once per frame, they save two of the five 3 x 3 means a step."""

    padded: torch.Tensor
    mu: torch.Tensor
    sigma: torch.Tensor


def mean_3x3(x: torch.Tensor) -> torch.Tensor:
    """The 3 x 3 mean of every full 3 x 3 neighbourhood (``avg_pool2d(x, 3, 1)``: H − 2 x W − 2)
    as two separable sums of shifted slices: equal within float rounding, ~8x faster forward
    and ~5x with the backward pass than ``avg_pool2d`` on CPU (SSIM runs five a step)."""
    rows = x[..., :, :-2] + x[..., :, 1:-1] + x[..., :, 2:]
    return (rows[..., :-2, :] + rows[..., 1:-1, :] + rows[..., 2:, :]) / 9


def ssim_target(y: torch.Tensor) -> SsimTarget:
    """:class:`SsimTarget` of ``y`` (N x C x H x W in [0, 1])."""
    y = F.pad(y, (1, 1, 1, 1), mode="reflect")
    mu_y = mean_3x3(y)
    return SsimTarget(y, mu_y, mean_3x3(y * y) - mu_y * mu_y)


def ssim_term(x: torch.Tensor, y: torch.Tensor,
              target: SsimTarget | None = None) -> torch.Tensor:
    """clamp((1 − SSIM(x, y)) / 2, 0, 1) per pixel and channel (Monodepth2 layers.py SSIM):
    3 x 3 means of the inputs reflection-padded by 1 (full-size map), C1 = 0.01², C2 = 0.03²;
    images in [0, 1]. ``target``: ``y``'s precomputed :func:`ssim_target` (same numbers)."""
    x = F.pad(x, (1, 1, 1, 1), mode="reflect")
    if target is None:
        target = ssim_target(y)
    elif target.padded.shape[-2:] != x.shape[-2:] or target.padded.shape[1] != x.shape[1]:
        raise InputError(f"SSIM target statistics of {tuple(target.padded.shape)} (padded) do "
                         f"not fit an image of {tuple(x.shape)} (padded)")
    mu_y, sigma_y = target.mu, target.sigma
    mu_x = mean_3x3(x)
    sigma_x = mean_3x3(x * x) - mu_x * mu_x
    sigma_xy = mean_3x3(x * target.padded) - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * sigma_xy + SSIM_C2)
    den = (mu_x * mu_x + mu_y * mu_y + SSIM_C1) * (sigma_x + sigma_y + SSIM_C2)
    return torch.clamp((1 - num / den) / 2, 0, 1)


def reprojection_error(pred: torch.Tensor, target: torch.Tensor, alpha: float = ALPHA,
                       target_stats: SsimTarget | None = None) -> torch.Tensor:
    """pe = α·mean_RGB(SSIM term) + (1 − α)·mean_RGB|pred − target|, N x 1 x H x W
    (``target_stats``: the target's :func:`ssim_target`, if already computed)."""
    l1 = (target - pred).abs().mean(1, keepdim=True)
    if alpha == 0:
        return l1
    return (alpha * ssim_term(pred, target, target_stats).mean(1, keepdim=True)
            + (1 - alpha) * l1)


# -- geometry -----------------------------------------------------------------------------------

def _batched(matrix, n: int, size: int, like: torch.Tensor, what: str) -> torch.Tensor:
    """A size x size matrix (numpy or torch, or N of them) as an N x size x size tensor."""
    m = torch.as_tensor(np.asarray(matrix) if not torch.is_tensor(matrix) else matrix)
    m = m.to(device=like.device, dtype=like.dtype)
    if m.shape == (size, size):
        m = m.expand(n, size, size)
    if m.shape != (n, size, size):
        raise InputError(f"{what} must be {size}x{size} or {n}x{size}x{size}, got "
                         f"{tuple(m.shape)}")
    return m


def warp(source_image: torch.Tensor, depth_target: torch.Tensor, K,
         T_source_from_target, K_inv: torch.Tensor | None = None
         ) -> tuple[torch.Tensor, torch.Tensor]:
    """The source image seen from the target camera, I_{s→t}, and where it is valid.

    ``source_image`` N x C x H x W, ``depth_target`` N x 1 x H x W (same H x W), ``K`` 3 x 3
    (or N x 3 x 3) in pixels at that size, ``T_source_from_target`` 4 x 4 (or N x 4 x 4)
    mapping target-camera points to source-camera points, translation in depth units.

    Back-projects every target pixel (centres at integers) with its depth and K⁻¹, moves it
    with T, projects it with K (divided by z + 1e-7) and samples the source bilinearly with
    "border" padding. Coordinates are normalised by (W − 1) and (H − 1): Monodepth2's
    convention, which is PyTorch's ``align_corners=True``. Returns (warped N x C x H x W,
    valid N x 1 x H x W bool: the point lies in front of the source camera). Points that project
    outside the image are not masked (Monodepth2: border padding). ``K_inv``: K⁻¹ computed
    before (a tensor on the device: no inversion per call; ``torch.linalg.inv`` syncs with the
    host on CUDA)."""
    if source_image.ndim != 4 or depth_target.ndim != 4 or depth_target.shape[1] != 1:
        raise InputError(f"warp needs an N x C x H x W image and an N x 1 x H x W depth, got "
                         f"{tuple(source_image.shape)} and {tuple(depth_target.shape)}")
    n, _, h, w = depth_target.shape
    if source_image.shape[0] != n or source_image.shape[-2:] != depth_target.shape[-2:]:
        raise InputError(f"source image {tuple(source_image.shape)} and target depth "
                         f"{tuple(depth_target.shape)} differ in batch or size")
    uv, cam = _project(depth_target, K, T_source_from_target, K_inv)
    grid = torch.stack([uv[:, 0] / (w - 1) * 2 - 1, uv[:, 1] / (h - 1) * 2 - 1], dim=-1)
    warped = F.grid_sample(source_image, grid.reshape(n, h, w, 2), mode="bilinear",
                           padding_mode="border", align_corners=True)
    valid = (cam[:, 2:3] > PROJECTION_EPS).reshape(n, 1, h, w)
    return warped, valid


def _project(depth_target: torch.Tensor, K, T_source_from_target,
             K_inv: torch.Tensor | None = None):
    """Every target pixel's point moved into the source camera and projected: (uv N x 2 x HW in
    pixels, camera points N x 3 x HW); ``K_inv``: K⁻¹ if computed before."""
    n, _, h, w = depth_target.shape
    K = _batched(K, n, 3, depth_target, "K")
    T = _batched(T_source_from_target, n, 4, depth_target, "T_source_from_target")
    ys, xs = torch.meshgrid(torch.arange(h, dtype=depth_target.dtype, device=K.device),
                            torch.arange(w, dtype=depth_target.dtype, device=K.device),
                            indexing="ij")
    pix = torch.stack([xs, ys, torch.ones_like(xs)]).reshape(1, 3, h * w)
    K_inv = (torch.linalg.inv(K) if K_inv is None
             else _batched(K_inv, n, 3, depth_target, "K_inv"))
    rays = K_inv @ pix  # N x 3 x HW
    cam = T[:, :3, :3] @ (rays * depth_target.reshape(n, 1, h * w)) + T[:, :3, 3:]
    return _pixels(K @ cam), cam


def _pixels(proj: torch.Tensor) -> torch.Tensor:
    """Homogeneous N x 3 x HW image points → N x 2 x HW pixels (divided by z + eps)."""
    return proj[:, :2] / (proj[:, 2:3] + PROJECTION_EPS)


def relative_pose(target_cam_from_world: np.ndarray, source_cam_from_world: np.ndarray,
                  scale: float = 1.0) -> np.ndarray:
    """T_{s<-t} = T_s · T_t⁻¹ from two world→camera 4 x 4 poses (SfM's ``cam_from_world``),
    its translation multiplied by ``scale`` (the window's ŝ: SfM units → network depth units,
    D_nn ≈ ŝ·D_sfm)."""
    if not (isinstance(scale, (int, float, np.floating)) and math.isfinite(scale) and scale > 0):
        raise InputError(f"alignment scale must be a positive number, got {scale!r}")
    Tt = np.asarray(target_cam_from_world, np.float64)
    Ts = np.asarray(source_cam_from_world, np.float64)
    if Tt.shape != (4, 4) or Ts.shape != (4, 4):
        raise InputError(f"cam_from_world poses must be 4x4, got {Tt.shape} and {Ts.shape}")
    T = Ts @ np.linalg.inv(Tt)
    T[:3, 3] *= float(scale)
    return T


def source_poses(names: Sequence[str], target: str, cam_from_world: Mapping[str, object],
                 scale: float, offsets: Iterable[int] = SOURCE_OFFSETS
                 ) -> list[tuple[str, np.ndarray]]:
    """The sources of ``target`` in a window and their T_{s<-t} in network depth units.

    ``names``: the window's frames in order; ``cam_from_world``: the registered frames' poses
    (``SfmResult.frames`` — values with a ``cam_from_world`` attribute — or plain 4 x 4
    arrays); ``scale``: the window's alignment scale ŝ. Offsets that fall outside the window
    and frames SfM did not register give no source; an unregistered target gives none at all
    (the frame then has no photometric term)."""
    names = list(names)
    if target not in names:
        raise InputError(f"target frame {target!r} is not in the window")
    if target not in cam_from_world:
        return []
    i = names.index(target)
    target_pose = getattr(cam_from_world[target], "cam_from_world", cam_from_world[target])
    out = []
    for off in offsets:
        j = i + int(off)
        if 0 <= j < len(names) and j != i and names[j] in cam_from_world:
            pose = getattr(cam_from_world[names[j]], "cam_from_world", cam_from_world[names[j]])
            out.append((names[j], relative_pose(target_pose, pose, scale)))
    return out


def network_intrinsics(intrinsics: Intrinsics, input_size: tuple[int, int]) -> np.ndarray:
    """K (3 x 3, pixels) of the image resized to the network's ``input_size`` (h, w).

    Pixel centres at integers and a resize with ``align_corners=False`` (as
    ``DepthModel.preprocess`` does) map x to (x + 0.5)·s − 0.5, so c' = (c + 0.5)·s − 0.5 and
    f' = f·s. (``Intrinsics.scaled`` uses c' = c·s, which is off by 0.5·(1 − s) px.)"""
    h, w = (int(v) for v in input_size)
    if h <= 1 or w <= 1:
        raise InputError(f"network input size must be at least 2 x 2, got {input_size}")
    sx, sy = w / intrinsics.width, h / intrinsics.height
    return np.array([[intrinsics.fx * sx, 0.0, (intrinsics.cx + 0.5) * sx - 0.5],
                     [0.0, intrinsics.fy * sy, (intrinsics.cy + 0.5) * sy - 0.5],
                     [0.0, 0.0, 1.0]])


def prepare_frames(model: DepthModel, names: Sequence[str], images: Mapping[str, np.ndarray],
                   cam_from_world: Mapping[str, object], scale: float, intrinsics: Intrinsics,
                   config: PhotometricConfig | None = None,
                   targets: Iterable[str] | None = None) -> list[PhotometricFrame]:
    """The window's :class:`PhotometricFrame` s: one per target (default: every frame) that SfM
    registered and that has at least one registered source at ``config.source_offsets``
    (:func:`source_poses`); the others have no photometric term and are left out.

    ``images``: uint8 RGB by name (full size, as given to SfM); ``cam_from_world``:
    ``SfmResult.frames``; ``scale``: the window's alignment scale ŝ; ``intrinsics``: of the
    full-size images."""
    cfg = config or PhotometricConfig()
    K = network_intrinsics(intrinsics, model.input_size)
    cache: dict[str, torch.Tensor] = {}

    def net_image(name: str) -> torch.Tensor:
        if name not in cache:
            cache[name] = model.preprocess(images[name])
        return cache[name]

    frames = []
    for name in (names if targets is None else targets):
        sources = source_poses(names, name, cam_from_world, scale, cfg.source_offsets)
        if not sources:
            continue
        target = net_image(name)
        src_images = [net_image(n) for n, _ in sources]
        with torch.no_grad():
            stats = ssim_target(target) if cfg.alpha != 0 else None
        identity = (identity_errors(target, src_images, cfg.alpha, cfg.seed, stats)
                    if cfg.automask else None)
        frames.append(PhotometricFrame(name, target, src_images, [n for n, _ in sources],
                                       [T for _, T in sources], K, identity, stats))
    return frames


# -- losses -------------------------------------------------------------------------------------

def identity_errors(target_image: torch.Tensor, source_images: Sequence[torch.Tensor],
                    alpha: float = ALPHA, seed: int = 0,
                    target_stats: SsimTarget | None = None) -> torch.Tensor:
    """Auto-masking's identity errors pe(I_t, I_s) + N(0, 1)·1e-5, N x S x H x W (one channel
    per source; noise from a generator seeded with ``seed``: deterministic). They do not depend
    on the depth: a refinement loop computes them once per frame and passes them to
    :func:`photometric_loss` (``identity=``), which saves two SSIM maps per step.
    ``target_stats``: the target's :func:`ssim_target` if computed before."""
    gen = torch.Generator().manual_seed(int(seed))
    out = []
    with torch.no_grad():
        stats = target_stats if target_stats is not None or alpha == 0 else \
            ssim_target(target_image)
        for src in source_images:
            err = reprojection_error(src, target_image, alpha, stats)
            noise = torch.randn(err.shape, generator=gen, dtype=err.dtype)
            out.append(err + noise.to(err.device) * IDENTITY_NOISE)
    return torch.cat(out, 1)


def photometric_loss(depth_target: torch.Tensor, target_image: torch.Tensor,
                     source_images: Sequence[torch.Tensor], K,
                     T_sources_from_target: Sequence, alpha: float = ALPHA,
                     automask: bool = True, seed: int = 0, return_maps: bool = False,
                     identity: torch.Tensor | None = None,
                     target_stats: SsimTarget | None = None, K_inv: torch.Tensor | None = None):
    """Monodepth2's photometric term: mean over pixels of min over sources of pe(I_t, I_{s→t}).

    ``depth_target`` N x 1 x H x W (network units), ``target_image`` and each source
    N x 3 x H x W in [0, 1], ``K`` at that size, one T_{s<-t} per source (4 x 4 or N x 4 x 4).
    With ``automask`` the identity errors (:func:`identity_errors` with ``seed``, or the
    precomputed ``identity``) join the minimum. Warped errors of points behind a source camera
    do not join it; pixels left with no term at all (no automask, no valid source) are left out of
    the mean. ``target_stats``: the target's :func:`ssim_target` (else computed once here, for all
    sources). ``K_inv``: K⁻¹ computed before (:func:`warp`). Returns the loss, or (loss,
    :class:`PhotometricMaps`) with ``return_maps``."""
    sources = list(source_images)
    poses = list(T_sources_from_target)
    if not sources:
        raise InputError("photometric_loss needs at least one source frame (a frame without "
                         "registered neighbours has no photometric term: skip it)")
    if len(poses) != len(sources):
        raise InputError(f"{len(sources)} source images but {len(poses)} poses")
    for src in sources:
        if src.shape != target_image.shape:
            raise InputError(f"source image {tuple(src.shape)} differs from the target "
                             f"{tuple(target_image.shape)}")
    errors = []
    if automask:
        if identity is None:
            identity = identity_errors(target_image, sources, alpha, seed)
        n, _, h, w = target_image.shape
        if tuple(identity.shape) != (n, len(sources), h, w):
            raise InputError(f"identity errors must be {n} x {len(sources)} x {h} x {w}, got "
                             f"{tuple(identity.shape)}")
        errors.append(identity)
    if target_stats is None and alpha != 0:
        target_stats = ssim_target(target_image)
    for src, T in zip(sources, poses, strict=True):
        warped, valid = warp(src, depth_target, K, T, K_inv)
        err = reprojection_error(warped, target_image, alpha, target_stats)
        errors.append(torch.where(valid, err, torch.full_like(err, math.inf)))
    min_error, idx = torch.cat(errors, 1).min(1, keepdim=True)
    finite = torch.isfinite(min_error)
    count = finite.sum()
    loss = torch.where(finite, min_error, torch.zeros_like(min_error)).sum() / count.clamp(min=1)
    if not return_maps:
        return loss
    n_identity = len(sources) if automask else 0
    identity_won = idx < n_identity
    source_index = torch.where(identity_won | ~finite, torch.full_like(idx, -1), idx - n_identity)
    return loss, PhotometricMaps(min_error.detach(), identity_won, source_index)


def smoothness_loss(disp: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
    """Edge-aware smoothness of the disparity d* = d / (mean(d) + 1e-7) (per image):
    mean |∂x d*|·exp(−mean_RGB|∂x I|) + mean |∂y d*|·exp(−mean_RGB|∂y I|). ``image`` is
    resized (area) to the disparity's size when they differ."""
    if image.shape[-2:] != disp.shape[-2:]:
        image = F.interpolate(image, size=tuple(disp.shape[-2:]), mode="area")
    d = disp / (disp.mean((2, 3), keepdim=True) + 1e-7)
    grad_d_x = (d[..., :, :-1] - d[..., :, 1:]).abs()
    grad_d_y = (d[..., :-1, :] - d[..., 1:, :]).abs()
    grad_i_x = (image[..., :, :-1] - image[..., :, 1:]).abs().mean(1, keepdim=True)
    grad_i_y = (image[..., :-1, :] - image[..., 1:, :]).abs().mean(1, keepdim=True)
    return (grad_d_x * torch.exp(-grad_i_x)).mean() + (grad_d_y * torch.exp(-grad_i_y)).mean()


def scale_outputs(model: DepthModel, features, scales: Sequence[int] = (0,)) -> list[ScaleOutput]:
    """Depth at the full input size and native disparity for each wanted decoder scale.

    A decoder that returns Monodepth2's dict (``{("disp", s): sigmoid}``, as the decoders here
    do) gives every head in ``scales``: the sigmoid disparity is upsampled (bilinear,
    ``align_corners=False``) to the scale-0 size and turned into depth with the model's depth
    range (Monodepth2's default, not ``v1_multiscale``). Any other decoder gives scale 0 only,
    through ``model.output_to_depth``, with disparity 1 / depth."""
    scales = tuple(int(s) for s in scales)
    if hasattr(model.decoder, "output_scales"):  # DepthDecoder: computes the heads asked for
        raw = model.decoder(features, scales=scales)
    else:
        raw = model.decoder(features)
    if not isinstance(raw, dict):
        if scales != (0,):
            raise InputError(f"{type(model.decoder).__name__} has a single output: use scales "
                             f"(0,), got {scales}")
        depth = model.output_to_depth(raw)
        return [ScaleOutput(0, depth, 1.0 / depth)]
    full = raw[("disp", 0)].shape[-2:] if ("disp", 0) in raw else model.input_size
    out = []
    for s in scales:
        if ("disp", s) not in raw:
            raise InputError(f"the decoder gave no disparity for scale {s}")
        disp = raw[("disp", s)]
        up = disp if disp.shape[-2:] == full else F.interpolate(
            disp, size=tuple(full), mode="bilinear", align_corners=False)
        depth = model.output_to_depth({("disp", 0): up})  # the model's own disp → depth
        out.append(ScaleOutput(s, depth, disp))
    return out


def photometric_objective(outputs: Sequence[ScaleOutput], target_image: torch.Tensor,
                          source_images: Sequence[torch.Tensor], K,
                          T_sources_from_target: Sequence,
                          config: PhotometricConfig | None = None,
                          identity: torch.Tensor | None = None,
                          target_stats: SsimTarget | None = None,
                          K_inv: torch.Tensor | None = None) -> PhotometricTerms:
    """Monodepth2's total: 1/|S| Σ_scale (L_p(depth_scale) + w_s / 2^scale · L_s(disp_scale)),
    every scale warped at the full input size with the full-size images and K. ``identity``
    and ``target_stats``: the frame's precomputed :func:`identity_errors` and
    :func:`ssim_target` (else computed here, once for all scales); ``K_inv``: K⁻¹ computed
    before (:func:`warp`)."""
    cfg = config or PhotometricConfig()
    if not outputs:
        raise InputError("photometric_objective needs at least one output scale")
    sources = list(source_images)
    if cfg.automask and identity is None and sources:
        identity = identity_errors(target_image, sources, cfg.alpha, cfg.seed)
    if target_stats is None and cfg.alpha != 0:
        target_stats = ssim_target(target_image)
    ph, sm, total = [], [], []
    for o in outputs:
        p = photometric_loss(o.depth, target_image, sources, K, T_sources_from_target,
                             cfg.alpha, cfg.automask, cfg.seed, identity=identity,
                             target_stats=target_stats, K_inv=K_inv)
        s = smoothness_loss(o.disp, target_image)
        ph.append(p)
        sm.append(s)
        total.append(p + cfg.smoothness_weight / 2 ** o.scale * s)
    k = len(outputs)
    return PhotometricTerms(sum(total) / k, sum(ph) / k, sum(sm) / k)
