"""The shipped parameter files against the node's ROS declaration: every key is a declared
parameter with the declared type and within its range, and the node starts with them (checked
in-process); the descriptors come from the rows of the one schema (sfm_ttr_ros.core.params,
whose own checks of the same files are in test_params_schema.py)."""

from __future__ import annotations

import os
import random

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("ROS_DOMAIN_ID", str(random.SystemRandom().randint(1, 100)))

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

rclpy = pytest.importorskip("rclpy")

import yaml  # noqa: E402
from rcl_interfaces.msg import ParameterType  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from sfm_ttr_ros.core import params as schema  # noqa: E402
from sfm_ttr_ros.ros import params as node_params  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SECTION = "/**"  # the shipped files' one section
FILES = sorted((REPO / "params").glob("*.yaml"))
pytestmark = pytest.mark.ros


def parameter_dict_from_yaml_file(path: str, target_nodes: list[str]) -> dict:
    """The file's parameters as rcl reads ``--params-file``: YAML types kept as they are.

    (rclpy's own ``parameter_dict_from_yaml_file`` turns every value into a string and guesses
    its type back, so a double below 1e-4 - ``3e-05`` once printed - comes back as a string;
    the node, which reads the file through rcl's C parser, gets the double.)"""
    data = yaml.safe_load(Path(path).read_text())
    out = {}
    for node in target_nodes:
        for name, value in data[node]["ros__parameters"].items():
            out[name] = Parameter(name, value=value).to_parameter_msg()
    return out


def test_both_files_are_shipped():
    assert {p.name for p in FILES} >= {"refiner.yaml", "kitti.yaml", "paper.yaml"}


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
def test_shipped_files_apply_in_any_namespace(path: Path):
    """One ``/**`` section: rcl applies it to the node under any ``__ns`` (a ``refiner:``
    section is ``/refiner``'s only)."""
    assert list(yaml.safe_load(path.read_text())) == [SECTION]


def test_the_defaults_file_lists_every_parameter_with_its_default():
    params = parameter_dict_from_yaml_file(str(REPO / "params" / "refiner.yaml"),
                                           target_nodes=[SECTION])
    values = {k: Parameter.from_parameter_msg(m).value for k, m in params.items()}
    assert values == node_params.DEFAULTS


@pytest.mark.parametrize("path", [f for f in FILES if f.name != "refiner.yaml"],
                         ids=lambda p: p.name)
def test_a_profile_lists_only_what_differs_from_the_defaults(path: Path):
    """A profile says what it changes and nothing else: a key at its default would be noise
    that goes stale when the default moves."""
    values = schema.read_params_file(path, "refiner")
    defaults = schema.defaults()
    same = sorted(k for k, v in values.items() if k in defaults and v == defaults[k])
    assert not same, f"{path.name}: at their defaults: {same}"
    assert not set(values) - set(defaults), f"{path.name}: legacy names in a shipped file"


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
def test_every_key_is_declared_typed_and_in_range(path: Path, context):
    params = parameter_dict_from_yaml_file(str(path), target_nodes=[SECTION])
    assert params, f"{path.name}: no parameters for node 'refiner'"
    unknown = sorted(set(params) - set(node_params.SPECS))
    assert not unknown, f"{path.name}: undeclared parameters {unknown}"
    for name, msg in params.items():
        spec = node_params.SPECS[name]
        if not spec.dynamic_typing:
            assert msg.value.type == node_params.ros_type(spec), (
                f"{path.name}: {name} is {ParameterType.__name__} {msg.value.type}, declared "
                f"{node_params.ros_type(spec)} (write doubles as 1.0, not 1)")
    # declare on a real node with the file's values as overrides: rclpy checks type and range
    overrides = [Parameter.from_parameter_msg(m) for m in params.values()]
    node = Node("refiner", context=context, parameter_overrides=overrides)
    try:
        node_params.declare(node)
        values = node_params.current_values(node)
    finally:
        node.destroy_node()
    for name, msg in params.items():
        assert values[name] == Parameter.from_parameter_msg(msg).value
    assert node_params.validate(values) == ""
    # the schema reads the file as rcl does
    assert schema.read_params_file(path, "refiner") == {
        k: Parameter.from_parameter_msg(m).value for k, m in params.items()}


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
def test_the_node_starts_with_the_file(path: Path, context):
    pytest.importorskip("torch")
    from sfm_ttr_ros.core.models.mobilenet import MobileDepthNet
    from sfm_ttr_ros.ros.node import RefinerNode

    # a small default-architecture network: kitti.yaml's frozen_encoder_levels needs its stages
    model = MobileDepthNet(input_size=(64, 96))
    node = RefinerNode(model=model, context=context,
                       cli_args=["--ros-args", "--params-file", str(path)])
    try:
        params = parameter_dict_from_yaml_file(str(path), target_nodes=[SECTION])
        for name, msg in params.items():
            assert node.get_parameter(name).value == Parameter.from_parameter_msg(msg).value
    finally:
        node.destroy_node()


def test_a_double_written_as_an_integer_stops_the_start_up(tmp_path: Path, context):
    bad = tmp_path / "bad.yaml"
    bad.write_text("refiner:\n  ros__parameters:\n    refinement.lr: 1\n")
    overrides = [Parameter.from_parameter_msg(m) for m in
                 parameter_dict_from_yaml_file(str(bad), target_nodes=["refiner"]).values()]
    node = Node("refiner", context=context, parameter_overrides=overrides)
    try:
        with pytest.raises(rclpy.exceptions.InvalidParameterTypeException):
            node_params.declare(node)
    finally:
        node.destroy_node()


def test_every_descriptor_is_complete_and_from_the_schema():
    assert node_params.PARAMS is schema.PARAMS and node_params.DEFAULTS == schema.defaults()
    types = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
             float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING}
    for spec in node_params.PARAMS:
        d = node_params.descriptor(spec)
        assert d.name == spec.name and d.description == spec.description
        assert d.read_only == (not spec.live) and d.dynamic_typing == spec.dynamic_typing
        if spec.dynamic_typing:
            assert d.type == ParameterType.PARAMETER_NOT_SET
        else:
            assert d.type == types[spec.type], spec.name
        if d.type in (ParameterType.PARAMETER_INTEGER, ParameterType.PARAMETER_DOUBLE):
            assert d.integer_range or d.floating_point_range, f"{spec.name} has no range"
            r = (d.integer_range or d.floating_point_range)[0]
            assert (r.from_value, r.to_value) == spec.range
        if spec.choices:
            assert d.additional_constraints.startswith(
                "one of: " + ", ".join(map(str, spec.choices)))
    ro = {s.name for s in node_params.PARAMS if not s.live}
    assert {"model_type", "device", "qos_reliability", "qos_depth", "max_pending"} <= ro
    assert not ro & {"refinement.steps", "window_size", "refinement.lr"}


TWO_CAMERAS = """\
/**:
  ros__parameters:
    refinement.steps: 40
/cam1/refiner:
  ros__parameters:
    window_size: 6
    window_stride: 6
/cam2/refiner:
  ros__parameters:
    window_size: 8
    window_stride: 4
"""


def test_two_namespaces_take_their_own_sections_through_rcl(tmp_path: Path, context, capfd):
    """Two refiners in /cam1 and /cam2 started as a user does (``-r __ns:=...
    --params-file``): rcl gives each its own section, the shared ``/**`` section both, and the
    launch's reader agrees; a file with only ``refiner:`` under a namespace applies nothing and
    the node says so."""
    pytest.importorskip("torch")
    from sfm_ttr_ros.core.models.mobilenet import MobileDepthNet
    from sfm_ttr_ros.ros.launch_params import node_parameters
    from sfm_ttr_ros.ros.node import RefinerNode

    shared = tmp_path / "cameras.yaml"
    shared.write_text(TWO_CAMERAS)
    bare = tmp_path / "bare.yaml"
    bare.write_text("refiner:\n  ros__parameters:\n    window_size: 9\n")
    want = {"/cam1": (6, 6, 40), "/cam2": (8, 4, 40)}
    for ns, (size, stride, steps) in want.items():
        node = RefinerNode(model=MobileDepthNet(input_size=(64, 96)), context=context,
                           cli_args=["--ros-args", "-r", f"__ns:={ns}", "--params-file",
                                     str(shared), "--params-file", str(bare)])
        try:
            assert node.get_fully_qualified_name() == f"{ns}/refiner"
            got = tuple(node.get_parameter(n).value
                        for n in ("window_size", "window_stride", "refinement.steps"))
            assert got == (size, stride, steps)
        finally:
            node.destroy_node()
        assert node_parameters(shared, namespace=ns) == {
            "refinement.steps": steps, "window_size": size, "window_stride": stride}
        err = capfd.readouterr().err
        assert f"{bare}: no section applies to node {ns}/refiner" in err
        assert f"{shared}: no section" not in err


def test_the_section_table_is_what_rcl_applies(tmp_path: Path, context):
    """test_params_schema.py's table of sections against node names, asked of rcl itself."""
    from test_params_schema import RCL_MATCHES

    f = tmp_path / "one.yaml"
    for section, fqn, applies in RCL_MATCHES:
        f.write_text(f"{section}:\n  ros__parameters:\n    probe: 1\n")
        ns, _, name = fqn.rpartition("/")
        node = Node(name, namespace=ns or "/", context=context,
                    cli_args=["--ros-args", "--params-file", str(f)],
                    automatically_declare_parameters_from_overrides=True)
        try:
            assert node.has_parameter("probe") is applies, (section, fqn)
        finally:
            node.destroy_node()
