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


def build_octaves(img, cfg: TorchSiftConfig):
    """Gaussian and DoG pyramids (Lowe 2004, Sec. 3): a list of (octave index o, Gaussian
    levels (S+3, H_o, W_o), DoG levels (S+2, H_o, W_o)); octave o's pixel i has its centre at
    (i + 0.5) * 2**o in the input image's corner convention."""
    import torch.nn.functional as F

    S = cfg.num_scales
    x = img[None, None]
    o = int(cfg.first_octave)
    if o < 0:
        for _ in range(-o):
            x = F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=False)
    elif o > 0:
        for _ in range(o):
            x = F.avg_pool2d(x, 2)
    blur = INPUT_BLUR * 2.0 ** (-o)
    x = gaussian_blur(x, math.sqrt(max(SIGMA0**2 - blur**2, 0.0)))
    k = 2.0 ** (1.0 / S)
    out = []
    while min(x.shape[-2:]) >= cfg.min_octave_size:
        levels = [x]
        for s in range(1, S + 3):
            sig_prev = SIGMA0 * k ** (s - 1)
            sig_inc = sig_prev * math.sqrt(k * k - 1.0)
            levels.append(gaussian_blur(levels[-1], sig_inc))
        gauss = torch_cat([lv[0] for lv in levels])  # (S+3, H, W)
        out.append((o, gauss, gauss[1:] - gauss[:-1]))
        x = F.avg_pool2d(levels[S], 2)  # twice sigma0: the next octave's first level
        o += 1
    return out


def torch_cat(tensors):
    import torch

    return torch.cat(tensors, 0)


def _extrema(dog, cfg: TorchSiftConfig):
    """Scale-space extrema of one octave's DoG (S+2, H, W): (s, y, x) integer indices (Sec.
    3.1), one pixel away from every border."""
    import torch
    import torch.nn.functional as F

    d = dog[:, None]  # 3x3 in space (max_pool2d), then 3 in scale: cheaper than max_pool3d
    mx = F.max_pool2d(d, 3, stride=1, padding=1)[:, 0]
    mn = -F.max_pool2d(-d, 3, stride=1, padding=1)[:, 0]
    mx = torch.maximum(torch.maximum(mx[:-2], mx[1:-1]), mx[2:])
    mn = torch.minimum(torch.minimum(mn[:-2], mn[1:-1]), mn[2:])
    pad = torch.zeros_like(dog[:1])
    mx, mn = torch.cat([pad, mx, pad]), torch.cat([pad, mn, pad])  # ends are excluded below
    thr = 0.8 * cfg.peak_threshold if cfg.refine else cfg.peak_threshold
    is_ext = ((dog == mx) & (dog > thr)) | ((dog == mn) & (dog < -thr))
    is_ext[0] = False
    is_ext[-1] = False
    is_ext[:, :1] = False
    is_ext[:, -1:] = False
    is_ext[:, :, :1] = False
    is_ext[:, :, -1:] = False
    return torch.nonzero(is_ext, as_tuple=True)


def _taylor(D, s, y, x):
    """Value, gradient (3) and Hessian (3 x 3) of D in (x, y, sigma) at integer samples by
    finite differences (Lowe 2004, Sec. 4)."""
    import torch

    def at(ds, dy, dx):
        return D[s + ds, y + dy, x + dx]

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


def _localise(dog, s, y, x, cfg: TorchSiftConfig):
    """Sec. 4 and 4.1 for one octave: the subpixel / subscale offset x̂ = −H⁻¹ g of the
    quadratic Taylor fit of D, Eq. (3); where it exceeds ``max_offset`` (0.5 in Lowe) in a
    dimension the sample moves one step that way and the fit is repeated (up to
    ``refine_iterations`` times; then discarded); the contrast of the fit D(x̂), Eq. (3), and
    the edge test (ratio of principal curvatures of the 2 x 2 spatial Hessian, Sec. 4.1) at the
    final sample. Returns (keep mask, xs, ys, ss: refined coordinates, value: D(x̂))."""
    import torch

    L, Hh, Ww = dog.shape
    off = torch.zeros(s.shape[0], 3, device=dog.device, dtype=dog.dtype)
    if cfg.refine:
        ok = torch.ones_like(s, dtype=torch.bool)
        for it in range(max(1, cfg.refine_iterations)):
            v, g, H = _taylor(dog, s, y, x)
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
        value = v + 0.5 * (g * off).sum(-1)  # D(x̂), Sec. 4
        keep = ok
    else:
        v, g, H = _taylor(dog, s, y, x)
        value = v
        keep = torch.ones_like(s, dtype=torch.bool)
    dxx, dyy, dxy = H[:, 0, 0], H[:, 1, 1], H[:, 0, 1]
    tr, det = dxx + dyy, dxx * dyy - dxy * dxy
    r = cfg.edge_threshold
    keep &= (det > 0) & (tr * tr * r < (r + 1) ** 2 * det)
    keep &= value.abs() > cfg.peak_threshold
    # candidates that converged on the same sample are one keypoint
    lin = (s * Hh + y) * Ww + x
    first = torch.full((L * Hh * Ww,), lin.numel(), device=lin.device, dtype=torch.long)
    idx = torch.arange(lin.numel(), device=lin.device)
    first.scatter_reduce_(0, lin[keep], idx[keep], reduce="amin")
    keep &= first[lin] == idx
    xs = x.to(dog.dtype) + off[:, 0]
    ys = y.to(dog.dtype) + off[:, 1]
    ss = s.to(dog.dtype) + off[:, 2]
    return keep, xs, ys, ss, value


def _gradients(gauss):
    """Gradient magnitude and orientation of Gaussian levels (L, H, W), central differences
    (Lowe 2004, Sec. 5)."""
    import torch
    import torch.nn.functional as F

    p = F.pad(gauss[:, None], (1, 1, 1, 1), mode="replicate")[:, 0]
    gx = 0.5 * (p[:, 1:-1, 2:] - p[:, 1:-1, :-2])
    gy = 0.5 * (p[:, 2:, 1:-1] - p[:, :-2, 1:-1])
    return torch.sqrt(gx * gx + gy * gy), torch.atan2(gy, gx)


def _orientations(mag, ang, lvl, ys, xs, sigma, cfg: TorchSiftConfig):
    """Sec. 5: dominant orientations of keypoints at (lvl, ys, xs) with scale ``sigma`` (octave
    pixels). Returns (index of the keypoint, angle in radians) for every peak kept."""
    import torch

    dev, dt = mag.device, mag.dtype
    n = xs.shape[0]
    win_sigma = ORI_SIGMA_FACTOR * sigma  # (n,)
    R = int(math.ceil(3.0 * float(win_sigma.max()))) if n else 1
    off = torch.arange(-R, R + 1, device=dev)
    oy, ox = torch.meshgrid(off, off, indexing="ij")
    oy, ox = oy.reshape(-1), ox.reshape(-1)
    H, W = mag.shape[-2:]
    cy, cx = torch.round(ys).long(), torch.round(xs).long()
    py, px = cy[:, None] + oy[None], cx[:, None] + ox[None]  # (n, P)
    inside = (py >= 0) & (py < H) & (px >= 0) & (px < W)
    py, px = py.clamp(0, H - 1), px.clamp(0, W - 1)
    L = lvl[:, None].expand_as(py)
    m = mag[L, py, px]
    a = ang[L, py, px]
    ry = py.to(dt) - ys[:, None]
    rx = px.to(dt) - xs[:, None]
    r2 = rx * rx + ry * ry
    w = torch.exp(-r2 / (2 * win_sigma[:, None] ** 2)) * m
    w = w * (inside & (r2 <= (3.0 * win_sigma[:, None]) ** 2))
    b = (a % (2 * math.pi)) * (ORI_BINS / (2 * math.pi))
    b0 = torch.floor(b)
    frac = b - b0
    b0 = b0.long() % ORI_BINS
    hist = torch.zeros(n, ORI_BINS, device=dev, dtype=dt)
    hist.scatter_add_(1, b0, w * (1 - frac))
    hist.scatter_add_(1, (b0 + 1) % ORI_BINS, w * frac)
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
    kp_idx = torch.arange(n, device=dev)[:, None].expand(-1, k)[sel]
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


def _descriptors(gauss, lvl, ys, xs, sigma, theta, cfg: TorchSiftConfig):
    """Sec. 6.1: 128-d descriptors of keypoints (Gaussian level, position, sigma in octave
    pixels, orientation). The window, 3 sigma per spatial bin, is resampled (bilinear) on a
    grid rotated by the keypoint's orientation, so that gradients of the resampled patch are
    already relative to it; each gradient is Gaussian-weighted (sigma: half the window) and
    spread trilinearly over the 4x4x8 bins."""
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
    for level in torch.unique(lvl).tolist():
        sel = torch.nonzero(lvl == level, as_tuple=True)[0]
        grid = torch.stack([(gx[sel] + 0.5) / W * 2 - 1, (gy[sel] + 0.5) / H * 2 - 1], -1)
        img = gauss[level][None, None].expand(sel.numel(), 1, H, W)
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
    [0, 1]) on ``device``."""
    import torch

    cfg = cfg or TorchSiftConfig()
    if isinstance(image, torch.Tensor):
        img = image.to(device=device, dtype=torch.float32)
    else:
        img = torch.from_numpy(np.ascontiguousarray(to_gray(image))).to(device)
    if img.ndim != 2:
        raise ValueError(f"expected a 2-D gray image, got shape {tuple(img.shape)}")
    S = cfg.num_scales
    kps, descs, resp = [], [], []
    with torch.no_grad():
        for o, gauss, dog in build_octaves(img, cfg):
            s, y, x = _extrema(dog, cfg)
            if s.numel() == 0:
                continue
            keep, xs, ys, ss, value = _localise(dog, s, y, x, cfg)
            xs, ys, ss, value = xs[keep], ys[keep], ss[keep], value[keep]
            H, W = dog.shape[-2:]
            inb = (xs >= 0) & (xs <= W - 1) & (ys >= 0) & (ys <= H - 1)
            xs, ys, ss, value = xs[inb], ys[inb], ss[inb], value[inb]
            if xs.numel() == 0:
                continue
            # the DoG level s lies between Gaussian levels s and s+1: sigma0 * k^s (Sec. 3)
            sigma = SIGMA0 * 2.0 ** (ss / S)
            lvl = torch.round(ss).long().clamp(0, S + 2)  # the Gaussian level nearest in scale
            mag, ang = _gradients(gauss)
            ki, theta = _orientations(mag, ang, lvl, ys, xs, sigma, cfg)
            if ki.numel() == 0:
                continue
            d = _descriptors(gauss, lvl[ki], ys[ki], xs[ki], sigma[ki], theta, cfg)
            f = 2.0 ** o
            kp = torch.stack([(xs[ki] + 0.5) * f, (ys[ki] + 0.5) * f, sigma[ki] * f, theta], 1)
            kps.append(kp)
            descs.append(d)
            resp.append(value[ki].abs())
    dev = img.device
    if not kps:
        return SiftFeatures(torch.zeros(0, 4, device=dev), torch.zeros(0, 128, device=dev),
                            torch.zeros(0, device=dev))
    kp, desc, r = torch.cat(kps), torch.cat(descs), torch.cat(resp)
    if kp.shape[0] > cfg.max_num_features:
        top = torch.topk(r, cfg.max_num_features).indices
        kp, desc, r = kp[top], desc[top], r[top]
    return SiftFeatures(kp, desc.float(), r)
