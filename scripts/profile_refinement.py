#!/usr/bin/env python3
"""Where a window's refinement step spends its time, per step mode (eager, static, a CUDA
graph), with torch.profiler: per-step host time, kernel launches (aten ops on the CPU), device
busy time, which mode ran; optionally the step micro-benchmark and the window's SfM with
pycolmap's and the torch features. The logic is sfm_ttr_ros/tools/step_profile.py.

Examples::

    # one 15-frame window of a generated drive on CUDA: eager against the graph
    .venv/bin/python scripts/profile_refinement.py --kitti-raw out/raw --set device=cuda \\
        --modes eager auto --micro-steps 200 --sfm-features colmap torch --out out/profile.json
    # small, on the CPU
    .venv/bin/python scripts/profile_refinement.py --kitti-raw out/raw --window 4 --steps 6 \\
        --modes eager static
"""

from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run from a source checkout without installing
    sys.path.insert(0, str(REPO))

from sfm_ttr_ros.tools.step_profile import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
