"""A synthetic distorted camera for the undistortion tests: bright dots drawn where a lens with
known K and D images a grid of directions (cv2's projectPoints, the fisheye's for
``equidistant``), and the dots found again in an image."""

from __future__ import annotations

import cv2
import numpy as np

SIZE = (320, 240)  # width, height
K = np.array([[260.0, 0.0, 161.0], [0.0, 255.0, 118.0], [0.0, 0.0, 1.0]])
PLUMB_BOB = (-0.32, 0.11, 0.001, -0.0015, -0.02)
EQUIDISTANT = (0.08, -0.03, 0.01, -0.002)


def directions(span: float = 0.45, n: int = 5) -> np.ndarray:
    """N x 3 unit-depth rays (x, y, 1) on an n x n grid over [-span, span]^2."""
    g = np.linspace(-span, span, n)
    x, y = np.meshgrid(g, g * 0.75)
    return np.stack([x.ravel(), y.ravel(), np.ones(x.size)], axis=1)


def distorted_pixels(rays: np.ndarray, model: str, D) -> np.ndarray:
    """Where the distorted camera (K, ``D`` of ``model``) images ``rays``: N x 2."""
    zero = np.zeros(3)
    D = np.asarray(D, np.float64)
    if model == "equidistant":
        px, _ = cv2.fisheye.projectPoints(rays.reshape(1, -1, 3), zero, zero, K, D)
    else:
        px, _ = cv2.projectPoints(rays, zero, zero, K, D)
    return px.reshape(-1, 2)


def pinhole_pixels(rays: np.ndarray, K_new: np.ndarray) -> np.ndarray:  # noqa: N803
    """Where a pinhole camera ``K_new`` images ``rays``: N x 2."""
    p = rays @ np.asarray(K_new).T
    return p[:, :2] / p[:, 2:]


def dots_image(pixels: np.ndarray, size=SIZE, sigma: float = 1.2) -> np.ndarray:
    """An RGB uint8 image with a Gaussian dot at each (sub-pixel) position of ``pixels``."""
    w, h = size
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.zeros((h, w), np.float64)
    for u, v in pixels:
        img += np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * sigma**2))
    gray = np.clip(img * 255, 0, 255).astype(np.uint8)
    return np.repeat(gray[:, :, None], 3, axis=2)


def dot_centres(image: np.ndarray, near: np.ndarray, radius: int = 5) -> np.ndarray:
    """The intensity-weighted centre of the dot in a window of ``radius`` px around each
    position of ``near``: N x 2."""
    gray = image[:, :, 0].astype(np.float64)
    out = []
    for u, v in near:
        x0, y0 = int(round(u)) - radius, int(round(v)) - radius
        patch = gray[max(y0, 0):y0 + 2 * radius + 1, max(x0, 0):x0 + 2 * radius + 1]
        yy, xx = np.mgrid[0:patch.shape[0], 0:patch.shape[1]]
        total = patch.sum()
        out.append((np.nan, np.nan) if total == 0 else
                   ((xx * patch).sum() / total + max(x0, 0),
                    (yy * patch).sum() / total + max(y0, 0)))
    return np.asarray(out)
