"""Shared pytest set-up: ROS 2 isolation and thread limits (set at import time, before any test
module imports rclpy or torch) and the fixtures for the data in ../shared/data."""

from __future__ import annotations

import inspect
import os
import random
from pathlib import Path

import pytest

# DDS discovery stays on this machine, and a random domain per run keeps parallel test runs
# (several developers, CI) from seeing each other's nodes and topics.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ["ROS_DOMAIN_ID"] = str(random.SystemRandom().randint(1, 100))
# 2 cores: keep BLAS / OpenMP / torch from oversubscribing them.
for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_var, "2")

try:
    import torch
except ImportError:  # the core tests that need torch import it themselves and fail clearly
    torch = None
else:
    torch.set_num_threads(2)

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def repo_root() -> Path:
    """The repository root (the folder holding package.xml and setup.py)."""
    return REPO_ROOT


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` beside the repository root (hololens_000, the KITTI calibration);
    skips the test when it is absent (a clone without the shared folder)."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data folder not found: {SHARED_DATA} (it lives beside the "
                    f"repository root as ../shared/data)")
    return SHARED_DATA


@pytest.fixture(scope="module")
def one_thread():
    """Torch single-threaded for a module: a tiny network on a busy 2-core machine measured 9x
    slower per step with 2 threads than with 1 (thread hand-offs dominate)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(scope="module")
def context():
    """An rclpy Context initialised for one test module (its nodes are independent of any other
    module's), shut down afterwards; skips the module without rclpy."""
    rclpy = pytest.importorskip("rclpy")
    from rclpy.context import Context

    ctx = Context()
    rclpy.init(context=ctx)
    yield ctx
    ctx.try_shutdown()


def tiny_model(input_size: tuple[int, int] = (64, 208), *, downsample: bool = True,
               batch_norm: int = 0, seed: int = 0):
    """A network small enough that a few refinement steps take well under a second; the same
    arguments give the same weights (``seed``), which the tests' numbers rely on.

    Encoder: Conv 3->8 (stride 2 when ``downsample``), a BatchNorm when ``batch_norm`` >= 1, ReLU,
    Conv 8->8, then BatchNorm + ReLU when ``batch_norm`` == 2. Decoder: Conv 8->1, an x2
    upsampling when ``downsample`` (the output is at the input size), sigmoid disparity.
    Imports torch itself: this function's source is also the plug-in of :func:`write_tiny_plugin`.
    """
    import torch
    from torch import nn

    from sfm_ttr_ros.core.models.base import EncoderDecoder

    torch.manual_seed(seed)
    enc = [nn.Conv2d(3, 8, 3, 2 if downsample else 1, 1)]
    enc += [nn.BatchNorm2d(8)] if batch_norm >= 1 else []
    enc += [nn.ReLU(), nn.Conv2d(8, 8, 3, 1, 1)]
    enc += [nn.BatchNorm2d(8), nn.ReLU()] if batch_norm == 2 else []
    dec = [nn.Conv2d(8, 1, 3, 1, 1)]
    dec += [nn.Upsample(scale_factor=2)] if downsample else []
    dec += [nn.Sigmoid()]
    return EncoderDecoder(nn.Sequential(*enc), nn.Sequential(*dec), tuple(input_size)).eval()


def write_tiny_plugin(path: Path, height: int, width: int) -> Path:
    """A plug-in model module (``python:<module>:factory``) with :func:`tiny_model` at the
    given input size, written to ``path`` (for a CLI or a subprocess, which cannot import
    conftest)."""
    factory = (f"\n\ndef factory(config=None):\n"
               f"    return tiny_model(({int(height)}, {int(width)}))\n")
    path.write_text(inspect.getsource(tiny_model) + factory)
    return path


@pytest.fixture(scope="session")
def tiny_plugin():
    """:func:`write_tiny_plugin`, for tests that hand the model to a CLI or a subprocess."""
    return write_tiny_plugin


def write_small_kitti_params(repo: Path, path: Path) -> Path:
    """params/kitti.yaml with the windows and thresholds of tiny generated drives (windows of 4
    every 2, the whole encoder refined, fewer points and features) at ``path``."""
    text = (repo / "params" / "kitti.yaml").read_text()
    small = {"window_size": 4, "window_stride": 2, "refinement.frozen_encoder_levels": 0,
             "min_supervision_points": 20, "sfm.max_num_features": 2048}
    for key in small:  # added to the file's one section: none of them there yet
        assert f"    {key}:" not in text, key
    text += "".join(f"    {key}: {value}\n" for key, value in small.items())
    path.write_text(text)
    return path


def open_hololens(shared: Path):
    """hololens_000 as an image sequence (GT in mm); the test is skipped without the data."""
    from sfm_ttr_ros.data.sequence import open_image_folder

    root = shared / "hololens_000"
    if not root.is_dir():
        pytest.skip(f"{root} not found")
    return open_image_folder(root / "images", root / "K.txt", root / "depth", gt_scale=1000.0)
