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
