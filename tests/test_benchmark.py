"""``sfm-ttr benchmark`` and the folder mode of ``sfm-ttr evaluate`` on a tiny generated drive.

The benchmark runs once per module (8 frames at 320x96, a tiny random network, 5 steps,
3 online windows): ~20 s on 2 cores."""

from __future__ import annotations

import argparse
import copy
import csv
import json
import math
import shlex
import sys
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import write_small_kitti_params

from sfm_ttr_ros.core.errors import InputError

REPO = Path(__file__).resolve().parents[1]
DRIVE = "2011_09_26_drive_0001_sync"
N_FRAMES, GT_SKIP = 8, 1
N_GT = N_FRAMES - 2 * GT_SKIP
MODES = ("no_ttr", "node_online", "sfm_ttr_online", "sfm_ttr_offline")
KEYS = ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3", "frames", "seconds_per_frame",
        "refined_frames", "timings")


def cli(argv: list[str]) -> int:
    """``sfm-ttr ARGV``: through ``cli.main`` once the commands are wired into it, else through
    a parser holding only this module's commands, with the same error handling."""
    from sfm_ttr_ros.tools import cli as cli_mod
    from sfm_ttr_ros.tools.cli_benchmark import add_commands

    sub = next(a for a in cli_mod.build_parser()._actions
               if isinstance(a, argparse._SubParsersAction))
    if "benchmark" in sub.choices:
        return cli_mod.main(argv)
    p = argparse.ArgumentParser(prog="sfm-ttr")
    add_commands(p.add_subparsers(dest="command", required=True))
    args = p.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except InputError as exc:
        print(f"sfm-ttr: error: {exc}", file=sys.stderr)
        return 2


@pytest.fixture(scope="module")
def data(tmp_path_factory, tiny_plugin):
    from sfm_ttr_ros.data.kitti import write_kitti_drive
    from sfm_ttr_ros.data.synthetic import make_sequence

    root = tmp_path_factory.mktemp("bench")
    seq = make_sequence(seed=1, domain="B", num_frames=N_FRAMES, width=320, height=96)
    write_kitti_drive(seq, root / "raw", root / "gt", gt_skip_ends=GT_SKIP)
    tiny_plugin(root / "bench_tiny_model.py", 64, 192)
    # The node's KITTI file with small windows and a lower point threshold for tiny images.
    # (the tiny plug-in has no staged encoder: its whole encoder is refined)
    write_small_kitti_params(REPO, root / "small.yaml")
    sys.path.insert(0, str(root))
    yield root
    sys.path.remove(str(root))


def gt_dir(root: Path) -> Path:
    return root / "gt" / "val" / DRIVE / "proj_depth" / "groundtruth" / "image_02"


def kitti_args(root: Path, out: Path, *extra: str) -> list[str]:
    return ["benchmark", "--kitti-raw", str(root / "raw"), "--kitti-gt", str(root / "gt"),
            "--drive", DRIVE, "--out", str(out), "--model", "python:bench_tiny_model:factory",
            *extra]


@pytest.fixture(scope="module")
def bench(data):
    out = data / "out"
    argv = kitti_args(data, out, "--params-file", str(data / "small.yaml"), "--steps", "5",
                      "--lr", "1e-3", "--set", "refinement.photometric_weight=5.0",
                      "--save-depth")
    saved, sys.argv = sys.argv, ["sfm-ttr", *argv]  # what results.json records as the command
    try:
        assert cli(argv) == 0
    finally:
        sys.argv = saved
    res = json.loads((out / "results.json").read_text())
    assert res["command"] == shlex.join(["sfm-ttr", *argv])
    return out, res


@pytest.mark.slow
def test_results_json_has_every_mode_and_key(bench, data):
    out, res = bench
    assert res["modes"] == list(MODES)
    assert res["frames_total"] == N_FRAMES and res["frames_with_gt"] == N_GT
    for m in MODES:
        r = res[m]
        assert set(KEYS) <= set(r), f"{m} lacks {set(KEYS) - set(r)}"
        assert r["frames"] == N_GT and r["processed_frames"] == N_FRAMES and r["lost_frames"] == 0
        for k in ("abs_rel", "sq_rel", "rmse", "rmse_log"):
            assert r[k] > 0 and math.isfinite(r[k])
        assert 0 <= r["a1"] <= r["a2"] <= r["a3"] <= 1
        assert r["seconds_per_frame"] > 0
        if m.endswith("_online"):  # paid before the first frame, as the node's worker does
            assert r["warm_up_s"] > 0
    assert res["no_ttr"]["refined_frames"] == 0 and set(res["no_ttr"]["timings"]) == {"predict"}
    for m in MODES[1:]:
        assert res[m]["refined_frames"] > 0
        assert {"sfm", "align", "refine", "predict_before", "predict_after"} <= \
            set(res[m]["timings"])
        assert set(res["relative_gain"][m]) == {"abs_rel", "sq_rel", "rmse", "rmse_log", "a1",
                                                "a2", "a3"}
        gain = res["relative_gain"][m]["abs_rel"]
        before, after = res["no_ttr"]["abs_rel"], res[m]["abs_rel"]
        assert gain == pytest.approx((before - after) / before)
    # online: the node's windows from the parameter file (4 frames, 2 new), every frame once
    online = res["sfm_ttr_online"]
    assert online["windows"] == 3 and online["stream_counters"]["received"] == N_FRAMES
    assert online["stream_counters"]["pending"] == 0
    assert res["sfm_ttr_offline"]["windows"] == 1
    assert res["sfm_ttr_offline"]["offline_windows"][0]["frames"] == N_FRAMES
    # settings: the file's values (kitti.yaml's overload_pending 50), the flags over them
    s = res["settings"]
    assert s["params_file"] == str(data / "small.yaml")
    assert s["stream"]["window_size"] == 4 and s["stream"]["window_stride"] == 2
    assert s["stream"]["overload_pending"] == 50 and s["ttr"]["min_supervision_points"] == 20
    assert s["ttr"]["refinement"]["steps"] == 5 and s["ttr"]["refinement"]["lr"] == 1e-3
    assert s["ttr"]["refinement"]["photometric_weight"] == 5.0  # --set
    assert s["stream"]["idle_flush_s"] == 2.0 and s["torch_threads"] >= 1
    assert res["model"]["type"] == "python:bench_tiny_model:factory"
    assert res["model"]["class"] == "EncoderDecoder"


@pytest.mark.slow
def test_markdown_csv_and_figure(bench):
    out, res = bench
    md = (out / "results.md").read_text()
    for m in MODES:
        assert f"| {m} | {res[m]['abs_rel']:.4f} |" in md
    assert "figure.png" in md
    rows = list(csv.DictReader(open(out / "per_frame.csv")))
    assert len(rows) == N_GT
    mean = np.mean([float(r["sfm_ttr_online_abs_rel"]) for r in rows])
    assert mean == pytest.approx(res["sfm_ttr_online"]["abs_rel"], rel=1e-5)
    fig = cv2.imread(str(out / "figure.png"))
    assert fig is not None and fig.ndim == 3
    # two frames, each: a depth row (96 px), an error row, a scatter row (>= 256 px)
    assert fig.shape[0] >= 2 * (96 * 2 + 256) and fig.shape[1] == (len(MODES) + 1) * 320
    assert fig.std() > 10  # not blank


@pytest.mark.slow
def test_every_window_is_listed_with_its_checks_and_drawn(bench):
    """each windowed mode lists its windows (frames, outcome, reason key, the
    checks' statistics); results.md tabulates them; windows.png draws them."""
    out, res = bench
    online = res["sfm_ttr_online"]
    log = online["window_log"]
    assert len(log) == online["windows"] == 3
    assert [w["frames"] for w in log] == [[0, 1, 2, 3], [2, 3, 4, 5], [4, 5, 6, 7]]
    for w in log:
        assert w["refined"] == (w["reason_key"] == "")
        if w["check"] is not None:
            assert w["check"]["reprojection_error"] > 0 and w["check"]["track_length"] >= 2
        if w["refined"]:  # the sanity checks passed
            assert w["check"]["parallax"] >= 0.1 and w["check"]["reason_key"] is None
    assert online["refined_frames"] > 0
    md = (out / "results.md").read_text()
    assert "Windows (refused" in md and "| sfm_ttr_online | 0 | 0-3 |" in md
    fig = cv2.imread(str(out / "windows.png"))
    assert fig is not None and fig.shape[1] == 1200 and fig.std() > 10


def test_timeline_marks_refused_windows_in_red():
    from sfm_ttr_ros.tools.benchmark.timeline import _REJECTED, window_timeline_figure

    abs_rel = {"no_ttr": {i: 0.2 for i in range(10)}, "m": {i: 0.1 for i in range(10)}}
    logs = {"m": [{"frames": list(range(0, 5)), "refined": True, "reason_key": ""},
                  {"frames": list(range(5, 10)), "refined": False,
                   "reason_key": "check_unsupported_change"}]}
    img = window_timeline_figure(abs_rel, logs, 0, 9, labels=["drive"] * 5 + ["lead"] * 5)
    red = np.all(img == np.array(_REJECTED, np.uint8), axis=2)
    cols = np.flatnonzero(red.any(axis=0))
    plot_left, plot_width = 60, img.shape[1] - 60 - 170  # the frame axis spans these pixels
    assert cols.size and cols.min() > plot_left + 0.4 * plot_width  # frames 5-9 only
    logs["m"][1]["refined"] = True
    img = window_timeline_figure(abs_rel, logs, 0, 9)
    assert not np.all(img == np.array(_REJECTED, np.uint8), axis=2).any()


@pytest.mark.slow
def test_saved_depth_evaluates_to_the_same_numbers(bench, data):
    """The saved depths through ``sfm-ttr evaluate`` give results.json's metrics, and the
    refined depths differ from the unrefined ones."""
    out, res = bench
    js = data / "eval.json"
    preds = [str(out / "depth" / m) for m in MODES]
    assert cli(["evaluate", "--pred", *preds, "--gt", str(gt_dir(data)), "--out", str(js)]) == 0
    ev = json.loads(js.read_text())
    for m in MODES:
        for k in ("abs_rel", "rmse", "a1"):
            assert ev["results"][m][k] == pytest.approx(res[m][k], rel=1e-6)
        assert ev["results"][m]["frames"] == N_GT and ev["results"][m]["missing_gt"] == 2
    name = "0000000003.npy"
    before = np.load(out / "depth" / "no_ttr" / name)
    for m in MODES[1:]:
        after = np.load(out / "depth" / m / name)
        assert after.shape == before.shape == (96, 320)
        assert np.abs(after - before).max() > 0


def hand_bands(depth_dir: Path, gt: Path, names: list[str]) -> dict[str, tuple[float, float,
                                                                              int]]:
    """abs rel, RMSE and pixel count per GT band, pooled over the frames' pixels, from the saved
    depths and the GT PNGs (median scaling, clamped to 1e-3 .. 80 m): written out by hand."""
    g_all, p_all = [], []
    for name in names:
        g = cv2.imread(str(gt / f"{name}.png"), cv2.IMREAD_UNCHANGED) / 256.0
        p = cv2.resize(np.load(depth_dir / f"{name}.npy").astype(np.float64),
                       (g.shape[1], g.shape[0]))
        m = (g > 1e-3) & (g < 80)
        g, p = g[m], p[m]
        g_all.append(g)
        p_all.append(np.clip(p * np.median(g) / np.median(p), 1e-3, 80))
    g, p = np.concatenate(g_all), np.concatenate(p_all)
    out = {}
    for lo, hi in ((0, 10), (10, 20), (20, 40), (40, 80)):
        k = (g >= lo) & (g < hi)
        out[f"{lo}-{hi}"] = (float(np.mean(np.abs(p[k] - g[k]) / g[k])) if k.any() else None,
                             float(np.sqrt(np.mean((p[k] - g[k]) ** 2))) if k.any() else None,
                             int(k.sum()))
    return out


@pytest.mark.slow
def test_every_mode_has_depth_bands_and_the_error_by_depth_figure(bench, data):
    """``bands`` (pooled over pixels) agree with a hand computation from the saved depths; the
    fine bins add up to the bands; error_by_depth.png is drawn."""
    out, res = bench
    names = sorted(p.stem for p in gt_dir(data).glob("*.png"))
    assert len(names) == N_GT
    for m in MODES:
        bands = res[m]["bands"]
        assert list(bands) == ["0-10", "10-20", "20-40", "40-80"]
        want = hand_bands(out / "depth" / m, gt_dir(data), names)
        for band, (abs_rel, rmse, pixels) in want.items():
            assert bands[band]["pixels"] == pixels, (m, band)
            if pixels:
                assert bands[band]["abs_rel"] == pytest.approx(abs_rel, rel=1e-5), (m, band)
                assert bands[band]["rmse"] == pytest.approx(rmse, rel=1e-5), (m, band)
            else:
                assert bands[band]["abs_rel"] is None
        fine = res[m]["error_by_depth"]
        assert len(fine["edges"]) == len(fine["pixels"]) + 1 and fine["edges"][-1] == 80
        assert sum(fine["pixels"]) == sum(b["pixels"] for b in bands.values())
    assert sum(b["pixels"] for b in res["no_ttr"]["bands"].values()) > 0
    md = (out / "results.md").read_text()
    assert "| no_ttr | " in md and "0-10 m" in md and "error_by_depth.png" in md
    fig = cv2.imread(str(out / "error_by_depth.png"))
    assert fig is not None and fig.shape[2] == 3 and fig.std() > 10


@pytest.fixture(scope="module")
def loss_bench(data):
    """The photometric and hybrid modes on the same drive and windows."""
    out = data / "out_loss"
    modes = ["no_ttr", "ph_ttr_online", "hybrid_online", "ph_ttr_offline", "hybrid_offline"]
    # one SfM thread: pycolmap's mapper is deterministic then (with two it once registered 2
    # of the 8 frames of the offline window, which the parallax check refused)
    argv = kitti_args(data, out, "--params-file", str(data / "small.yaml"), "--steps", "5",
                      "--lr", "1e-3", "--save-depth", "--figure-frames", "1",
                      "--set", "sfm.num_threads=1", "--modes", *modes)
    assert cli(argv) == 0
    return out, json.loads((out / "results.json").read_text()), modes


@pytest.mark.slow
def test_photometric_and_hybrid_modes(loss_bench, bench):
    out, res, modes = loss_bench
    assert res["modes"] == modes
    sfm_out, sfm_res = bench
    for m in modes[1:]:
        r = res[m]
        assert r["frames"] == N_GT and r["lost_frames"] == 0 and r["refined_frames"] > 0, m
        assert math.isfinite(r["abs_rel"]) and set(r["bands"]) == {"0-10", "10-20", "20-40",
                                                                   "40-80"}
        assert r["windows"] == (3 if m.endswith("_online") else 1)
        # refined with its own objective: other depths than SfM-TTR's on the same windows
        twin = "sfm_ttr_" + m.split("_")[-1]
        name = "0000000003.npy"
        assert np.abs(np.load(out / "depth" / m / name)
                      - np.load(sfm_out / "depth" / twin / name)).max() > 0
    # the file's loss (kitti.yaml's auto: the hybrid for this network) is recorded; each mode
    # ran its own (runners.mode_config): the sfm_ttr_* twins above ran Eq. (5), other depths
    assert res["settings"]["ttr"]["refinement"]["loss"] == "auto"
    assert set(res["relative_gain"]) == set(modes[1:])
    md = (out / "results.md").read_text()
    for m in modes:
        assert f"| {m} | {res[m]['abs_rel']:.4f} |" in md
    assert (out / "error_by_depth.png").is_file() and (out / "figure.png").is_file()


def test_each_mode_runs_its_own_loss():
    from sfm_ttr_ros.core.pipeline import TTRConfig
    from sfm_ttr_ros.tools.benchmark import MODES as ALL_MODES
    from sfm_ttr_ros.tools.benchmark.runners import mode_config

    cfg = TTRConfig()
    cfg.refinement.loss, cfg.refinement.photometric_weight = "hybrid", 0.3
    want = {"sfm_ttr_online": "sfm", "sfm_ttr_offline": "sfm", "ph_ttr_online": "photometric",
            "ph_ttr_offline": "photometric", "hybrid_online": "hybrid",
            "hybrid_offline": "hybrid"}
    assert set(want) <= set(ALL_MODES)
    cfg.weight_policy = "continue"
    for mode, loss in want.items():
        out = mode_config(mode, cfg)
        assert out.refinement.loss == loss and out.refinement.photometric_weight == 0.3
        # the paper's modes refine every window from the start-up weights; the others keep
        # the file's policy
        assert out.weight_policy == ("reset" if mode.startswith("sfm_ttr") else "continue")
    assert cfg.refinement.loss == "hybrid"  # not modified in place
    assert mode_config("no_ttr", cfg) is cfg


def test_depth_bands_by_hand():
    """Two frames without median scaling: pooled abs rel / RMSE per band, by hand."""
    from sfm_ttr_ros.core.evaluation import EvalConfig
    from sfm_ttr_ros.tools.benchmark.bands import DepthBands

    acc = DepthBands(EvalConfig(median_scaling=False))
    acc.add(np.array([[4.0, 12.0], [30.0, 100.0]]), np.array([[5.0, 10.0], [25.0, 50.0]]))
    acc.add(np.array([[6.0, 0.0]]), np.array([[5.0, 0.0]]))  # GT 0: not a valid pixel
    b = acc.bands()
    assert b["0-10"] == {"abs_rel": pytest.approx(0.2), "rmse": pytest.approx(1.0),
                         "pixels": 2}
    assert b["10-20"] == {"abs_rel": pytest.approx(0.2), "rmse": pytest.approx(2.0),
                          "pixels": 1}
    assert b["20-40"]["abs_rel"] == pytest.approx(0.2) and b["20-40"]["pixels"] == 1
    # 100 m is clamped to the 80 m cap: |80 - 50| / 50
    assert b["40-80"]["abs_rel"] == pytest.approx(0.6) and b["40-80"]["rmse"] == 30.0
    assert sum(acc.by_depth()["pixels"]) == 5


@pytest.mark.parametrize("prediction", ["depth", "relative_inverse_depth"])
def test_the_bands_pool_to_the_frames_own_metrics(prediction):
    """The bands see the frame exactly as the evaluation does: on a frame with NaN, +-inf,
    negative and too-far predictions, at another size than the GT, pooling the bands' errors
    over the four bands [0, 80) gives the frame's abs rel and RMSE from ``compute_errors`` on
    the evaluation's scaled prediction, over the same pixels the evaluation counted."""
    from sfm_ttr_ros.core.evaluation import (
        EvalConfig,
        compute_errors,
        evaluate_frame,
        scaled_prediction,
    )
    from sfm_ttr_ros.tools.benchmark.bands import DepthBands

    rng = np.random.default_rng(5)
    gt = rng.uniform(0.5, 90.0, (48, 160))
    gt[rng.random(gt.shape) < 0.4] = 0.0  # sparse, and some GT beyond the 80 m cap
    if prediction == "depth":
        pred = cv2.resize(gt, (64, 20), interpolation=cv2.INTER_NEAREST) * 0.7 + 1.0
        pred[3, 5], pred[10, 40], pred[15, 60], pred[7, 7] = np.nan, np.inf, -np.inf, -2.0
        pred[0, :8] = 1e5  # far beyond max_depth once scaled
    else:
        pred = rng.uniform(0.01, 1.0, (20, 64))
        pred[3, 5], pred[10, 40], pred[15, 60] = np.nan, np.inf, -np.inf
    cfg = EvalConfig(prediction=prediction)
    frame = evaluate_frame(pred, gt, cfg)
    assert frame is not None and frame.invalid_pred > 0
    want = compute_errors(*scaled_prediction(pred, gt, cfg).values())
    assert want == frame.metrics
    acc = DepthBands(cfg)
    acc.add(pred, gt)
    bands = acc.bands().values()
    pixels = sum(b["pixels"] for b in bands)
    assert pixels == frame.num_pixels == sum(acc.by_depth()["pixels"])
    abs_rel = sum(b["abs_rel"] * b["pixels"] for b in bands if b["pixels"]) / pixels
    mse = sum(b["rmse"] ** 2 * b["pixels"] for b in bands if b["pixels"]) / pixels
    assert abs_rel == pytest.approx(want["abs_rel"], rel=1e-12)
    assert math.sqrt(mse) == pytest.approx(want["rmse"], rel=1e-12)
    # a frame the evaluation skips adds nothing
    acc.add(np.full_like(pred, np.nan), gt)
    assert sum(b["pixels"] for b in acc.bands().values()) == pixels


def test_default_settings_are_the_node_kitti_file_and_offline_chunks(data, tmp_path):
    """Without settings, run_benchmark uses params/kitti.yaml; offline_max_frames splits."""
    from bench_tiny_model import factory

    from sfm_ttr_ros.core import params as schema
    from sfm_ttr_ros.core.models.mobilenet import MobileDepthNet
    from sfm_ttr_ros.data.sequence import open_kitti
    from sfm_ttr_ros.tools.benchmark import (
        BenchmarkOptions,
        default_params_file,
        read_params_file,
        run_benchmark,
        settings_from_params,
    )

    path = default_params_file()
    assert path == REPO / "params" / "kitti.yaml"
    values = read_params_file(path)
    assert "window_size" not in values and values["metric.source"] == "camera_height"  # camera
    ttr, stream, model = settings_from_params(values)
    assert (stream.window_size, stream.overload_pending) == (15, 50)  # the defaults
    full = schema.build({**schema.defaults(), **values})  # as the node builds them
    assert (ttr, stream, model) == (full.ttr, full.stream, full.model)
    assert model.type == "default"

    seq = open_kitti(data / "raw", DRIVE, data / "gt")
    # the default architecture (its staged encoder: the default frozen_encoder_levels apply)
    res = run_benchmark(seq, lambda: MobileDepthNet(input_size=(64, 192)), out_dir=tmp_path / "a",
                        modes=["no_ttr"],
                        options=BenchmarkOptions(figure_frames=0, progress=None))
    assert res["settings"]["stream"] == asdict(stream)
    assert res["settings"]["ttr"] == asdict(ttr)
    assert res["settings"]["ttr"]["refinement"]["steps"] == 70
    assert res["no_ttr"]["frames"] == N_GT and res["relative_gain"] == {}
    assert not (tmp_path / "a" / "figure.png").exists()

    small = copy.deepcopy(ttr)
    small.refinement.steps, small.min_supervision_points = 3, 20
    # the tiny plug-in has no encoder stages: the default frozen levels train it whole
    small.sfm.first_octave = -1  # octave 0 finds too few features in 320x96 images
    lines: list[str] = []
    res = run_benchmark(seq, factory, small, out_dir=tmp_path / "b",
                        modes=["no_ttr", "sfm_ttr_offline"],
                        options=BenchmarkOptions(offline_max_frames=5, figure_frames=1,
                                                 progress=lines.append))
    assert res["settings"]["stream"]["window_size"] == 15
    off = res["sfm_ttr_offline"]
    assert off["windows"] == 2 and [w["frames"] for w in off["offline_windows"]] == [5, 3]
    assert off["processed_frames"] == N_FRAMES and off["frames"] == N_GT
    assert "sfm_ttr_online" not in res and set(res["relative_gain"]) == {"sfm_ttr_offline"}
    assert any("sfm_ttr_offline: window 2/2" in x for x in lines)
    assert (tmp_path / "b" / "figure.png").is_file()


@pytest.mark.slow
def test_run_takes_a_params_file_and_set(data, tmp_path):
    """``sfm-ttr run`` reads the node's parameter file and ``--set`` over it (70 steps in the
    file, 3 given): one offline window over the drive, refined with 3 steps."""
    out = tmp_path / "run"
    argv = ["run", "--kitti-raw", str(data / "raw"), "--kitti-gt", str(data / "gt"), "--drive",
            DRIVE, "--out", str(out), "--model", "python:bench_tiny_model:factory",
            "--params-file", str(data / "small.yaml"), "--set", "refinement.steps=3"]
    assert cli(argv) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["refined"] and len(summary["loss_history"]) == 3
    assert summary["frames"] == N_FRAMES and "metrics" in summary
    # per_frame.csv written as the benchmark's (tools/report.write_per_frame_csv)
    rows = list(csv.DictReader(open(out / "per_frame.csv")))
    assert list(rows[0]) == ["index", "name", "no_ttr_abs_rel", "no_ttr_rmse", "no_ttr_refined",
                             "sfm_ttr_abs_rel", "sfm_ttr_rmse", "sfm_ttr_refined"]
    assert len(rows) == N_GT and all(r["no_ttr_refined"] == "0" for r in rows)
    assert all(r["sfm_ttr_refined"] == "1" and float(r["sfm_ttr_abs_rel"]) > 0 for r in rows)


def _write_png16(path: Path, depth_m: np.ndarray, scale: float = 256.0) -> None:
    assert cv2.imwrite(str(path), np.round(depth_m * scale).astype(np.uint16))


def test_evaluate_folder_matches_hand_computed_metrics(tmp_path):
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    gt.mkdir()
    pred.mkdir()
    # frame a: 4 valid pixels, gt 2, 4, 8, 16 m; prediction 1, 4, 10, 16
    _write_png16(gt / "a.png", np.array([[2.0, 4.0], [8.0, 16.0]]))
    np.save(pred / "a.npy", np.array([[1.0, 4.0], [10.0, 16.0]], np.float32))
    # frame b: gt 5, 5 and two pixels out of range (0 = none, 100 m > 80 m cap)
    _write_png16(gt / "b.png", np.array([[5.0, 5.0], [0.0, 100.0]]))
    np.save(pred / "b.npy", np.array([[5.0, 10.0], [3.0, 3.0]], np.float32))
    js = tmp_path / "r.json"
    assert cli(["evaluate", "--pred", str(pred), "--gt", str(gt), "--no-median-scaling",
                "--out", str(js)]) == 0
    r = json.loads(js.read_text())["results"]["pred"]
    a = {"abs_rel": (0.5 + 0 + 0.25 + 0) / 4, "sq_rel": (0.5 + 0 + 0.5 + 0) / 4,
         "rmse": math.sqrt(5 / 4), "rmse_log": math.sqrt((math.log(2) ** 2
                                                          + math.log(0.8) ** 2) / 4),
         "a1": 0.5, "a2": 0.75, "a3": 0.75}
    b = {"abs_rel": 0.5, "sq_rel": 2.5, "rmse": math.sqrt(12.5),
         "rmse_log": math.sqrt(math.log(2) ** 2 / 2), "a1": 0.5, "a2": 0.5, "a3": 0.5}
    for k in a:
        assert r[k] == pytest.approx((a[k] + b[k]) / 2), k
    assert r["frames"] == 2
    # per-image median scaling: a × 6/7 (medians 6 and 7), b × 2/3 (medians 5 and 7.5)
    assert cli(["evaluate", "--pred", str(pred), "--gt", str(gt), "--out", str(js)]) == 0
    r = json.loads(js.read_text())["results"]["pred"]
    assert r["abs_rel"] == pytest.approx((13 / 56 + 1 / 3) / 2)
    # a 1.5 m cap leaves no valid pixel in either frame: both skipped, exit status 1
    assert cli(["evaluate", "--pred", str(pred), "--gt", str(gt), "--max-depth", "1.5",
                "--out", str(js)]) == 1
    r = json.loads(js.read_text())["results"]["pred"]
    assert r["frames"] == 0 and r["skipped"] == 2


def test_evaluate_eigen_crop(tmp_path):
    """10 x 10 frame, prediction wrong by 100 % in row 0 only: 0.1 abs rel without the crop,
    0 inside it (rows int(0.408 * 10) = 4 to int(0.992 * 10) = 9)."""
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    gt.mkdir()
    pred.mkdir()
    _write_png16(gt / "f.png", np.full((10, 10), 10.0))
    p = np.full((10, 10), 10.0, np.float32)
    p[0] = 20.0
    np.save(pred / "f.npy", p)
    js = tmp_path / "r.json"
    base = ["evaluate", "--pred", str(pred), "--gt", str(gt), "--no-median-scaling", "--out",
            str(js)]
    assert cli(base) == 0
    assert json.loads(js.read_text())["results"]["pred"]["abs_rel"] == pytest.approx(0.1)
    assert cli([*base, "--eigen-crop"]) == 0
    r = json.loads(js.read_text())["results"]["pred"]
    assert r["abs_rel"] == 0 and r["per_frame"][0]["pixels"] == 5 * 9


def test_bad_input_is_a_clear_error(data, tmp_path, capsys):
    images = tmp_path / "images"
    images.mkdir()
    k = tmp_path / "K.txt"
    k.write_text("100 100 160 48\n")
    model = ["--model", "python:bench_tiny_model:factory"]
    cases = [
        # no frames
        ["benchmark", "--images", str(images), "--intrinsics", str(k), "--out",
         str(tmp_path / "o"), *model],
        # a missing GT folder
        ["benchmark", "--images", str(data / "raw" / "2011_09_26" / DRIVE / "image_02" / "data"),
         "--intrinsics", str(k), "--gt-depth", str(tmp_path / "nope"), "--out",
         str(tmp_path / "o"), *model],
        # a drive without GT
        kitti_args(data, tmp_path / "o")[:4] + [str(tmp_path), "--drive", DRIVE, "--out",
                                                str(tmp_path / "o"), *model],
        # start past the end, a bad parameter file
        kitti_args(data, tmp_path / "o", "--start", "100"),
        kitti_args(data, tmp_path / "o", "--params-file", str(tmp_path / "none.yaml")),
        # --set: an unknown name, a value out of range, no value
        kitti_args(data, tmp_path / "o", "--set", "refinement.stepz=3"),
        kitti_args(data, tmp_path / "o", "--set", "refinement.steps=-1"),
        kitti_args(data, tmp_path / "o", "--set", "refinement.steps"),
        # evaluate: nothing given, a missing GT folder, no matching names, a missing bag
        ["evaluate"],
        ["evaluate", "--pred", str(tmp_path), "--gt", str(tmp_path / "nope")],
        ["evaluate", "--pred", str(images), "--gt", str(gt_dir(data))],
        ["evaluate", "--bag", str(tmp_path / "none.bag")],
        ["evaluate", "--bag", str(tmp_path / "none.bag"), "--pred", str(images)],
    ]
    for argv in cases:
        assert cli(argv) == 2, argv
        err = capsys.readouterr().err
        assert "error" in err and "Traceback" not in err, (argv, err)
    assert not (tmp_path / "o").exists()
    with pytest.raises(SystemExit):
        cli(kitti_args(data, tmp_path / "o", "--modes", "sideways"))


def test_live_frames_skipped_for_overflow_are_counted_not_lost(data, tmp_path, monkeypatch):
    """A live frame the serving queue drops (overflow) is reported under not_published with its
    reason, not as a frame that never came out: processed + not published = fed."""
    import time

    from sfm_ttr_ros.core.stream.serving import ServingModel

    real = ServingModel.serve  # what the live server calls for every frame

    def slow(self, image):
        time.sleep(0.03)
        return real(self, image)

    monkeypatch.setattr(ServingModel, "serve", slow)
    out = tmp_path / "live"
    argv = kitti_args(data, out, "--params-file", str(data / "small.yaml"), "--steps", "2",
                      "--modes", "sfm_ttr_live", "--rate", "200",
                      "--set", "stream.live_max_queue=1")
    assert cli(argv) == 0
    r = json.loads((out / "results.json").read_text())["sfm_ttr_live"]
    skipped = r["live_counters"]["skipped"].get("overflow", 0)
    assert skipped > 0
    assert r["not_published"] == {"live_overflow": skipped} and r["lost_frames"] == 0
    assert r["processed_frames"] + skipped == N_FRAMES
    assert r["warm_up_s"] > 0


def test_node_mode_runs_the_parameter_files_objective_as_it_is():
    from sfm_ttr_ros.core.pipeline import TTRConfig
    from sfm_ttr_ros.tools.benchmark import MODES as ALL_MODES
    from sfm_ttr_ros.tools.benchmark.runners import NODE_MODE, mode_config

    cfg = TTRConfig()
    cfg.refinement.loss, cfg.weight_policy = "photometric", "continue"
    assert NODE_MODE == "node_online" and NODE_MODE in ALL_MODES
    assert mode_config(NODE_MODE, cfg) is cfg


def test_live_time_line_counts_from_each_windows_last_frame():
    from types import SimpleNamespace

    from sfm_ttr_ros.tools.benchmark.live import timeline_summary, window_timeline

    arrivals = [100.0 + 0.1 * k for k in range(20)]  # 10 Hz
    ws = SimpleNamespace(index=0, refined=True, reason_key="", sfm_mapping="continued",
                         names=[f"{k:010d}" for k in range(10)],
                         started_at=101.0, finished_at=104.5,
                         timings={"predict_before": 0.2, "sfm": 0.8, "align": 0.0,
                                  "refine": 2.0})
    row = window_timeline(ws, arrivals, {"interim": 102.5, "final": 104.0})
    assert row["first_frame_arrival"] == pytest.approx(-0.9)
    assert row["sfm_mapping"] == "continued"
    assert row["closed"] == pytest.approx(0.1) and row["sfm_done"] == pytest.approx(1.1)
    assert row["refined"] == pytest.approx(3.1) and row["first_served"] == pytest.approx(1.6)
    assert row["served"] == pytest.approx(3.1) and row["since_feed_start"] == pytest.approx(2.5)
    refused = window_timeline(SimpleNamespace(**{**vars(ws), "index": 1, "refined": False,
                                                 "names": [f"{k:010d}" for k in range(10, 20)]}),
                              arrivals, {})
    assert refused["served"] is None and refused["first_served"] is None
    s = timeline_summary([row, refused])
    assert s["first_weights_s"] == pytest.approx(2.5)
    assert s["last_frame_to_weights_s"] == pytest.approx(3.1)
    assert s["last_frame_to_first_weights_s"] == pytest.approx(1.6)


def test_a_window_cut_short_by_the_end_of_the_feed_is_on_the_time_line():
    from sfm_ttr_ros.tools.benchmark.live import interim_timeline, timeline_summary

    arrivals = [10.0 + 0.1 * k for k in range(30)]
    row = interim_timeline(2, {"interim": 14.0, "names": [f"{k:010d}" for k in range(15, 30)]},
                           arrivals)
    assert row["accepted"] is None and row["served"] is None
    assert row["first_served"] == pytest.approx(14.0 - 12.9)
    assert row["since_feed_start"] == pytest.approx(4.0)
    assert timeline_summary([row])["first_weights_s"] == pytest.approx(4.0)


def test_node_online_in_virtual_time_queues_what_a_camera_sends_meanwhile():
    """``--node-rate``: frame k arrives at k / rate; each of the worker's steps advances the clock
    by its measured time, so the frames due meanwhile are queued before its next step, and
    every frame counts as served live (the node serves each one) at its feed stamp."""
    import time
    from types import SimpleNamespace

    from sfm_ttr_ros.core.frames import Frame
    from sfm_ttr_ros.tools.benchmark.runners import _push_in_virtual_time

    class SlowStream:  # takes one queued frame per step, in 20 ms
        def __init__(self):
            self.q, self.taken, self.longest = [], [], 0

        def submit(self, frame, intr):
            self.q.append(frame)

        def queued(self):
            return len(self.q)

        def step(self, timeout=None):
            self.longest = max(self.longest, len(self.q))
            time.sleep(0.02)
            self.taken.append(self.q.pop(0))
            return []

    seq = SimpleNamespace(stamps=[5.0 + i for i in range(20)], intrinsics=None,
                          frame=lambda i: Frame(index=i, image=np.zeros((2, 2, 3), np.uint8),
                                                stamp=-1.0))
    stream, run = SlowStream(), SimpleNamespace(seconds=0.0)
    _push_in_virtual_time(stream, seq, list(range(20)), 200.0, lambda outs: None, run)
    assert [f.index for f in stream.taken] == list(range(20))
    assert all(f.served_live for f in stream.taken)
    assert [f.stamp for f in stream.taken] == pytest.approx([5.0 + k / 200 for k in range(20)])
    # 20 ms a step against a frame every 5 ms: three or four frames wait at each step
    assert stream.longest >= 3 and run.seconds >= 0.02 * 20
