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
    assert {p.name for p in FILES} >= {"refiner.yaml", "kitti.yaml"}


def test_the_defaults_file_lists_every_parameter_with_its_default():
    params = parameter_dict_from_yaml_file(str(REPO / "params" / "refiner.yaml"),
                                           target_nodes=["refiner"])
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
    params = parameter_dict_from_yaml_file(str(path), target_nodes=["refiner"])
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
        params = parameter_dict_from_yaml_file(str(path), target_nodes=["refiner"])
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
