"""The one parameter schema (sfm_ttr_ros.core.params): defaults written once (in the config
dataclasses), every row reaching its config field, ``--set`` typing and errors, parameter
files, the precedence of the command line, and the generated docs/parameters.md. ROS-free."""

from __future__ import annotations

import copy
import dataclasses
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from sfm_ttr_ros.core import params as schema
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.params import SECTIONS, Settings

REPO = Path(__file__).resolve().parents[1]
PARAM_FILES = sorted((REPO / "params").glob("*.yaml"))


def _section(settings: Settings, section: str):
    return {"sfm": settings.ttr.sfm, "alignment": settings.ttr.alignment,
            "refinement": settings.ttr.refinement, "ttr": settings.ttr,
            "check": settings.ttr.check, "metric": settings.ttr.metric,
            "stream": settings.stream, "model": settings.model,
            "node": settings.node}[section]


def test_every_default_is_the_dataclass_field_default():
    for p in schema.PARAMS:
        for target in p.targets:
            section, _, name = target.partition(".")
            value = getattr(SECTIONS[section](), name)  # a fresh config
            if p.name == "window_stride":  # 0 stands for window_size: resolved in the config
                assert p.default == 0 and value == SECTIONS[section]().window_size
                continue
            assert value == p.default and type(value) is p.type, (p.name, target, value)
    assert schema.defaults()["idle_flush_s"] == 2.0  # the node's value, now the stream's too
    assert schema.defaults()["torch_num_threads"] == 0  # torch's default


def _other_value(p: schema.Param):
    """A valid value of ``p`` that is not its default."""
    special = {"model_type": "mobilenet", "device": "auto", "camera_info_use_projection": True,
               "check.unsupported_change_ratio": 1.5, "first_window_size": 4,
               "fallback_intrinsics": "700 700 300 200", "outputs": "depth,points",
               "odom.frame_id": "map", "odom.child_frame_id": "camera_optical_frame",
               "odom.camera_mount": "0.5 0 1.2 -90 5 -90", "window_stride": 5}
    if p.name in special:
        return special[p.name]
    if p.choices:
        return next(c for c in p.choices if c != p.default)
    if p.type is bool:
        return not p.default
    if p.type is str:
        return "/tmp/some/file.pth"
    lo, hi = p.range
    step = 1 if p.type is int else 0.25 * min(1.0, hi - lo)
    return p.default + step if p.default + step <= hi else p.default - step


def test_every_row_reaches_its_config_fields():
    companions = {"encoder_path": "decoder_path", "decoder_path": "encoder_path"}
    for p in schema.PARAMS:
        value = _other_value(p)
        values = {p.name: value}
        if p.name in companions:
            values[companions[p.name]] = value
        if p.name == "window_stride":  # a stride above the default window needs a wider one
            values["window_size"] = value
        if p.name == "sfm.features":  # torch features: batch SfM only (the default streams)
            values["sfm.mode"] = "batch"
        settings = schema.build(values)
        for target in p.targets:
            section, _, name = target.partition(".")
            assert getattr(_section(settings, section), name) == value, (p.name, target)
    # a settable field no parameter targets (experiments: --set ttr.predict_batch=3)
    assert schema.build({"ttr.predict_batch": 3}).ttr.predict_batch == 3


def test_set_values_are_typed_by_the_schema():
    values = schema.parse_overrides([
        "refinement.lr=3e-5", "refinement.steps=40", "fx=700", "fy=700.5", "sfm.min_tri_angle=1",
        "fallback_intrinsics=700 700.5 0 0",
        "model.channels_last=true", "encoder_path=", "decoder_path=", "model_type=python:a.b:f",
        "camera_info_use_projection=false", "refinement.bn_mode='train'", "seed=3", "seed=4"])
    assert values == {
        "refinement.lr": 3e-5, "refinement.steps": 40, "fx": 700.0, "fy": 700.5,
        "fallback_intrinsics": "700 700.5 0 0",
        "sfm.min_tri_angle": 1.0, "channels_last": True, "encoder_path": "",
        "decoder_path": "", "model_type": "python:a.b:f", "camera_info_use_projection": False,
        "refinement.bn_mode": "train", "seed": 4}
    for name in ("refinement.lr", "fx", "sfm.min_tri_angle"):
        assert type(values[name]) is float, name
    assert schema.parse_overrides(["camera_info_use_projection=auto"]) == {
        "camera_info_use_projection": "auto"}
    s = schema.build(values)
    assert s.ttr.refinement.lr == 3e-5 and s.ttr.sfm.min_tri_angle == 1.0
    assert (s.ttr.sfm.seed, s.ttr.alignment.seed, s.ttr.refinement.seed) == (4, 4, 4)
    assert s.model.channels_last and s.node.use_projection is False
    assert s.node.fallback == (700.0, 700.5, 0.0, 0.0)
    assert any("'fx' is deprecated" in w for w in s.warnings)  # a legacy name, translated


@pytest.mark.parametrize("item, match", [
    ("nonsense=1", "unknown parameter 'nonsense'"),
    ("refinement.stepz=3", r"did you mean refinement\.steps"),
    ("sfm.no_such_field=1", "unknown parameter"),
    ("ttr.sfm=1", "unknown parameter"),  # a nested config is not a value
    ("steps", "expected NAME=VALUE"),
    ("=3", "expected NAME=VALUE"),
    ("refinement.steps=1.5", "refinement.steps must be an integer"),
    ("refinement.steps=-1", "refinement.steps must be >= 0"),
    ("refinement.lr=2.0", "refinement.lr must be <= 1"),
    ("keyframe_policy=sideways", "must be one of newest, all"),
    ("weight_policy=maybe", "must be one of"),
    ("window_size=true", "must be an integer"),
    ("fx=abc", "fx must be a double"),  # a legacy name keeps its old type
    ("check.holdout_fraction=0.2", None),  # removed: accepted by --set, refused by build
])
def test_set_errors_name_the_problem(item, match):
    if match is None:
        with pytest.raises(InputError, match="was removed"):
            schema.build(schema.parse_overrides([item]))
        return
    with pytest.raises(InputError, match=match):
        schema.parse_overrides([item])


def test_check_value_is_strict_like_rclpy():
    assert schema.check_value("refinement.lr", 1e-3) == ""
    assert "write doubles as 1.0" in schema.check_value("refinement.lr", 1)
    assert "an integer" in schema.check_value("window_size", True)
    assert "an integer" in schema.check_value("window_size", 4.0)
    assert "one of" in schema.check_value("refinement.loss", "huber")
    assert schema.check_value("camera_info_use_projection", True) == ""
    assert "unknown parameter" in schema.check_value("no_such", 1)


@pytest.mark.parametrize("values, match", [
    ({"window_size": 3, "window_stride": 4}, "window_stride"),
    ({"fallback_intrinsics": "500 0 1 1"}, "fx and fy must be > 0"),
    ({"fallback_intrinsics": "500 500"}, "four numbers"),
    ({"outputs": "depth,cloudz"}, "unknown output"),
    ({"cloud.stride": 0}, "cloud.stride"),
    ({"cloud.max_range": -0.5}, "cloud.max_range"),
    ({"encoder_path": "e.pth"}, "both encoder_path and decoder_path"),
    ({"model_type": "resnet"}, "model_type must be"),
    ({"camera_info_use_projection": "sometimes"}, "camera_info_use_projection"),
    ({"refinement.lr": 0.0}, "lr must be a positive number"),
    ({"alignment.tau": 0.0}, "tau"),
    ({"no_such": 1}, "unknown parameter"),
])
def test_validate_checks_the_whole_set(values, match):
    reason = schema.validate(values)
    assert match in reason
    with pytest.raises(InputError, match=match):
        schema.build(values)
    assert schema.validate({}) == "" and schema.validate(schema.defaults()) == ""


@pytest.mark.parametrize("path", PARAM_FILES, ids=lambda p: p.name)
def test_shipped_parameter_files_pass_the_schema(path):
    values = schema.read_params_file(path, "refiner")
    assert values and schema.validate(values) == ""
    if path.name == "refiner.yaml":  # it lists every parameter at its default
        assert values == schema.defaults()


def test_params_file_is_read_and_checked_like_the_node(tmp_path):
    def write(body: str) -> Path:
        p = tmp_path / "p.yaml"
        p.write_text(textwrap.dedent(body))
        return p

    nested = write("""
        /**:
          ros__parameters:
            window_size: 6
            window_stride: 2
        /robot/refiner:
          ros__parameters:
            window_stride: 3
            refinement: {steps: 7}
        other:
          ros__parameters:
            window_size: 99
    """)
    assert schema.read_params_file(nested, "refiner", namespace="robot") == {
        "window_size": 6, "window_stride": 3, "refinement.steps": 7}
    assert schema.read_params_file(nested, "refiner") == {"window_size": 6, "window_stride": 2}
    for body, msg in (
        ("refiner:\n  ros__parameters:\n    refinement.lr: 1\n", "write doubles"),
        ("refiner:\n  ros__parameters:\n    refinement.stepz: 1\n",
         r"not a parameter of the refiner node \(did you mean refinement\.steps"),
        ("refiner:\n  ros__parameters:\n    ttr.predict_batch: 1\n", "not a parameter"),
        ("refiner:\n  ros__parameters:\n    window_size: 1\n", "window_size must be >= 2"),
        ("refiner:\n  ros__parameters:\n    keyframe_policy: x\n", "one of"),
        ("refiner:\n  ros__parameters: [1, 2]\n", "not a mapping"),
        ("other_node:\n  ros__parameters:\n    window_size: 4\n",
         r"no section applies to node /refiner \(its sections: /other_node\)"),
        ("- a list\n", "expected a mapping"),
        ("refiner: {ros__parameters: {window_size: [}\n", "cannot read"),
    ):
        with pytest.raises(InputError, match=msg):
            schema.read_params_file(write(body), "refiner")
    with pytest.raises(InputError, match="not found"):
        schema.read_params_file(tmp_path / "missing.yaml", "refiner")


# (section, the node's full name, whether rcl applies the section: measured with rclpy's own
# --params-file; test_params_files.py checks a few against a live rcl)
RCL_MATCHES = [
    ("/**", "/refiner", True), ("/**", "/cam1/refiner", True), ("/**", "/a/b/refiner", True),
    ("/*", "/refiner", True), ("/*", "/cam1/refiner", False),
    ("/**/refiner", "/refiner", True), ("/**/refiner", "/cam1/refiner", True),
    ("/**/refiner", "/a/b/refiner", True), ("/**/refiner", "/cam1/other", False),
    ("/cam1/*", "/refiner", False), ("/cam1/*", "/cam1/refiner", True),
    ("/cam1/*", "/cam1/a/refiner", False), ("/cam1/**", "/cam1/a/refiner", True),
    ("refiner", "/refiner", True), ("refiner", "/cam1/refiner", False),
    ("/refiner", "/refiner", True), ("/refiner", "/cam1/refiner", False),
    ("/cam1/refiner", "/cam1/refiner", True), ("/cam1/refiner", "/refiner", False),
    ("/cam1/refiner", "/cam2/refiner", False), ("cam1/refiner", "/cam1/refiner", True),
    ("/*/refiner", "/refiner", False), ("/*/refiner", "/cam1/refiner", True),
    ("/**/*", "/a/b/refiner", True), ("/**/cam1/*", "/cam1/refiner", True),
    ("/**/cam1/*", "/cam1/a/refiner", False), ("/*/*", "/cam1/refiner", True),
]


@pytest.mark.parametrize("section,fqn,applies", RCL_MATCHES)
def test_sections_match_node_names_as_rcl_does(section, fqn, applies):
    from sfm_ttr_ros.core.params.sections import section_matches

    assert section_matches(section, fqn) is applies


def test_later_sections_override_earlier_ones_key_by_key(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text(textwrap.dedent("""
        /cam1/refiner:
          ros__parameters: {window_size: 6, window_stride: 2}
        /**:
          ros__parameters: {window_size: 8}
        /cam2/refiner:
          ros__parameters: {window_size: 12}
        /cam1/*:
          ros__parameters: {refinement.steps: 9}
    """))
    assert schema.read_params_file(f, "refiner", namespace="/cam1") == {
        "window_size": 8, "window_stride": 2, "refinement.steps": 9}
    assert schema.read_params_file(f, "refiner", namespace="cam2") == {"window_size": 12}
    assert schema.read_params_file(f, "refiner") == {"window_size": 8}


def test_parameter_files_that_skip_the_node_are_named(tmp_path):
    from sfm_ttr_ros.core.params.sections import params_file_arguments, unapplied_files

    own, other = tmp_path / "own.yaml", tmp_path / "other.yaml"
    own.write_text("/**:\n  ros__parameters:\n    window_size: 6\n")
    other.write_text("refiner:\n  ros__parameters:\n    window_size: 6\n")
    args = ["prog", "--accounting", "a.json", "--ros-args", "-r", "__ns:=/cam1",
            "--params-file", str(own), "--", "--params-file", "not-ros.yaml",
            "--ros-args", "--params-file", str(other)]
    assert params_file_arguments(args) == [str(own), str(other)]
    [message] = unapplied_files(args, "/cam1/refiner")
    assert message.startswith(f"{other}: no section applies to node /cam1/refiner (its "
                              "sections: /refiner)")
    assert unapplied_files(args, "/refiner") == []


BEFORE = json.loads((REPO / "tests" / "data" / "params_before_defaults.json").read_text())


#: the node's settings that changed on purpose the same day, none with an effect on the depth
#: (docs/decisions.md, "A ROS citizen on any camera"): reliable inputs, the odometry of the
#: robot's base in its own frame, intrinsics assumed for an uncalibrated camera
CONVENTIONS_CHANGED = ("qos_reliability", "odom_frame_id", "odom_child_frame_id",
                       "odom_camera_mount", "assumed_hfov_deg")


def _without_conventions(settings: dict) -> dict:
    """``settings`` (JSON-like) less the node's CONVENTIONS_CHANGED (a copy)."""
    out = copy.deepcopy(settings)
    for key in CONVENTIONS_CHANGED:
        out["node"].pop(key, None)
    return out


def _built(values: dict) -> dict:
    """Everything ``values`` configures, as JSON would hold it (less CONVENTIONS_CHANGED)."""
    s = schema.build(values)
    return _without_conventions(json.loads(json.dumps(
        {k: dataclasses.asdict(getattr(s, k)) for k in ("ttr", "stream", "model", "node")})))


#: defaults measured since the profiles moved (parameter: its new default; docs/decisions.md):
#: a profile that does not set one builds the new value, the paper's profiles set the old one
MEASURED_SINCE = {"sfm.overlap": 5}


def _before(name: str, values: dict | None = None) -> dict:
    """What profile ``name`` built before the defaults moved (less CONVENTIONS_CHANGED), with
    the defaults measured since wherever its ``values`` do not set them."""
    before = _without_conventions(BEFORE["settings"][name])
    for key, value in MEASURED_SINCE.items():
        if key not in (values or {}):
            section, field = key.split(".")
            before["ttr"][section][field] = value
    return before


@pytest.mark.parametrize("name", sorted(BEFORE["settings"]))
def test_shipped_profiles_build_what_they_built_before_the_defaults_moved(name):
    """The defaults became the measured real-footage settings (docs/decisions.md, 2026-11-29):
    kitti.yaml keeps KITTI's camera, paper.yaml and kitti_accurate.yaml say everything the
    paper's method sets; each still builds exactly the configs it built with the old defaults
    (``tests/data/params_before_defaults.json``, computed from the tree before the change),
    less the defaults measured since (MEASURED_SINCE) where it does not set them."""
    values = schema.read_params_file(REPO / "params" / f"{name}.yaml", "refiner")
    assert _built(values) == _before(name, values)
    if name != "kitti":
        assert set(MEASURED_SINCE) <= set(values)  # the paper's profiles keep the paper's


def test_the_defaults_are_the_kitti_profile_without_kittis_camera():
    """No file: the settings every real-footage figure was made with (the old kitti.yaml),
    less KITTI's camera facts: its intrinsics, their source and metres from its height."""
    expected = _before("kitti")
    expected["node"].update(fallback_intrinsics="", camera_info_use_projection="auto")
    expected["ttr"]["metric"]["source"] = "none"
    assert _built({}) == expected


def test_command_line_precedence(tmp_path):
    """schema default < parameter file < flag < --set, on the parser of ``sfm-ttr run``."""
    from sfm_ttr_ros.tools.cli import build_parser
    from sfm_ttr_ros.tools.cli_args import PARAM_FLAGS, parameter_values

    f = tmp_path / "p.yaml"
    f.write_text("refiner:\n  ros__parameters:\n    refinement.steps: 7\n    refinement.lr: "
                 "0.001\n    encoder_path: e.pth\n    decoder_path: d.pth\n")
    parser = build_parser()

    def values(*extra: str) -> dict:
        args = parser.parse_args(["run", "--out", str(tmp_path / "o"), *extra])
        return parameter_values(args)[1]

    def steps(*extra: str) -> int:
        return schema.build(values(*extra)).ttr.refinement.steps

    assert values() == {} and steps() == 70  # no file: the defaults (measured on real video)
    assert steps("--params-file", str(f)) == 7
    assert steps("--params-file", str(f), "--steps", "9") == 9
    assert steps("--params-file", str(f), "--steps", "9", "--set", "refinement.steps=11") == 11
    assert values("--params-file", str(f))["refinement.lr"] == 0.001
    # --model: the file's weights files belong to the file's model
    v = values("--params-file", str(f), "--model", "mobilenet")
    assert (v["model_type"], v["encoder_path"], v["decoder_path"]) == ("mobilenet", "", "")
    # every flag is a row of the table, typed by its parameter
    assert schema.build(values("--threads", "3", "--lr", "1")).node.torch_num_threads == 3
    assert type(values("--lr", "1")["refinement.lr"]) is float
    for name, _ in PARAM_FLAGS.values():
        assert name in schema.SCHEMA
    with pytest.raises(SystemExit):
        parser.parse_args(["run", "--out", "o", "--bn-mode", "sideways"])


def test_parameters_page_is_up_to_date(capsys):
    """docs/parameters.md is what ``sfm-ttr params`` prints (regenerate:
    ``sfm-ttr params > docs/parameters.md``)."""
    from sfm_ttr_ros.tools.cli import main

    assert main(["params"]) == 0
    page = capsys.readouterr().out
    assert (REPO / "docs" / "parameters.md").read_text(encoding="utf-8") == page
    assert main(["params", "--table"]) == 0
    table = capsys.readouterr().out
    assert table in page and len(table.splitlines()) == len(schema.PARAMS) + 2
    assert "| `refinement.steps` | integer | `70` | 0 … 1e6 | live |" in table
    assert "| `model_type` | string | `\"default\"` |" in table and "start-up" in table


def test_schema_and_cli_parsers_import_without_ros():
    """The schema, ``sfm-ttr run`` / ``benchmark`` argument handling and the benchmark package
    import with rclpy, rcl_interfaces and every *_msgs package blocked."""
    code = textwrap.dedent("""
        import sys
        class Block:
            def find_spec(self, name, path=None, target=None):
                top = name.split(".")[0]
                if top in ("rclpy", "rcl_interfaces") or top.endswith("_msgs"):
                    raise ImportError(f"blocked: {name}")
        sys.meta_path.insert(0, Block())
        from sfm_ttr_ros.core import params
        from sfm_ttr_ros.tools import benchmark, cli, cli_args, cli_benchmark
        cli.build_parser().parse_args(["benchmark", "--images", "x", "--out", "o",
                                       "--set", "refinement.steps=3"])
        bad = sorted(m for m in sys.modules
                     if m.split(".")[0] in ("rclpy", "rcl_interfaces")
                     or m.split(".")[0].endswith("_msgs"))
        assert not bad, bad
    """)
    _run_in_fresh_python(code)


def test_reading_the_schema_imports_the_configs_not_the_pipeline():
    """``import sfm_ttr_ros.core.params.schema`` loads the config dataclasses it reads, not the
    pipeline, the stream's worker or pycolmap (a tool reading parameters pays for no SfM)."""
    code = textwrap.dedent("""
        import sys
        import sfm_ttr_ros.core.params.schema
        heavy = ("pycolmap", "sfm_ttr_ros.core.pipeline", "sfm_ttr_ros.core.stream.window_runner",
                 "sfm_ttr_ros.core.refinement.encoder", "sfm_ttr_ros.core.sfm.reconstruction")
        loaded = [m for m in heavy if m in sys.modules]
        assert not loaded, loaded
    """)
    _run_in_fresh_python(code)


def test_parameters_retired_on_2026_11_29_set_their_config_fields():
    """The parameters that left the schema on 2026-11-29 (docs/decisions.md) still work under
    their old names for one release and set the config field; its checks still apply."""
    old = {"refinement.bn_mode": "train", "refinement.photometric_weight": 3.0,
           "min_keyframe_interval_s": 0.5, "reuse_live_predictions": False,
           "compressed_depth.png_level": 9, "sfm.mapping_attempts": 3}
    assert not set(old) & set(schema.SCHEMA)
    s = schema.build(old, as_node=True)
    assert (s.ttr.refinement.bn_mode, s.ttr.refinement.photometric_weight) == ("train", 3.0)
    assert s.stream.min_keyframe_interval_s == 0.5 and not s.ttr.reuse_live_predictions
    assert s.node.compressed_depth_png_level == 9 and s.ttr.sfm.mapping_attempts == 3
    assert len(s.warnings) == len(old) and all("deprecated" in w for w in s.warnings)
    assert "mapping_attempts" in schema.validate({"sfm.mapping_attempts": 0})
    assert "png_level" in schema.validate({"compressed_depth.png_level": 10})


def test_node_settings_validate_themselves():
    from sfm_ttr_ros.core.params.node import NodeSettings

    assert NodeSettings().use_projection is None
    for bad, match in (({"fallback_intrinsics": "-1 1 0 0"}, "fallback_intrinsics"),
                       ({"qos_depth": 0}, "qos_depth"), ({"outputs": "depth;points"}, "outputs"),
                       ({"qos_reliability": "sometimes"}, "qos_reliability"),
                       ({"diagnostics_period_s": 0.0}, "diagnostics_period_s"),
                       ({"torch_num_threads": -1}, "torch_num_threads"),
                       ({"cloud_stride": 0}, "cloud.stride"),
                       ({"cloud_max_range": -1.0}, "cloud.max_range"),
                       ({"cloud_max_range": float("nan")}, "cloud.max_range")):
        with pytest.raises(InputError, match=match):
            NodeSettings(**bad)
    # every node setting is a parameter, or a config field that was one (legacy.py)
    fields_now = {row.becomes.removeprefix("the field node.") for row in schema.LEGACY
                  if row.becomes.startswith("the field node.")}
    assert {f.name for f in dataclasses.fields(NodeSettings)} == fields_now | {
        t.partition(".")[2] for p in schema.PARAMS for t in p.targets if t.startswith("node.")}


def test_legacy_names_still_work_for_one_release_with_a_warning(tmp_path):
    """A parameter file of the last release still runs: renamed parameters are translated,
    parameters that became config fields set the field, removed ones are ignored at their old
    default and refused at any other value; each says what replaces it."""
    old = tmp_path / "old.yaml"
    old.write_text("refiner:\n  ros__parameters:\n    reset_each_window: true\n"
                   "    fx: 721.5\n    fy: 721.5\n    cx: 609.5\n    cy: 172.8\n"
                   "    publish_colored: false\n    publish_points: false\n"
                   "    worker_nice: 5\n    refinement.photometric_alpha: 0.8\n"
                   "    check.holdout_fraction: 0.0\n    carried_steps: 0\n")
    values = schema.read_params_file(old, "refiner")
    s = schema.build(values)
    assert s.ttr.weight_policy == "reset"
    assert s.node.fallback == (721.5, 721.5, 609.5, 172.8)
    assert s.node.published == {"depth", "depth_refined", "diagnostics"}
    assert s.stream.worker_nice == 5 and s.ttr.refinement.photometric_alpha == 0.8
    text = "\n".join(s.warnings)
    for name in ("reset_each_window", "fx", "publish_points", "worker_nice",
                 "check.holdout_fraction", "carried_steps"):
        assert f"'{name}'" in text, name
    assert "use weight_policy" in text and "the field stream.worker_nice" in text
    # the new name wins over a translated legacy one
    assert schema.build({"publish_points": False, "outputs": "points"}).node.published == \
        {"points"}
    # a removed parameter at anything but its old default: the behaviour is gone, refused
    with pytest.raises(InputError, match="'check.holdout_fraction' was removed"):
        schema.build({"check.holdout_fraction": 0.2})
    with pytest.raises(InputError, match="must be a double"):
        schema.build({"fx": 700})
    assert schema.build(schema.parse_overrides(["reset_each_window=true"])).ttr.weight_policy \
        == "reset"


def _run_in_fresh_python(code: str) -> None:
    """Run ``code`` in a fresh interpreter with the repository first on the path; its
    assertions must hold."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=env, cwd=REPO, timeout=120)
    assert proc.returncode == 0, proc.stderr
