"""The package skeleton: package.xml (as catkin_pkg and colcon read it), the single-source version,
and the install layout that `colcon build` produces and `ros2 run` relies on."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PKG = "sfm_ttr_ros"
PY_VERSION = f"python{sys.version_info.major}.{sys.version_info.minor}"

EXEC_DEPENDS = {
    "rclpy",
    "sensor_msgs",
    "std_msgs",
    "diagnostic_msgs",
    "nav_msgs",
    "geometry_msgs",
    "rcl_interfaces",
    "builtin_interfaces",
    "python3-numpy",
    "python3-opencv",
    "python3-torch",
    "python3-yaml",
    "rosgraph_msgs",
    "launch",
    "launch_ros",
    "ament_index_python",
}
EXECUTABLES = {"refiner": "sfm_ttr_ros.ros.node", "sfm-ttr": "sfm_ttr_ros.tools.cli"}


@pytest.fixture(scope="module")
def package():
    catkin_pkg_package = pytest.importorskip("catkin_pkg.package")
    return catkin_pkg_package.parse_package(str(REPO / "package.xml"))


def test_package_xml_is_valid_format_3(package):
    package.validate()  # raises InvalidPackage (a rejected maintainer e-mail included)
    assert package.package_format == 3
    assert package.name == PKG
    assert package.get_build_type() == "ament_python"
    assert [str(lic) for lic in package.licenses] == ["MIT"]
    assert package.maintainers and package.maintainers[0].email
    assert package.description.strip()


def test_package_xml_rosdep_keys(package):
    assert {d.name for d in package.exec_depends} == EXEC_DEPENDS
    assert {d.name for d in package.test_depends} == {"python3-pytest"}
    # ament_python packages declare no buildtool_depend (as `ros2 pkg create` generates them).
    assert not package.buildtool_depends


def test_version_has_one_source(package):
    out = subprocess.run([sys.executable, "setup.py", "--version"], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    setup_version = out.stdout.strip().splitlines()[-1]
    import sfm_ttr_ros

    assert setup_version == package.version
    assert sfm_ttr_ros.__version__ == package.version


def test_colcon_identifies_an_ament_python_package():
    # colcon identifies a ROS package through catkin_pkg; when catkin_pkg rejects package.xml
    # (e.g. the maintainer's e-mail) colcon silently falls back to a plain Python package and
    # `ros2 run` can no longer find it.
    ident = pytest.importorskip("colcon_core.package_identification")
    desc = ident.identify(ident.get_package_identification_extensions(), str(REPO))
    assert (desc.type, desc.name) == ("ros.ament_python", PKG)


def test_requirements_txt_lists_the_deps_without_rosdep_key():
    lines = [ln.split("#")[0].strip() for ln in
             (REPO / "requirements.txt").read_text().splitlines()]
    names = {ln.split(";")[0].split(">")[0].split("<")[0].split("=")[0].strip()
             for ln in lines if ln}
    assert names == {"pycolmap", "rosbags", "cmeel-mimalloc"}


def _colcon() -> list[str]:
    exe = Path(sys.executable).parent / "colcon"
    if exe.is_file():
        return [str(exe)]
    found = shutil.which("colcon")
    if found is None:
        pytest.skip("colcon is not installed (pip install -e '.[dev]')")
    return [found]


def _run(cmd: list[str], cwd: Path, env: dict[str, str] | None = None, timeout: float = 120):
    out = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, (
        f"{' '.join(cmd)} exited {out.returncode}\n--- stdout\n{out.stdout[-4000:]}"
        f"\n--- stderr\n{out.stderr[-4000:]}")
    return out


@pytest.fixture(scope="module")
def colcon_install(tmp_path_factory) -> Path:
    """`colcon build` of the repository into a temporary build/install base; returns the
    package's install prefix (colcon's default isolated layout: <install-base>/sfm_ttr_ros)."""
    tmp = tmp_path_factory.mktemp("colcon")
    colcon = _colcon()
    _run(colcon + ["--log-base", str(tmp / "log"), "build", "--paths", str(REPO),
                   "--build-base", str(tmp / "build"), "--install-base", str(tmp / "install")],
         cwd=tmp, timeout=120)
    return tmp / "install" / PKG


def _install_env(prefix: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["AMENT_PREFIX_PATH"] = str(prefix)
    env["PYTHONPATH"] = str(prefix / "lib" / PY_VERSION / "site-packages")
    return env


@pytest.mark.slow
def test_colcon_install_layout(colcon_install: Path):
    prefix = colcon_install
    assert (prefix / "share/ament_index/resource_index/packages" / PKG).is_file()
    assert (prefix / "share" / PKG / "package.xml").read_bytes() == \
        (REPO / "package.xml").read_bytes()
    # colcon-ros's ament_python hook: present only when colcon built it as a ROS package.
    assert (prefix / "share" / PKG / "hook/ament_prefix_path.dsv").is_file()
    for name in EXECUTABLES:
        exe = prefix / "lib" / PKG / name
        assert exe.is_file(), f"{exe} missing: `ros2 run {PKG} {name}` would not find it"
        assert os.access(exe, os.X_OK)
        assert f"'{name}'" in exe.read_text()
    for yaml_file in sorted((REPO / "params").glob("*.yaml")):
        assert (prefix / "share" / PKG / "params" / yaml_file.name).is_file()
    # `ros2 launch sfm_ttr_ros refiner.launch.py` looks in share/<pkg>/launch
    launch_files = sorted((REPO / "launch").glob("*.launch.py"))
    assert [p.name for p in launch_files] == ["refiner.launch.py"]
    for launch_file in launch_files:
        installed = prefix / "share" / PKG / "launch" / launch_file.name
        assert installed.read_bytes() == launch_file.read_bytes()


@pytest.mark.slow
def test_colcon_installs_every_module_and_the_weights(colcon_install: Path):
    site = colcon_install / "lib" / PY_VERSION / "site-packages"
    wanted = {p.relative_to(REPO) for top in (PKG, "msg_adapters")
              for p in (REPO / top).rglob("*.py") if "__pycache__" not in p.parts}
    wanted |= {p.relative_to(REPO) for p in (REPO / PKG / "core/models/weights").glob("*.pth")}
    assert wanted, "no sources found"
    missing = sorted(str(p) for p in wanted if not (site / p).is_file())
    assert not missing, f"not installed: {missing}"
    assert not (site / "tests").exists()


@pytest.mark.slow
def test_ament_index_finds_the_installed_package(colcon_install: Path, tmp_path: Path):
    code = ("from ament_index_python.packages import get_package_prefix, "
            "get_package_share_directory\n"
            f"print(get_package_prefix('{PKG}'))\n"
            f"print(get_package_share_directory('{PKG}'))\n"
            "import sfm_ttr_ros, msg_adapters\n"
            "print(sfm_ttr_ros.__file__)\nprint(msg_adapters.__file__)\n")
    pytest.importorskip("ament_index_python")
    out = _run([sys.executable, "-c", code], cwd=tmp_path, env=_install_env(colcon_install),
               timeout=60)
    prefix, share, core_file, adapters_file = out.stdout.split()[-4:]
    assert Path(prefix) == colcon_install
    assert Path(share) == colcon_install / "share" / PKG
    # The installed copies are imported, not the source tree.
    assert Path(core_file).is_relative_to(colcon_install)
    assert Path(adapters_file).is_relative_to(colcon_install)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(EXECUTABLES))
def test_installed_entry_points_load(colcon_install: Path, tmp_path: Path, name: str):
    module = EXECUTABLES[name]
    if not (REPO / (module.replace(".", "/") + ".py")).is_file():
        pytest.skip(f"{module} is not written yet")
    code = ("from importlib.metadata import distribution\n"
            f"eps = [e for e in distribution('{PKG}').entry_points "
            f"if e.group == 'console_scripts' and e.name == '{name}']\n"
            "func = eps[0].load()\n"
            "print(func.__module__, callable(func), __import__(func.__module__).__file__)\n")
    out = _run([sys.executable, "-c", code], cwd=tmp_path, env=_install_env(colcon_install),
               timeout=120)
    mod, is_callable, origin = out.stdout.split()[-3:]
    assert (mod, is_callable) == (module, "True")
    assert Path(origin).is_relative_to(colcon_install)


@pytest.mark.slow
def test_installed_launch_file_finds_and_checks_the_installed_params(colcon_install: Path,
                                                                   tmp_path: Path):
    pytest.importorskip("ament_index_python")
    launch_file = colcon_install / "share" / PKG / "launch" / "refiner.launch.py"
    code = ("import importlib.util\n"
            "spec = importlib.util.spec_from_file_location("
            f"'refiner_launch', {str(launch_file)!r})\n"
            "m = importlib.util.module_from_spec(spec)\n"
            "spec.loader.exec_module(m)\n"
            "default = m.default_params_file()\n"
            "assert m.launch_params.node_parameters(default)\n"
            "print(default)\nprint(m.names.__file__)\n")
    out = _run([sys.executable, "-c", code], cwd=tmp_path, env=_install_env(colcon_install),
               timeout=120)
    default, names_file = out.stdout.split()[-2:]
    assert Path(default) == colcon_install / "share" / PKG / "params" / "refiner.yaml"
    assert Path(names_file).is_relative_to(colcon_install)
