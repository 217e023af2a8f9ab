"""launch/refiner.launch.py without the `launch` packages (not installable from PyPI): it
compiles, its Node action and arguments match sfm_ttr_ros.ros.names and the node (read from the
AST), and the parameter file it hands the node applies in a namespace (rclpy)."""

from __future__ import annotations

import ast
import importlib.util
import os
import random
from pathlib import Path

import pytest
import yaml

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.ros import names

REPO = Path(__file__).resolve().parents[1]
LAUNCH = REPO / "launch" / "refiner.launch.py"
ARGUMENTS = {"params_file", "image_topic", "camera_info_topic", "namespace"}


def _tree() -> ast.Module:
    return ast.parse(LAUNCH.read_text(encoding="utf-8"), filename=str(LAUNCH))


def _load_module():
    """The launch file as a module (it imports `launch` only inside
    generate_launch_description, which is not called)."""
    spec = importlib.util.spec_from_file_location("refiner_launch", LAUNCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _call(tree: ast.AST, func: str) -> list[ast.Call]:
    return [n for n in ast.walk(tree) if isinstance(n, ast.Call)
            and isinstance(n.func, ast.Name) and n.func.id == func]


def _src(node: ast.AST) -> str:
    return ast.unparse(node)


def test_it_compiles():
    compile(LAUNCH.read_text(encoding="utf-8"), str(LAUNCH), "exec")
    names_in_module = {n.name for n in _tree().body if isinstance(n, ast.FunctionDef)}
    assert "generate_launch_description" in names_in_module


def test_arguments_are_declared_and_every_one_is_used():
    module = _load_module()
    assert set(module.ARGUMENTS) == ARGUMENTS
    tree = _tree()
    used = {c.args[0].value for c in _call(tree, "LaunchConfiguration")}
    assert used == ARGUMENTS
    (declare,) = _call(tree, "DeclareLaunchArgument")  # one call, over ARGUMENTS
    assert _src(declare.args[0]) == "name"


def test_the_node_action_matches_names_and_the_executable():
    (node,) = _call(_tree(), "Node")
    kw = {k.arg: k.value for k in node.keywords}
    assert _src(kw["package"]) == "names.PACKAGE" and names.PACKAGE == "sfm_ttr_ros"
    assert _src(kw["name"]) == "names.NODE_NAME"
    assert _src(kw["namespace"]) == "LaunchConfiguration('namespace')"
    remaps = [(_src(e.elts[0]), _src(e.elts[1])) for e in kw["remappings"].elts]
    assert remaps == [("names.IMAGE_TOPIC", "LaunchConfiguration('image_topic')"),
                      ("names.CAMERA_INFO_TOPIC", "LaunchConfiguration('camera_info_topic')")]
    assert _src(kw["parameters"]) == "[node_params_file(params_file)]"
    # the executable is the console script that runs the node
    module = _load_module()
    setup_py = (REPO / "setup.py").read_text(encoding="utf-8")
    assert f'"{module.EXECUTABLE} = sfm_ttr_ros.ros.node:main"' in setup_py


def test_the_node_subscribes_to_the_names_the_launch_file_remaps():
    used = set()
    for module in ("node.py", "subscriptions.py"):  # the node and its inputs
        tree = ast.parse((REPO / "sfm_ttr_ros" / "ros" / module).read_text(encoding="utf-8"))
        used |= {_src(n) for n in ast.walk(tree) if isinstance(n, ast.Attribute)
                 and isinstance(n.value, ast.Name) and n.value.id == "names"}
    assert {"names.IMAGE_TOPIC", "names.CAMERA_INFO_TOPIC", "names.NODE_NAME"} <= used


def test_params_file_is_checked_and_rekeyed_for_any_namespace(tmp_path):
    module = _load_module()
    out = Path(module.node_params_file(str(REPO / "params" / "kitti.yaml")))
    try:
        doc = yaml.safe_load(out.read_text())
    finally:
        out.unlink()
    assert list(doc) == ["/**"]
    params = doc["/**"]["ros__parameters"]
    src = yaml.safe_load((REPO / "params" / "kitti.yaml").read_text())
    assert params["window_size"] == src[names.NODE_NAME]["ros__parameters"]["window_size"]
    bad = tmp_path / "bad.yaml"
    bad.write_text(f"{names.NODE_NAME}:\n  ros__parameters:\n    no_such_param: 1\n")
    with pytest.raises(InputError, match="no_such_param"):
        module.node_params_file(str(bad))


@pytest.mark.ros
def test_a_namespaced_node_gets_the_file_values(monkeypatch):
    rclpy = pytest.importorskip("rclpy")
    from rclpy.context import Context

    from sfm_ttr_ros.ros import params as node_params

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("ROS_DOMAIN_ID", str(random.SystemRandom().randint(1, 100)))
    module = _load_module()
    path = module.node_params_file(str(REPO / "params" / "kitti.yaml"))
    expected = yaml.safe_load(Path(path).read_text())["/**"]["ros__parameters"]
    ctx = Context()
    rclpy.init(context=ctx, args=["--ros-args", "--params-file", path, "-r", "__ns:=/robot1"])
    try:
        node = rclpy.create_node(names.NODE_NAME, context=ctx)
        node_params.declare(node)
        assert node.get_fully_qualified_name() == "/robot1/refiner"
        got = node_params.current_values(node)
        assert {k: got[k] for k in expected} == expected
        node.destroy_node()
    finally:
        ctx.try_shutdown()
        os.unlink(path)
