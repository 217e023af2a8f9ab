"""Files the package installs beside its code (``params/``): found beside the package in a
source checkout or an editable install, else in the package's ament share folder (colcon /
pip install of the ROS package). Pure Python: the ROS-free tools use it too."""

from __future__ import annotations

from pathlib import Path

from sfm_ttr_ros.ros.names import PACKAGE


def share_candidates(folder: str, name: str) -> list[Path]:
    """Where ``<folder>/<name>`` may be, in the order looked at."""
    tried = [Path(__file__).resolve().parents[2] / folder / name]
    try:
        from ament_index_python.packages import get_package_share_directory

        tried.append(Path(get_package_share_directory(PACKAGE)) / folder / name)
    except Exception:  # not installed, no AMENT_PREFIX_PATH, no ament_index_python
        pass
    return tried


def find_share_file(folder: str, name: str) -> Path | None:
    """The first existing :func:`share_candidates` path, or None."""
    return next((p for p in share_candidates(folder, name) if p.is_file()), None)
