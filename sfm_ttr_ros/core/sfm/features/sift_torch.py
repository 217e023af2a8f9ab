"""A weight-free SIFT in torch: the difference-of-Gaussians detector and the SIFT descriptor
(Lowe, "Distinctive Image Features from Scale-Invariant Keypoints", IJCV 2004), batched so that
it runs on a GPU when there is one (and on the CPU in the tests).

What each step implements:

* scale space (Lowe 2004, Sec. 3): ``num_scales`` intervals per octave, sigma0 = 1.6, the input
  assumed blurred by 0.5 px (1.0 px of the upsampled first octave, ``first_octave = -1``, as
  Lowe's Sec. 3.3 and COLMAP do); ``num_scales + 3`` Gaussian levels per octave built by
  incremental separable blurs, ``num_scales + 2`` difference-of-Gaussian levels; the next octave
  starts from the level with twice sigma0, halved by a 2x2 average (which keeps pixel centres
  exactly aligned between octaves);
* extrema (Sec. 3.1): a DoG sample larger (smaller) than its 26 neighbours in space and scale,
  with |D| above ``peak_threshold``;
* accurate keypoint localisation (Sec. 4): the Newton step of the quadratic fit of D in
  (x, y, sigma), Eq. (3); where the offset exceeds ``max_offset`` in a dimension the sample
  moves one step that way and the fit is repeated (``refine_iterations``, 5 as vlfeat/COLMAP),
  else the candidate is discarded; the interpolated contrast |D(x̂)| must stay above
  ``peak_threshold`` (a prefilter of 0.8 times it runs on the samples);
* eliminating edge responses (Sec. 4.1): Tr(H)² / Det(H) < (r + 1)² / r, r = ``edge_threshold``;
* orientation assignment (Sec. 5): a 36-bin histogram of gradient orientations in a Gaussian
  window of 1.5 sigma, weighted by gradient magnitude, smoothed; every peak within 80 % of the
  highest gives a keypoint, its angle refined by a parabola through three bins;
* the descriptor (Sec. 6.1): a 4x4 grid of 8-bin orientation histograms (128 values) of
  gradients rotated into the keypoint's frame, spatial bins 3 sigma wide, a Gaussian weight of
  half the window width, trilinear interpolation into the bins; normalised to unit length,
  clipped at 0.2 and normalised again (Sec. 6.1, illumination invariance). ``root_sift``
  replaces the last step by RootSIFT (Arandjelović & Zisserman, CVPR 2012: L1 normalisation and
  a square root, so that Euclidean distances compare as the Hellinger kernel).

Keypoints are returned in COLMAP's pixel convention (the image's top-left corner at (0, 0), a
pixel's centre at +0.5), in the pixels of the image given, with their scale (sigma in those
pixels) and orientation (radians).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

SIGMA0 = 1.6  # Lowe 2004, Sec. 3.3
INPUT_BLUR = 0.5  # assumed blur of the input image (Lowe 2004, Sec. 3.3)
ORI_BINS = 36  # Sec. 5
ORI_PEAK_RATIO = 0.8  # Sec. 5
ORI_SIGMA_FACTOR = 1.5  # Sec. 5: the orientation window is 1.5 times the keypoint's sigma
DESC_WIDTH = 4  # Sec. 6.1: 4x4 spatial bins ...
DESC_BINS = 8  # ... of 8 orientations
DESC_MAGNIFICATION = 3.0  # a spatial bin is 3 sigma wide (vlfeat / COLMAP, Lowe's code)
DESC_CLIP = 0.2  # Sec. 6.1
DESC_SAMPLES = 6  # samples per spatial bin side of the resampled descriptor window
ORI_CHUNK_ELEMENTS = 1 << 24  # window samples per chunk of keypoints in the orientation step


@dataclass
class TorchSiftConfig:
    """Options of :func:`detect_and_describe` (defaults: Lowe 2004; thresholds as COLMAP's)."""

    num_scales: int = 3  # intervals per octave, Sec. 3.2
    first_octave: int = -1  # -1: the image upsampled 2x first (Sec. 3.3); 0: as given
    peak_threshold: float = 0.02 / 3  # |D| on [0, 1] images (COLMAP: 0.02 / num_scales)
    edge_threshold: float = 10.0  # r of Sec. 4.1
    max_offset: float = 0.6  # subpixel refinement: move the sample where the fit is further
    refine: bool = True  # Sec. 4's quadratic fit; False: keypoints at the sample
    refine_iterations: int = 5  # fits (and moves) at most per candidate (vlfeat / COLMAP: 5)
    max_num_features: int = 8192  # the strongest |D| kept (after orientation assignment)
    max_orientations: int = 2  # orientations per location at most (COLMAP: 2)
    root_sift: bool = True  # COLMAP's default normalisation (L1_ROOT)
    min_octave_size: int = 16  # no octave smaller than this on its short side


def to_gray(image: np.ndarray) -> np.ndarray:
    """An RGB uint8 (H x W x 3) or gray image as float32 gray in [0, 1]."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = img[..., :3].astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
    img = img.astype(np.float32)
    if np.asarray(image).dtype == np.uint8:
        img /= 255.0
    return img


def _gauss_kernel(sigma: float, device, dtype):
    import torch

    radius = max(1, int(math.ceil(4.0 * sigma)))
    x = torch.arange(-radius, radius + 1, device=device, dtype=dtype)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def gaussian_blur(img, sigma: float):
    """Separable Gaussian blur of a (B, 1, H, W) tensor, borders replicated."""
    import torch.nn.functional as F

    if sigma <= 0:
        return img
    k = _gauss_kernel(sigma, img.device, img.dtype)
    r = k.numel() // 2
    x = F.conv2d(F.pad(img, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
    x = F.pad(x, (0, 0, r, r), mode="replicate")
    return F.conv2d(x, k.view(1, 1, -1, 1))


def _blur(x, sigma: float, per_image: bool):
    """:func:`gaussian_blur` of a batch, one image at a time with ``per_image`` (the numbers of
    each image alone: on the CPU oneDNN picks its convolution by batch size, which moves the
    last bit of small octaves), else as one batch (CUDA: one kernel per pass for the window)."""
    if not per_image or x.shape[0] == 1:
        return gaussian_blur(x, sigma)
    return torch_cat([gaussian_blur(x[i:i + 1], sigma) for i in range(x.shape[0])])


def build_octaves(img, cfg: TorchSiftConfig, per_image_blur: bool | None = None):
    """Gaussian and DoG pyramids (Lowe 2004, Sec. 3) of one image (H, W) or of a batch of
    images of one size (B, H, W): a list of (octave index o, Gaussian levels (S+3, H_o, W_o),
    DoG levels (S+2, H_o, W_o)), each with the batch dimension in front for a batch; octave o's
    pixel i has its centre at (i + 0.5) * 2**o in the input image's corner convention.
    ``per_image_blur`` (default: on the CPU) blurs a batch's images one at a time (:func:`_blur`);
    resampling and differences are per image in any case."""
    import torch.nn.functional as F

    batched = img.ndim == 3
    per_image = img.device.type == "cpu" if per_image_blur is None else per_image_blur
    S = cfg.num_scales
    x = img[:, None] if batched else img[None, None]
    o = int(cfg.first_octave)
    if o < 0:
        for _ in range(-o):
            x = F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=False)
    elif o > 0:
        for _ in range(o):
            x = F.avg_pool2d(x, 2)
    blur = INPUT_BLUR * 2.0 ** (-o)
    x = _blur(x, math.sqrt(max(SIGMA0**2 - blur**2, 0.0)), per_image)
    k = 2.0 ** (1.0 / S)
    out = []
    while min(x.shape[-2:]) >= cfg.min_octave_size:
        levels = [x]
        for s in range(1, S + 3):
            sig_prev = SIGMA0 * k ** (s - 1)
            sig_inc = sig_prev * math.sqrt(k * k - 1.0)
            levels.append(_blur(levels[-1], sig_inc, per_image))
        gauss = torch_cat(levels, 1)  # (B, S+3, H, W)
        dog = gauss[:, 1:] - gauss[:, :-1]
        out.append((o, gauss, dog) if batched else (o, gauss[0], dog[0]))
        x = F.avg_pool2d(levels[S], 2)  # twice sigma0: the next octave's first level
        o += 1
    return out


def torch_cat(tensors, dim: int = 0):
    import torch

    return torch.cat(tensors, dim)


def _extrema(dog, cfg: TorchSiftConfig):
    """Scale-space extrema of one octave's DoG of a batch (B, S+2, H, W): (b, s, y, x) integer
    indices (Sec. 3.1), one pixel away from every border, in (b, s, y, x) order."""
    import torch
    import torch.nn.functional as F

    B, L, H, W = dog.shape
    d = dog.reshape(B * L, 1, H, W)  # 3x3 in space (max_pool2d), then 3 in scale
    mx = F.max_pool2d(d, 3, stride=1, padding=1).reshape(B, L, H, W)
    mn = -F.max_pool2d(-d, 3, stride=1, padding=1).reshape(B, L, H, W)
    mx = torch.maximum(torch.maximum(mx[:, :-2], mx[:, 1:-1]), mx[:, 2:])
    mn = torch.minimum(torch.minimum(mn[:, :-2], mn[:, 1:-1]), mn[:, 2:])
    pad = torch.zeros_like(dog[:, :1])
    mx, mn = torch.cat([pad, mx, pad], 1), torch.cat([pad, mn, pad], 1)  # ends excluded below
    thr = 0.8 * cfg.peak_threshold if cfg.refine else cfg.peak_threshold
    is_ext = ((dog == mx) & (dog > thr)) | ((dog == mn) & (dog < -thr))
    is_ext[:, 0] = False
    is_ext[:, -1] = False
    is_ext[:, :, :1] = False
    is_ext[:, :, -1:] = False
    is_ext[:, :, :, :1] = False
    is_ext[:, :, :, -1:] = False
    return torch.nonzero(is_ext, as_tuple=True)


def _taylor(D, b, s, y, x):
    """Value, gradient (3) and Hessian (3 x 3) of D (B, L, H, W) in (x, y, sigma) at integer
    samples by finite differences (Lowe 2004, Sec. 4)."""
    import torch

    def at(ds, dy, dx):
        return D[b, s + ds, y + dy, x + dx]

    v = at(0, 0, 0)
    g = torch.stack([0.5 * (at(0, 0, 1) - at(0, 0, -1)), 0.5 * (at(0, 1, 0) - at(0, -1, 0)),
                     0.5 * (at(1, 0, 0) - at(-1, 0, 0))], -1)
    dxx = at(0, 0, 1) + at(0, 0, -1) - 2 * v
    dyy = at(0, 1, 0) + at(0, -1, 0) - 2 * v
    dss = at(1, 0, 0) + at(-1, 0, 0) - 2 * v
    dxy = 0.25 * (at(0, 1, 1) - at(0, 1, -1) - at(0, -1, 1) + at(0, -1, -1))
    dxs = 0.25 * (at(1, 0, 1) - at(1, 0, -1) - at(-1, 0, 1) + at(-1, 0, -1))
    dys = 0.25 * (at(1, 1, 0) - at(1, -1, 0) - at(-1, 1, 0) + at(-1, -1, 0))
    H = torch.stack([torch.stack([dxx, dxy, dxs], -1), torch.stack([dxy, dyy, dys], -1),
                     torch.stack([dxs, dys, dss], -1)], -2)
    return v, g, H


def _fit(dog, b, s, y, x, cfg: TorchSiftConfig):
    """Sec. 4's iterated fit: the offset x̂ = −H⁻¹ g of the quadratic Taylor fit of D, Eq. (3);
    where it exceeds ``max_offset`` in a dimension the sample moves one step that way and the
    fit is repeated (up to ``refine_iterations`` times). A converged candidate does not move,
    so further rounds (another image of the batch still converging) leave it as it was.
    Returns (ok, s, y, x, offset, value at the sample, gradient, Hessian)."""
    import torch

    L, Hh, Ww = dog.shape[1:]
    for it in range(max(1, cfg.refine_iterations)):
        v, g, H = _taylor(dog, b, s, y, x)
        det3 = torch.linalg.det(H)
        solvable = det3.abs() > 1e-12
        Hs = torch.where(solvable[:, None, None], H,
                         torch.eye(3, device=H.device, dtype=H.dtype))
        off = -torch.linalg.solve(Hs, g[..., None])[..., 0]
        off = torch.where(solvable[:, None], off, torch.zeros_like(off))
        ok = solvable & (off.abs() <= cfg.max_offset).all(-1)
        if it == cfg.refine_iterations - 1 or bool(ok.all()):
            break
        step = torch.where(off.abs() > cfg.max_offset, torch.sign(off),
                           torch.zeros_like(off)).long()
        step = torch.where(solvable[:, None], step, torch.zeros_like(step))
        x = (x + step[:, 0]).clamp(1, Ww - 2)
        y = (y + step[:, 1]).clamp(1, Hh - 2)
        s = (s + step[:, 2]).clamp(1, L - 2)
    return ok, s, y, x, off, v, g, H


def _localise(dog, b, s, y, x, cfg: TorchSiftConfig):
    """Sec. 4 and 4.1 for one octave of a batch (B, L, H, W): the subpixel / subscale fit
    (:func:`_fit`, else the sample itself), the contrast of the fit D(x̂), Eq. (3), and the edge
    test (ratio of principal curvatures of the 2 x 2 spatial Hessian, Sec. 4.1) at the final
    sample; candidates that converged on the same sample of the same image are one. Returns
    (keep mask, xs, ys, ss: refined coordinates, value: D(x̂))."""
    import torch

    if cfg.refine:
        keep, s, y, x, off, v, g, H = _fit(dog, b, s, y, x, cfg)
        value = v + 0.5 * (g * off).sum(-1)  # D(x̂), Sec. 4
    else:
        value, g, H = _taylor(dog, b, s, y, x)
        off = torch.zeros(s.shape[0], 3, device=dog.device, dtype=dog.dtype)
        keep = torch.ones_like(s, dtype=torch.bool)
    dxx, dyy, dxy = H[:, 0, 0], H[:, 1, 1], H[:, 0, 1]
    tr, det = dxx + dyy, dxx * dyy - dxy * dxy
    r = cfg.edge_threshold
    keep &= (det > 0) & (tr * tr * r < (r + 1) ** 2 * det)
    keep &= value.abs() > cfg.peak_threshold
    # candidates that converged on the same sample are one keypoint: the first is kept
    L, Hh, Ww = dog.shape[1:]
    lin = ((b * L + s) * Hh + y) * Ww + x
    _, inv = torch.unique(lin, return_inverse=True)
    idx = torch.arange(lin.numel(), device=lin.device)
    first = torch.full((lin.numel(),), lin.numel(), device=lin.device, dtype=torch.long)
    first.scatter_reduce_(0, inv[keep], idx[keep], reduce="amin")
    keep &= first[inv] == idx
    xs = x.to(dog.dtype) + off[:, 0]
    ys = y.to(dog.dtype) + off[:, 1]
    ss = s.to(dog.dtype) + off[:, 2]
    return keep, xs, ys, ss, value


def _gradients(gauss):
    """Gradient magnitude and orientation of Gaussian levels (B, L, H, W), central differences
    (Lowe 2004, Sec. 5)."""
    import torch
    import torch.nn.functional as F

    p = F.pad(gauss, (1, 1, 1, 1), mode="replicate")
    gx = 0.5 * (p[..., 1:-1, 2:] - p[..., 1:-1, :-2])
    gy = 0.5 * (p[..., 2:, 1:-1] - p[..., :-2, 1:-1])
    return torch.sqrt(gx * gx + gy * gy), torch.atan2(gy, gx)


def orientation_radius(cfg: TorchSiftConfig) -> int:
    """The half-width of the orientation window (Sec. 5: 3 x 1.5 sigma) for the largest sigma
    a kept keypoint can have (scale index at most num_scales + max_offset): one window size for
    every keypoint of every image, so that a keypoint's histogram does not depend on the others
    it is computed with."""
    top = cfg.num_scales + (cfg.max_offset if cfg.refine else 0.0)
    return int(math.ceil(3.0 * ORI_SIGMA_FACTOR * SIGMA0 * 2.0 ** (top / cfg.num_scales)))


def _orientations(mag, ang, b, lvl, ys, xs, sigma, cfg: TorchSiftConfig):
    """Sec. 5: dominant orientations of keypoints at (image b, level, ys, xs) with scale
    ``sigma`` (octave pixels), in chunks of keypoints (memory; each keypoint's numbers are its
    own). Returns (index of the keypoint, angle in radians) for every peak kept."""
    import torch

    R = orientation_radius(cfg)
    chunk = max(1, ORI_CHUNK_ELEMENTS // (2 * R + 1) ** 2)
    parts = [_orientation_chunk(mag, ang, b[i:i + chunk], lvl[i:i + chunk], ys[i:i + chunk],
                                xs[i:i + chunk], sigma[i:i + chunk], R, cfg)
             for i in range(0, xs.shape[0], chunk)]
    if not parts:
        empty = torch.zeros(0, device=mag.device)
        return empty.long(), empty.to(mag.dtype)
    return (torch.cat([k + i * chunk for i, (k, _) in enumerate(parts)]),
            torch.cat([t for _, t in parts]))


def _orientation_chunk(mag, ang, b, lvl, ys, xs, sigma, R: int, cfg: TorchSiftConfig):
    """:func:`_orientations` of one chunk: the 36-bin histogram of gradient orientations in a
    Gaussian window of 1.5 sigma weighted by gradient magnitude, smoothed; every peak within
    80 % of the highest, refined by a parabola through three bins (Sec. 5)."""
    import torch

    dev, dt = mag.device, mag.dtype
    n = xs.shape[0]
    win_sigma = ORI_SIGMA_FACTOR * sigma  # (n,)
    off = torch.arange(-R, R + 1, device=dev)
    oy, ox = torch.meshgrid(off, off, indexing="ij")
    oy, ox = oy.reshape(-1), ox.reshape(-1)
    H, W = mag.shape[-2:]
    cy, cx = torch.round(ys).long(), torch.round(xs).long()
    py, px = cy[:, None] + oy[None], cx[:, None] + ox[None]  # (n, P)
    inside = (py >= 0) & (py < H) & (px >= 0) & (px < W)
    py, px = py.clamp(0, H - 1), px.clamp(0, W - 1)
    B_, L = b[:, None].expand_as(py), lvl[:, None].expand_as(py)
    m = mag[B_, L, py, px]
    a = ang[B_, L, py, px]
    ry = py.to(dt) - ys[:, None]
    rx = px.to(dt) - xs[:, None]
    r2 = rx * rx + ry * ry
    w = torch.exp(-r2 / (2 * win_sigma[:, None] ** 2)) * m
    w = w * (inside & (r2 <= (3.0 * win_sigma[:, None]) ** 2))
    bins = (a % (2 * math.pi)) * (ORI_BINS / (2 * math.pi))
    b0 = torch.floor(bins)
    frac = bins - b0
    b0 = b0.long() % ORI_BINS
    hist = torch.zeros(n, ORI_BINS, device=dev, dtype=dt)
    hist.scatter_add_(1, b0, w * (1 - frac))
    hist.scatter_add_(1, (b0 + 1) % ORI_BINS, w * frac)
    return _orientation_peaks(hist, cfg)


def _orientation_peaks(hist, cfg: TorchSiftConfig):
    """Sec. 5's peaks of orientation histograms (n, 36): smoothed, every local peak within
    80 % of the highest (at most ``max_orientations``, the highest first), its angle refined by
    a parabola through three bins. Returns (index of the row, angle in radians)."""
    import torch

    n, dt = hist.shape[0], hist.dtype
    for _ in range(6):  # circular smoothing [1, 1, 1] / 3, as vlfeat / COLMAP
        hist = (torch.roll(hist, 1, 1) + hist + torch.roll(hist, -1, 1)) / 3.0
    left, right = torch.roll(hist, 1, 1), torch.roll(hist, -1, 1)
    peak = (hist > left) & (hist > right) & (hist >= ORI_PEAK_RATIO * hist.max(1, True).values)
    peak &= hist > 0
    # at most max_orientations peaks per keypoint, the highest first
    score = torch.where(peak, hist, torch.full_like(hist, -1.0))
    k = min(cfg.max_orientations, ORI_BINS)
    top, idx = score.topk(k, dim=1)
    sel = top > 0
    kp_idx = torch.arange(n, device=hist.device)[:, None].expand(-1, k)[sel]
    bins = idx[sel]
    hl, hc, hr = left[kp_idx, bins], hist[kp_idx, bins], right[kp_idx, bins]
    denom = hl - 2 * hc + hr
    delta = torch.where(denom.abs() > 1e-12, 0.5 * (hl - hr) / denom, torch.zeros_like(hc))
    # bin b collects orientations in [b, b+1) * 10 deg, linearly shared: its centre is b
    theta = (bins.to(dt) + delta) * (2 * math.pi / ORI_BINS)
    return kp_idx, theta


def _spatial_weights(cy, cx, d: int):
    """Weights of each resampled window position (bin units, the keypoint at 0) in the d x d
    spatial bins: the Gaussian weight (sigma = half the window, Sec. 6.1) times the bilinear
    share of the two nearest bin centres in x and in y (the spatial part of Sec. 6.1's trilinear
    interpolation; the window is already rotated, so it is the same for every keypoint)."""
    import torch

    g = torch.exp(-(cx ** 2 + cy ** 2) / (2 * (d / 2.0) ** 2)).reshape(-1)
    centres = torch.arange(d, device=cx.device, dtype=cx.dtype) - (d - 1) / 2.0
    wx = (1 - (cx.reshape(-1, 1) - centres).abs()).clamp_min(0)  # (P'^2, d)
    wy = (1 - (cy.reshape(-1, 1) - centres).abs()).clamp_min(0)
    w = (wy[:, :, None] * wx[:, None, :]).reshape(-1, d * d) * g[:, None]
    return w.T.contiguous()


def _descriptors(gauss, b, lvl, ys, xs, sigma, theta, cfg: TorchSiftConfig):
    """Sec. 6.1: 128-d descriptors of keypoints (image b of the batch, Gaussian level, position,
    sigma in octave pixels, orientation), one level of one image at a time. The window, 3
    sigma per spatial bin, is resampled (bilinear) on a grid rotated by the keypoint's
    orientation, so that gradients of the resampled patch are already relative to it; each
    gradient is Gaussian-weighted (sigma: half the window) and spread trilinearly over the
    4x4x8 bins."""
    import torch
    import torch.nn.functional as F

    dev, dt = gauss.device, gauss.dtype
    n = xs.shape[0]
    if n == 0:
        return torch.zeros(0, DESC_WIDTH * DESC_WIDTH * DESC_BINS, device=dev, dtype=dt)
    d, nb = DESC_WIDTH, DESC_BINS
    ns = DESC_SAMPLES
    P = int(round((d + 1) * ns)) + 2  # samples per side, +2 for central differences
    # sample coordinates in bin units, centred on the keypoint
    u = (torch.arange(P, device=dev, dtype=dt) - (P - 1) / 2.0) / ns
    vy, vx = torch.meshgrid(u, u, indexing="ij")
    bin_px = DESC_MAGNIFICATION * sigma  # (n,) bin width in octave pixels
    c, s = torch.cos(theta), torch.sin(theta)
    # rotate the window: image offset = R(theta) @ (vx, vy) * bin_px
    gx = xs[:, None, None] + bin_px[:, None, None] * (c[:, None, None] * vx - s[:, None, None] * vy)
    gy = ys[:, None, None] + bin_px[:, None, None] * (s[:, None, None] * vx + c[:, None, None] * vy)
    H, W = gauss.shape[-2:]
    spatial = _spatial_weights(vy[1:-1, 1:-1], vx[1:-1, 1:-1], d)  # (16, P'^2)
    desc = torch.zeros(n, d * d * nb, device=dev, dtype=dt)
    levels = gauss.shape[1]
    key = b * levels + lvl
    for k in torch.unique(key).tolist():
        sel = torch.nonzero(key == k, as_tuple=True)[0]
        grid = torch.stack([(gx[sel] + 0.5) / W * 2 - 1, (gy[sel] + 0.5) / H * 2 - 1], -1)
        img = gauss[k // levels, k % levels][None, None].expand(sel.numel(), 1, H, W)
        patch = F.grid_sample(img, grid, mode="bilinear", padding_mode="border",
                              align_corners=False)[:, 0]  # (m, P, P)
        # gradients in the rotated frame (per sample spacing; magnitudes scale uniformly)
        px_ = 0.5 * (patch[:, 1:-1, 2:] - patch[:, 1:-1, :-2])
        py_ = 0.5 * (patch[:, 2:, 1:-1] - patch[:, :-2, 1:-1])
        mag = torch.sqrt(px_ * px_ + py_ * py_)
        ang = torch.atan2(py_, px_) % (2 * math.pi)
        m = sel.numel()
        # orientation bins (linear in angle), per keypoint: (m, P'^2, 8)
        bo = (ang * (nb / (2 * math.pi))).reshape(m, -1)
        o0 = torch.floor(bo)
        fo = bo - o0
        o0 = o0.long() % nb
        mag = mag.reshape(m, -1)
        wo = torch.zeros(m, mag.shape[1], nb, device=dev, dtype=dt)
        wo.scatter_add_(2, o0[..., None], (mag * (1 - fo))[..., None])
        wo.scatter_add_(2, ((o0 + 1) % nb)[..., None], (mag * fo)[..., None])
        desc[sel] = torch.matmul(spatial, wo).reshape(m, -1)  # (m, 16, 8) -> (m, 128)
    # Sec. 6.1: normalise, clip at 0.2, normalise again
    desc = desc / desc.norm(dim=1, keepdim=True).clamp_min(1e-12)
    desc = desc.clamp_max(DESC_CLIP)
    desc = desc / desc.norm(dim=1, keepdim=True).clamp_min(1e-12)
    if cfg.root_sift:
        desc = torch.sqrt(desc / desc.sum(1, keepdim=True).clamp_min(1e-12))
    return desc


@dataclass
class SiftFeatures:
    """Keypoints (N x 4: x, y in COLMAP's pixel convention, scale sigma in pixels, orientation
    in radians) and unit-length descriptors (N x 128 float32), both torch tensors on the device
    they were computed on; ``response`` = |D| at the keypoint."""

    keypoints: object
    descriptors: object
    response: object

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])

    def keypoints_numpy(self) -> np.ndarray:
        return self.keypoints.detach().float().cpu().numpy()

    def descriptors_uint8(self) -> np.ndarray:
        """Descriptors as COLMAP stores SIFT ones: round(512 * d) clipped to 255."""
        import torch

        d = torch.clamp(torch.round(self.descriptors * 512.0), 0, 255)
        return d.to(torch.uint8).cpu().numpy()


def detect_and_describe(image, cfg: TorchSiftConfig | None = None, device: str = "cpu"
                        ) -> SiftFeatures:
    """SIFT keypoints and descriptors of one image (numpy RGB/gray or a 2-D torch tensor in
    [0, 1]) on ``device``: :func:`detect_and_describe_batch` of that one image."""
    return detect_and_describe_batch([image], cfg, device)[0]


def gray_batch(images, device: str):
    """Images of one size (numpy RGB/gray, or 2-D torch tensors in [0, 1]) as a (B, H, W)
    float32 batch on ``device``; numpy images go through pinned memory to a CUDA device (a copy
    that does not block the host, no pageable staging)."""
    import torch

    if all(isinstance(im, torch.Tensor) for im in images):
        img = torch.stack([im.to(device=device, dtype=torch.float32) for im in images])
    else:
        img = torch.from_numpy(np.stack([np.ascontiguousarray(to_gray(np.asarray(im)))
                                         for im in images]))
        if str(device).startswith("cuda"):
            img = img.pin_memory()
        img = img.to(device, non_blocking=True)
    if img.ndim != 3:
        raise ValueError(f"expected 2-D gray images, got shape {tuple(img.shape[1:])}")
    return img


def detect_and_describe_batch(images, cfg: TorchSiftConfig | None = None,
                              device: str = "cpu") -> list[SiftFeatures]:
    """SIFT keypoints and descriptors (Lowe 2004, Sec. 3-6, module docstring) of images of ONE
    size, their scale spaces built as one batch (a window's frames at once: fewer, larger
    kernels on a GPU). Each image's features are those it has alone: every step works on one
    image's samples and a keypoint's numbers never depend on the others' (the tests hold the
    batch to the images one by one)."""
    import torch

    cfg = cfg or TorchSiftConfig()
    if not len(images):
        return []
    img = gray_batch(list(images), device)
    found = []  # per octave: (image index, keypoints (n, 4), descriptors, response)
    with torch.no_grad():
        for o, gauss, dog in build_octaves(img, cfg):
            octave = _octave_features(o, gauss, dog, cfg)
            if octave is not None:
                found.append(octave)
    return _split_by_image(found, img.shape[0], cfg, img.device)


def _octave_features(o: int, gauss, dog, cfg: TorchSiftConfig):
    """One octave of a batch: extrema (Sec. 3.1), localisation (Sec. 4), orientations (Sec. 5),
    descriptors (Sec. 6.1); (image index, keypoints (x, y, sigma in input pixels, angle),
    descriptors, |D|) or None when nothing was kept."""
    import torch

    S = cfg.num_scales
    b, s, y, x = _extrema(dog, cfg)
    if s.numel() == 0:
        return None
    keep, xs, ys, ss, value = _localise(dog, b, s, y, x, cfg)
    b, xs, ys, ss, value = b[keep], xs[keep], ys[keep], ss[keep], value[keep]
    H, W = dog.shape[-2:]
    inb = (xs >= 0) & (xs <= W - 1) & (ys >= 0) & (ys <= H - 1)
    b, xs, ys, ss, value = b[inb], xs[inb], ys[inb], ss[inb], value[inb]
    if xs.numel() == 0:
        return None
    # the DoG level s lies between Gaussian levels s and s+1: sigma0 * k^s (Sec. 3)
    sigma = SIGMA0 * 2.0 ** (ss / S)
    lvl = torch.round(ss).long().clamp(0, S + 2)  # the Gaussian level nearest in scale
    mag, ang = _gradients(gauss)
    ki, theta = _orientations(mag, ang, b, lvl, ys, xs, sigma, cfg)
    if ki.numel() == 0:
        return None
    d = _descriptors(gauss, b[ki], lvl[ki], ys[ki], xs[ki], sigma[ki], theta, cfg)
    f = 2.0 ** o
    kp = torch.stack([(xs[ki] + 0.5) * f, (ys[ki] + 0.5) * f, sigma[ki] * f, theta], 1)
    return b[ki], kp, d, value[ki].abs()


def _split_by_image(found, n_images: int, cfg: TorchSiftConfig, dev) -> list[SiftFeatures]:
    """Each image's features from the octaves' (octave order, then the order found), the
    ``max_num_features`` strongest |D| kept per image."""
    import torch

    if not found:
        return [SiftFeatures(torch.zeros(0, 4, device=dev), torch.zeros(0, 128, device=dev),
                             torch.zeros(0, device=dev)) for _ in range(n_images)]
    b, kp, desc, r = (torch.cat([f[i] for f in found]) for i in range(4))
    order = torch.argsort(b, stable=True)  # by image; within one, as found
    counts = torch.bincount(b, minlength=n_images).tolist()
    out = []
    for kp_i, desc_i, r_i in zip(*(torch.split(t[order], counts) for t in (kp, desc, r)),
                                 strict=True):
        if kp_i.shape[0] > cfg.max_num_features:
            top = torch.topk(r_i, cfg.max_num_features).indices
            kp_i, desc_i, r_i = kp_i[top], desc_i[top], r_i[top]
        out.append(SiftFeatures(kp_i, desc_i.float(), r_i))
    return out
