"""The geometry the stages share, below them all: camera centres, the rotation nearest a
matrix, the similarity between two reconstructions' frames, and a depth map read at pixels.

Poses are ``cam_from_world`` (COLMAP's convention): x_cam = R·x_world + t, 4 x 4 or 3 x 4.
Pixels follow OpenCV's convention (x right, y down, (0, 0) the first pixel's centre).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F


def camera_centre(cam_from_world: np.ndarray) -> np.ndarray:
    """C = −Rᵀt, the camera's centre in the world (Hartley & Zisserman 2003, Sec. 6.1:
    x_cam = R·(x_world − C)), of one 4 x 4 (or 3 x 4) ``cam_from_world`` (→ 3) or of a stack
    N x 4 x 4 (→ N x 3)."""
    T = np.asarray(cam_from_world, np.float64)
    R, t = T[..., :3, :3], T[..., :3, 3]
    return -(np.swapaxes(R, -1, -2) @ t[..., None])[..., 0]


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation nearest ``M`` in the Frobenius norm: U·diag(1, 1, ±1)·Vᵀ of M's SVD, the
    sign making it a rotation, not a reflection (Kabsch 1976; the sign as in Umeyama 1991).
    For M = Σ b_i a_iᵀ the rotation that best turns the a_i onto the b_i; for M a sum of
    rotations their chordal L2 mean (Hartley et al. 2013, "Rotation Averaging")."""
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return U @ D @ Vt


def rotation_angle(R: np.ndarray) -> float:
    """The angle (rad) of a rotation: acos((tr R − 1)/2), clipped to acos's domain."""
    return math.acos(max(-1.0, min(1.0, (np.trace(R) - 1.0) / 2.0)))


@dataclass
class Similarity:
    """x_odom = s·R·x_world + t, and the mean squared residuals of the fit that chose it."""

    s: float
    R: np.ndarray
    t: np.ndarray
    position_res2: float = 0.0
    rotation_res2: float = 0.0

    def apply(self, cam_from_world: np.ndarray) -> np.ndarray:
        """odom_from_camera of a camera whose pose in the world is ``cam_from_world``."""
        out = np.eye(4)
        out[:3, :3] = self.R @ cam_from_world[:3, :3].T
        out[:3, 3] = self.s * self.R @ camera_centre(cam_from_world) + self.t
        return out


def fit_similarity(path_poses: list[np.ndarray], cam_from_world: list[np.ndarray],
                   scale: float | None) -> Similarity | None:
    """S with S·world_from_cam_i ≈ path_pose_i (``odom_from_camera``) over shared frames: R the
    chordal L2 mean of R_path·R_worldᵀ (:func:`nearest_rotation`), then, with R fixed,
    Umeyama 1991's least-squares scale s = Σ R(c_i − c̄)·(p_i − p̄) / Σ |c_i − c̄|² of the camera
    centres c_i onto the path positions p_i (``scale`` given: kept) and t = p̄ − s·R·c̄. The
    residuals: mean squared of the centres and of the rotations' angles. None when it cannot be
    fitted (no frames, or a fitted scale from fewer than two distinct centres)."""
    if not path_poses:
        return None
    M = sum(P[:3, :3] @ T[:3, :3] for P, T in zip(path_poses, cam_from_world, strict=True))
    R = nearest_rotation(M)
    c = np.array([camera_centre(T) for T in cam_from_world])
    p = np.array([P[:3, 3] for P in path_poses])
    rc = (c - c.mean(0)) @ R.T
    if scale is None:
        denom = float(np.sum(rc * rc))
        if len(path_poses) < 2 or denom <= 1e-12:
            return None
        scale = float(np.sum(rc * (p - p.mean(0)))) / denom
        if not (math.isfinite(scale) and scale > 0):
            return None
    t = p.mean(0) - scale * R @ c.mean(0)
    res = p - (scale * c @ R.T + t)
    rot = [rotation_angle(P[:3, :3] @ (R @ T[:3, :3].T).T)
           for P, T in zip(path_poses, cam_from_world, strict=True)]
    return Similarity(scale, R, t, float(np.mean(np.sum(res * res, 1))),
                      float(np.mean(np.square(rot))))


def normalized_grid(pixels: np.ndarray, width: int, height: int) -> torch.Tensor:
    """Pixel centres (OpenCV convention) of an image of width x height → grid_sample coords:
    (x + 0.5)/width·2 − 1 (``align_corners=False``: −1 and 1 are the image's outer edges)."""
    g = np.empty((1, 1, len(pixels), 2), np.float32)
    g[0, 0, :, 0] = (pixels[:, 0] + 0.5) / width * 2.0 - 1.0
    g[0, 0, :, 1] = (pixels[:, 1] + 0.5) / height * 2.0 - 1.0
    return torch.from_numpy(g)


def sample_depth(depth: torch.Tensor, grid: torch.Tensor, mode: str = "bilinear") -> torch.Tensor:
    """Read a 1 x 1 x h x w depth map at grid points (any resolution: coords are normalised),
    the edge value beyond the border: D(p) of Eq. (4) and (5)."""
    return F.grid_sample(depth, grid, mode=mode, padding_mode="border",
                         align_corners=False).reshape(-1)


def sample_at(depth: np.ndarray, pixels: np.ndarray, mode: str = "bilinear") -> np.ndarray:
    """An image-resolution depth map read at pixels (OpenCV convention): D_nn(p_lj) of
    Eq. (4)."""
    d = torch.from_numpy(np.ascontiguousarray(depth, np.float32))[None, None]
    return sample_depth(d, normalized_grid(pixels, depth.shape[1], depth.shape[0]), mode).numpy()
