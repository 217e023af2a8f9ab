"""Shared pytest set-up: ROS 2 isolation and thread limits (set at import time, before any test
module imports rclpy or torch) and the fixtures for the data in ../shared/data."""

from __future__ import annotations

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


TINY_PLUGIN = '''
import torch
from torch import nn
from sfm_ttr_ros.core.models.base import EncoderDecoder

def factory(config=None):
    torch.manual_seed(0)
    enc = nn.Sequential(nn.Conv2d(3, 8, 3, 2, 1), nn.ReLU(), nn.Conv2d(8, 8, 3, 1, 1))
    dec = nn.Sequential(nn.Conv2d(8, 1, 3, 1, 1), nn.Upsample(scale_factor=2), nn.Sigmoid())
    return EncoderDecoder(enc, dec, ({height}, {width})).eval()
'''


def write_tiny_plugin(path: Path, height: int, width: int) -> Path:
    """A plug-in model module (``python:<module>:factory``) with a tiny network at the given
    input size, written to ``path``."""
    path.write_text(TINY_PLUGIN.format(height=height, width=width))
    return path


@pytest.fixture(scope="session")
def tiny_plugin():
    """:func:`write_tiny_plugin`, for tests that hand the model to a CLI or a subprocess."""
    return write_tiny_plugin
