"""scripts/profile_refinement.py (sfm_ttr_ros/tools/step_profile.py) small on the CPU: one window
of a generated drive, each step mode from the same weights under torch.profiler (per-step host
time, aten ops per step, which mode ran and why), the step micro-benchmark and the window's SfM
with pycolmap's features. 6 frames of 320x96, a tiny plug-in network, 6 steps."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import write_small_kitti_params

from sfm_ttr_ros.tools import step_profile

REPO = Path(__file__).resolve().parents[1]
STEPS = 6


@pytest.fixture(scope="module")
def data(tmp_path_factory, tiny_plugin, one_thread):
    from sfm_ttr_ros.data.kitti import write_kitti_drive
    from sfm_ttr_ros.data.synthetic import make_sequence

    root = tmp_path_factory.mktemp("profile")
    seq = make_sequence(seed=1, domain="B", num_frames=6, width=320, height=96)
    write_kitti_drive(seq, root / "raw", root / "gt")
    tiny_plugin(root / "profile_tiny_model.py", 64, 192)
    write_small_kitti_params(REPO, root / "small.yaml")
    sys.path.insert(0, str(root))
    yield root
    sys.path.remove(str(root))
    sys.modules.pop("profile_tiny_model", None)


def args(root: Path, *extra: str) -> list[str]:
    return ["--kitti-raw", str(root / "raw"), "--params-file", str(root / "small.yaml"),
            "--set", "model_type=python:profile_tiny_model:factory",
            "--set", "torch_num_threads=1", "--window", "4", "--steps", str(STEPS), *extra]


@pytest.fixture(scope="module")
def report(data):
    out = data / "profile.json"
    assert step_profile.main(args(data, "--modes", "eager", "static", "auto", "--micro-steps",
                                  str(STEPS), "--micro-points", "50", "--micro-frames", "2",
                                  "--sfm-features", "colmap", "--out", str(out))) == 0
    return json.loads(out.read_text())


def test_each_mode_is_profiled_per_step(report):
    p = report["profile"]
    assert report["environment"]["device"] == "cpu" and report["frames"] == 4
    assert report["steps"] == STEPS and report["loss"] == "hybrid"
    assert [p[m]["step_mode"] for m in ("eager", "static", "auto")] == \
        ["eager", "static", "eager"]
    assert p["auto"]["reason"] == "not on CUDA (cpu)"
    for r in p.values():
        assert r["steps"] == STEPS and len(r["host_ms"]) == STEPS and min(r["host_ms"]) > 0
        assert r["launches_kind"] == "aten ops (CPU)"
        assert len(r["launches"]) == STEPS and min(r["launches"]) > 100
        assert r["launches_steady_median"] > 100 and r["steady_ms_per_step"] > 0
        assert r["device_busy_ms"] is None  # no CUDA here
    # the same weights and seed: the static step's losses are the eager step's
    assert p["static"]["max_rel_loss_diff"] < 1e-5 and p["auto"]["max_rel_loss_diff"] == 0


def test_micro_benchmark_and_sfm(report):
    m = report["micro"]
    assert (m["points"], m["frames"], m["steps"]) == (50, 2, STEPS)
    assert m["eager"]["step_mode"] == "eager" and m["eager"]["steady_ms_per_step"] > 0
    s = report["sfm"]["colmap"]
    assert s["ok"] and s["registered"] >= 3 and s["points"] > 0 and s["seconds"] > 0


def test_the_script_runs_and_refuses_a_window_outside_the_drive(data):
    script = REPO / "scripts" / "profile_refinement.py"
    r = subprocess.run([sys.executable, str(script), *args(data, "--start", "4", "--modes",
                                                           "eager")],
                       capture_output=True, text=True, cwd=REPO, timeout=300)
    assert r.returncode == 2 and "not all in the 6-frame sequence" in r.stderr
    lines = step_profile.summary_lines({"environment": {"device_name": "cpu", "torch": "x"},
                                        "frames": 4, "image_size": [320, 96],
                                        "stop": "SfM failed"})
    assert lines[-1] == "window not refined: SfM failed"


def test_the_gpu_checks_summary(data, report, tmp_path):
    """scripts/gpu_window_check.sh's check.json from the files its parts write (here: the
    profile above, a parts line, a benchmark's results.json in short)."""
    (tmp_path / "profile.json").write_text(json.dumps(report))
    (tmp_path / "parts.jsonl").write_text('{"part": "profile", "rc": 0, "seconds": 3}\n')
    bench = tmp_path / "bench_graph"
    bench.mkdir()
    (bench / "results.json").write_text(json.dumps({"modes": ["node_online"], "node_online": {
        "abs_rel": 0.1, "seconds_per_frame": 0.3, "timings": {"refine": 2.0}, "windows": 2,
        "window_log": [{"step_mode": "graph"}, {"step_mode": "graph"}]}}))
    path = step_profile.write_check_summary(tmp_path)
    s = json.loads(path.read_text())
    assert s["parts"] == [{"part": "profile", "rc": 0, "seconds": 3}]
    assert s["profile"]["profile"]["auto"]["reason"] == "not on CUDA (cpu)"
    assert s["profile"]["micro"]["eager"]["step_mode"] == "eager" and s["profile"]["sfm"]
    assert s["bench_graph"]["node_online"]["step_modes"] == {"graph": 2}
    assert s["bench_graph"]["node_online"]["refine_s"] == 2.0
    assert s["timing"] == {} and s["bench_eager"] is None  # parts that wrote nothing


def test_a_cuda_trace_counts_host_steps_and_device_work_only():
    """A CUDA profile of two steps (tests/data/cuda_profile_trace.json, torch.profiler's Chrome
    trace events): each ProfilerStep range also appears on the device's timeline
    (gpu_user_annotation) and must not double the steps; launches are counted on the host;
    device busy time is kernels, copies and sets only, never annotation spans."""
    trace = json.loads((REPO / "tests" / "data" / "cuda_profile_trace.json").read_text())
    events = [e for e in trace["traceEvents"] if e.get("ph") == "X"]
    assert len(step_profile.step_ranges(events)) == 2
    launches = step_profile._count_per_step(events, lambda n: n in step_profile.KERNEL_LAUNCHES)
    assert launches == [3, 3]
    graphs = step_profile._count_per_step(events, lambda n: n in step_profile.GRAPH_LAUNCHES)
    assert graphs == [1, 1]
    assert step_profile._device_busy_ms(events) == pytest.approx(2 * (100 + 20 + 10 + 2 + 68)
                                                                 / 1e3)
    assert step_profile._device_busy_ms([e for e in events if e["cat"] != "kernel"]) == \
        pytest.approx(2 * 12 / 1e3)
