"""launch/refiner.launch.py without the `launch` packages (not installable from PyPI): it
compiles, its Node action and arguments match sfm_ttr_ros.ros.names and the node (read from the
AST), a shared parameter file is checked as docs/node.md "Launch" says, and the arguments it
hands the node give a namespaced node its parameters, sim time and remaps (rclpy)."""

from __future__ import annotations

import ast
import importlib.util
import random
from pathlib import Path

import pytest
import yaml

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.ros import launch_params, names

REPO = Path(__file__).resolve().parents[1]
LAUNCH = REPO / "launch" / "refiner.launch.py"


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


def _shared_file(tmp_path: Path, own: dict | None = None) -> Path:
    """A parameter file shared by several nodes: ``/**`` for all (sim time, a QoS override,
    another driver's key, one of ours), a section for another node, and ours."""
    doc = {
        "/**": {"ros__parameters": {
            "use_sim_time": False, "window_size": 7, "frame_rate": 30,
            "qos_overrides": {"/cam1/camera/image_raw": {
                "subscription": {"reliability": "reliable"}}}}},
        "/cam1/camera_driver": {"ros__parameters": {"exposure_us": 800}},
        "/cam1/refiner": {"ros__parameters": {"window_stride": 3, **(own or {})}},
    }
    path = tmp_path / "shared.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def test_it_compiles():
    compile(LAUNCH.read_text(encoding="utf-8"), str(LAUNCH), "exec")
    names_in_module = {n.name for n in _tree().body if isinstance(n, ast.FunctionDef)}
    assert "generate_launch_description" in names_in_module


def test_every_input_and_output_topic_has_a_remap_argument():
    module = _load_module()
    topics = {v for k, v in vars(names).items() if k.endswith("_TOPIC") and isinstance(v, str)
              and not v.startswith("/")}  # /diagnostics is global by convention
    assert set(launch_params.REMAPS.values()) == topics
    assert {names.ODOMETRY_TOPIC, names.DEPTH_TOPIC, names.POINTS_TOPIC} <= topics
    assert set(module.ARGUMENTS) == {"params_file", "namespace", "use_sim_time",
                                     *launch_params.REMAPS}
    (declare,) = _call(_tree(), "DeclareLaunchArgument")  # one call, over ARGUMENTS
    assert _src(declare.args[0]) == "name"
    (config,) = _call(_tree(), "LaunchConfiguration")  # every argument read, by name
    assert _src(config.args[0]) == "name"


def test_the_node_action_matches_names_and_writes_no_file():
    (node,) = _call(_tree(), "Node")
    kw = {k.arg: _src(k.value) for k in node.keywords}
    assert kw["package"] == "names.PACKAGE" and names.PACKAGE == "sfm_ttr_ros"
    assert kw["name"] == "names.NODE_NAME"
    assert kw["namespace"] == "given['namespace']"
    assert kw["remappings"] == "launch_params.remappings(given)"
    assert kw["ros_arguments"] == ("launch_params.parameter_arguments(values, "
                                   "given['use_sim_time'])")
    assert "parameters" not in kw  # a dict there makes launch_ros write a file it keeps
    # the file is read for the node's full name, as rcl would apply it: in its namespace
    (read,) = _call(_tree(), "launch_params.node_parameters") or [
        n for n in ast.walk(_tree()) if isinstance(n, ast.Call)
        and _src(n.func) == "launch_params.node_parameters"]
    assert {k.arg: _src(k.value) for k in read.keywords} == {"namespace": "given['namespace']"}
    for source in (LAUNCH, REPO / "sfm_ttr_ros" / "ros" / "launch_params.py"):
        assert "tempfile" not in source.read_text(encoding="utf-8")
    module = _load_module()
    setup_py = (REPO / "setup.py").read_text(encoding="utf-8")
    assert f'"{module.EXECUTABLE} = sfm_ttr_ros.ros.node:main"' in setup_py


def test_the_default_parameter_file_is_the_generic_one():
    (func,) = [n for n in _tree().body if isinstance(n, ast.FunctionDef)
               and n.name == "default_params_file"]
    literals = {n.value for n in ast.walk(func) if isinstance(n, ast.Constant)}
    assert "refiner.yaml" in literals and "kitti.yaml" not in literals
    values = launch_params.node_parameters(REPO / "params" / "refiner.yaml")
    assert values["metric.source"] == "none" and values["fallback_intrinsics"] == ""


def test_a_shared_file_passes_ros_keys_and_other_nodes_keys(tmp_path):
    values = launch_params.node_parameters(_shared_file(tmp_path), namespace="cam1")
    assert values == {
        "use_sim_time": False, "window_size": 7,
        "qos_overrides./cam1/camera/image_raw.subscription.reliability": "reliable",
        "window_stride": 3}  # frame_rate (/**) and exposure_us (another node) left to others


@pytest.mark.parametrize("own, match", [
    ({"no_such_param": 1}, "'no_such_param' is not a parameter of the refiner node"),
    ({"window_size": 1.5}, "window_size"),
    ({"window_size": -3}, "window_size"),
])
def test_the_nodes_own_bad_keys_stop_the_launch_with_the_key_named(tmp_path, own, match):
    with pytest.raises(InputError, match=match):
        launch_params.node_parameters(_shared_file(tmp_path, own), namespace="/cam1")


def test_a_bad_value_of_ours_in_a_wildcard_section_is_refused(tmp_path):
    path = tmp_path / "wild.yaml"
    path.write_text("/**:\n  ros__parameters:\n    window_stride: abc\n")
    with pytest.raises(InputError, match="window_stride"):
        launch_params.node_parameters(path)
    path.write_text("/other_node:\n  ros__parameters:\n    gain: 1\n")
    with pytest.raises(InputError, match="no section applies to node /refiner"):
        launch_params.node_parameters(path)


def test_each_namespace_gets_its_own_section_and_a_stray_one_stops_the_launch(tmp_path):
    """One file for /cam1/refiner and /cam2/refiner: each launch (``namespace:=cam1``,
    ``namespace:=cam2``) hands its node its own section over the shared ``/**``, never the
    other camera's; a namespace the file does not name stops the launch, the sections named
    (rcl would start that node at the defaults)."""
    path = tmp_path / "cameras.yaml"
    path.write_text(yaml.safe_dump({
        "/**": {"ros__parameters": {"refinement.steps": 40, "frame_rate": 30}},
        "/cam1/refiner": {"ros__parameters": {"window_size": 6, "window_stride": 6}},
        "/cam2/refiner": {"ros__parameters": {"window_size": 8, "window_stride": 4}},
        "/cam2/camera_driver": {"ros__parameters": {"exposure_us": 800}},
    }, sort_keys=False))
    assert launch_params.node_parameters(path, namespace="cam1") == {
        "refinement.steps": 40, "window_size": 6, "window_stride": 6}
    assert launch_params.node_parameters(path, namespace="/cam2") == {
        "refinement.steps": 40, "window_size": 8, "window_stride": 4}
    path.write_text(yaml.safe_dump({k: v for k, v in yaml.safe_load(path.read_text()).items()
                                    if k != "/**"}, sort_keys=False))
    with pytest.raises(InputError, match=r"no section applies to node /cam3/refiner \(its "
                       r"sections: /cam1/refiner, /cam2/refiner, /cam2/camera_driver\)"):
        launch_params.node_parameters(path, namespace="cam3")


def test_arguments_become_parameters_and_remaps():
    args = launch_params.parameter_arguments({"window_size": 7, "sfm.features": "colmap",
                                              "refinement.lr": 1e-05}, "True")
    assert args == ["-p", "window_size:=7", "-p", 'sfm.features:="colmap"',
                    "-p", "refinement.lr:=1.0e-05", "-p", "use_sim_time:=true"]
    assert launch_params.parameter_arguments({}, "") == []
    with pytest.raises(InputError, match="use_sim_time"):
        launch_params.parameter_arguments({}, "yes")
    assert launch_params.remappings({"image_topic": "", "odom_topic": " "}) == []
    assert launch_params.remappings({"image_topic": "/cam/image_raw",
                                     "depth_topic": "depth"}) == [
        (names.IMAGE_TOPIC, "/cam/image_raw"), (names.DEPTH_TOPIC, "depth")]


@pytest.mark.ros
def test_namespace_sim_time_and_a_shared_file_reach_the_node(monkeypatch, tmp_path):
    """What `refiner.launch.py use_sim_time:=true namespace:=cam1 params_file:=<shared>
    image_topic:=... depth_topic:=...` starts: the node's command line, given to rclpy."""
    rclpy = pytest.importorskip("rclpy")
    from rclpy.context import Context
    from rclpy.qos import ReliabilityPolicy
    from sensor_msgs.msg import Image

    from sfm_ttr_ros.core.params.node import NodeSettings
    from sfm_ttr_ros.ros import params as node_params
    from sfm_ttr_ros.ros import subscriptions

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("ROS_DOMAIN_ID", str(random.SystemRandom().randint(1, 100)))
    values = launch_params.node_parameters(_shared_file(tmp_path), namespace="cam1")
    given = {"image_topic": "/cam1/camera/image_raw", "depth_topic": "/cam1/depth",
             "points_topic": "sparse_points"}
    remaps = [a for src, dst in launch_params.remappings(given) for a in ("-r", f"{src}:={dst}")]
    ctx = Context()
    rclpy.init(context=ctx, args=["--ros-args", "-r", "__ns:=/cam1", *remaps,
                                  *launch_params.parameter_arguments(values, "true")])
    try:
        node = rclpy.create_node(names.NODE_NAME, context=ctx)
        node_params.declare(node)
        assert node.get_fully_qualified_name() == "/cam1/refiner"
        assert node.get_parameter("use_sim_time").value is True  # the argument beats the file
        got = node_params.current_values(node)
        assert (got["window_size"], got["window_stride"]) == (7, 3)
        assert node.resolve_topic_name(names.IMAGE_TOPIC) == "/cam1/camera/image_raw"
        assert node.resolve_topic_name(names.CAMERA_INFO_TOPIC) == "/cam1/camera_info"
        assert node.resolve_topic_name(names.DEPTH_TOPIC) == "/cam1/depth"
        assert node.resolve_topic_name(names.POINTS_TOPIC) == "/cam1/sparse_points"
        assert node.resolve_topic_name(names.CLOUD_TOPIC) == "/cam1/refiner/cloud"
        # the file's qos_overrides (named after the remapped topic) reach the subscription
        sub_input = subscriptions.Input(Image, names.IMAGE_TOPIC, lambda m: None)
        subscriptions.subscribe(node, [sub_input],
                                subscriptions.input_qos(NodeSettings(
                                    qos_reliability="best_effort")), lambda *a: None)
        (sub,) = [s for s in node.subscriptions if s.topic_name == "/cam1/camera/image_raw"]
        assert sub.qos_profile.reliability == ReliabilityPolicy.RELIABLE
        node.destroy_node()
    finally:
        ctx.try_shutdown()


def _replay(bag: Path, ros_args: list[str], clock: bool) -> tuple[dict[int, object], dict]:
    """Start the node as the launch file would (``ros_args``), play ``bag`` into it (with
    ``/clock`` when ``clock``); its windowed depth per frame stamp (ns), and its accounting."""
    import threading
    import time

    import numpy as np
    from conftest import tiny_model
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    from msg_adapters.image import image_to_depth
    from msg_adapters.stamp import stamp_to_ns
    from sfm_ttr_ros.ros.kitti_bag import CAMERA_INFO_TOPIC, IMAGE_TOPIC
    from sfm_ttr_ros.ros.node import RefinerNode
    from sfm_ttr_ros.ros.player import play_bag

    rclpy = pytest.importorskip("rclpy")
    ctx = Context()
    rclpy.init(context=ctx, args=["--ros-args", *ros_args])
    depths: dict[int, np.ndarray] = {}
    try:
        refiner = RefinerNode(model=tiny_model(), context=ctx)
        listener = rclpy.create_node("listener", context=ctx)
        # the refined depth, in metres or (not metric: the network's units) on its relative twin
        for topic in ("/cam1/depth_out",
                      refiner.resolve_topic_name(names.DEPTH_REFINED_RELATIVE_TOPIC)):
            listener.create_subscription(
                Image, topic,
                lambda m: depths.__setitem__(stamp_to_ns(m.header.stamp), image_to_depth(m)),
                QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE))
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(refiner)
        executor.add_node(listener)
        threading.Thread(target=executor.spin, daemon=True).start()
        played = play_bag(bag, rate=1.0, clock=clock, progress=False,
                          topics=[IMAGE_TOPIC, CAMERA_INFO_TOPIC],
                          wait_topics=[IMAGE_TOPIC, CAMERA_INFO_TOPIC])
        n = played.published[IMAGE_TOPIC]
        deadline = time.monotonic() + 240
        while len(depths) < n and time.monotonic() < deadline:
            time.sleep(0.1)
        assert refiner.get_parameter("use_sim_time").value is clock
        assert len(depths) == n, f"{len(depths)} of {n} frames came back"
        values = refiner.diagnostics_values()
        counts = {k: values[k] for k in ("frames_received", "frames_refined", "frames_unrefined",
                                         "frames_dropped", "windows_ok", "windows_failed")}
        executor.shutdown()
        refiner.destroy_node()
        listener.destroy_node()
    finally:
        ctx.try_shutdown()
    return depths, counts


@pytest.mark.slow
@pytest.mark.ros
def test_the_launched_node_replays_a_bag_in_sim_time_to_the_same_depth(monkeypatch, tmp_path):
    """`refiner.launch.py namespace:=cam1 use_sim_time:=true params_file:=<shared /** file>`
    with the inputs remapped to a KITTI bag played with /clock: every frame comes back on the
    remapped output with the depth of the same node on wall time."""
    pytest.importorskip("rclpy")
    import numpy as np

    from sfm_ttr_ros.data.kitti import write_kitti_drive
    from sfm_ttr_ros.data.synthetic import make_sequence
    from sfm_ttr_ros.ros.kitti_bag import CAMERA_INFO_TOPIC, IMAGE_TOPIC, kitti_to_bag

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("ROS_DOMAIN_ID", str(random.SystemRandom().randint(1, 100)))
    seq = make_sequence(seed=0, domain="A", num_frames=8, width=160, height=48)
    name = write_kitti_drive(seq, tmp_path / "raw", tmp_path / "gt", gt_skip_ends=2)
    bag = kitti_to_bag(tmp_path / "raw", name, tmp_path / "bag", tmp_path / "gt",
                       storage="mcap").path
    shared = tmp_path / "robot.yaml"
    shared.write_text(yaml.safe_dump({
        "/**": {"ros__parameters": {
            "use_sim_time": False, "window_size": 4, "window_stride": 2, "keyframe_policy": "all",
            "republish_unrefined": True, "refinement.steps": 5, "min_supervision_points": 20,
            "sfm.max_num_features": 2048, "torch_num_threads": 1,
            # the stand-in network's encoder has no stages to hold fixed; 160x48 frames: the
            # paper's SfM (each window mapped alone, SIFT from the upsampled octave)
            "refinement.frozen_encoder_levels": 0, "sfm.mode": "batch", "sfm.first_octave": -1}},
        "/cam1/lidar": {"ros__parameters": {"range_max": 80.0}}}))
    remaps = launch_params.remappings({"image_topic": IMAGE_TOPIC,
                                       "camera_info_topic": CAMERA_INFO_TOPIC,
                                       "depth_refined_topic": "depth_out"})
    values = launch_params.node_parameters(shared)

    def args(sim: str) -> list[str]:
        return ["-r", "__ns:=/cam1", *(a for src, dst in remaps for a in ("-r", f"{src}:={dst}")),
                *launch_params.parameter_arguments(values, sim)]

    sim, sim_counts = _replay(bag, args("true"), clock=True)
    wall, wall_counts = _replay(bag, args(""), clock=False)  # as the file says: false
    assert sorted(sim) == sorted(wall) and len(sim) == 8
    assert sim_counts == wall_counts and sim_counts["windows_ok"] >= 1, (sim_counts, wall_counts)
    # two runs on wall time differ by up to 0.09 % (measured): the refinement is not bitwise
    # reproducible across runs
    for stamp, depth in wall.items():
        assert np.allclose(sim[stamp], depth, rtol=5e-3, equal_nan=True), stamp
