"""``sfm-ttr speed`` (tools/benchmark/speed.py) on a tiny drive: the naive and tuned
configurations side by side (stage shares, latency, accuracy, speed-up), the report files, the
configurations from the command's parameters, and the memory stream.

8 frames of 192x64, a tiny plug-in network, 2 refinement steps, windows of 4 frames every 2:
~15 s on 2 busy cores."""

from __future__ import annotations

import json
import math
import sys

import numpy as np
import pytest
import torch

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.tools.benchmark import speed
from sfm_ttr_ros.tools.benchmark.drive import StreetStream, load_drive
from sfm_ttr_ros.tools.benchmark.speed_report import speed_table, write_speed
from sfm_ttr_ros.tools.cli import build_parser
from sfm_ttr_ros.tools.cli_speed import speed_configs

W, H, N = 192, 64, 8
SMALL = ["window_size=4", "window_stride=2", "refinement.steps=2", "min_supervision_points=5",
         "sfm.min_points=5", "refinement.frozen_encoder_levels=0",
         "sfm.first_octave=-1"]  # (octave 0 finds too few features in 192x64 images)
TINY = "python:tiny_speed_model:factory"


def sets(values):
    return [a for v in values for a in ("--set", v)]


def args_of(*extra: str):
    return build_parser().parse_args(["speed", "--out", "unused", "--model", TINY, *extra])


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory, tiny_plugin):
    d = tmp_path_factory.mktemp("plugin")
    tiny_plugin(d / "tiny_speed_model.py", 32, 96)
    sys.path.insert(0, str(d))
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield TINY
    torch.set_num_threads(previous)
    sys.path.remove(str(d))
    sys.modules.pop("tiny_speed_model", None)


@pytest.fixture(scope="module")
def run(tiny_model, tmp_path_factory):
    cache = tmp_path_factory.mktemp("cache")
    drive = load_drive("B", 3, N, W, H, cache_dir=cache)
    again = load_drive("B", 3, N - 2, W, H, cache_dir=cache)  # a prefix
    naive_set = [a for v in SMALL for a in ("--naive-set", v)]
    configs = speed_configs(args_of(*sets(SMALL), *naive_set), (W, H))
    results = speed.run_speed(drive, configs)
    out = tmp_path_factory.mktemp("out")
    write_speed(results, out)
    return drive, again, configs, results, out


def test_drive_is_cached_and_reused(run):
    drive, again, *_ = run
    assert drive.images.shape == (N, H, W, 3) and drive.depths.shape == (N, H, W)
    assert np.array_equal(again.images, drive.images[: N - 2])
    assert again.info["cache"] == drive.info["cache"]
    assert np.all(np.diff(drive.stamps) > 0)


def test_naive_is_the_same_method_done_naively(run):
    _, _, (naive, tuned), results, _ = run
    assert (naive.name, tuned.name) == ("naive", "tuned")
    assert naive.ttr.sfm.max_image_size == W and naive.ttr.sfm.first_octave == -1
    assert not naive.feature_cache and tuned.feature_cache
    assert naive.ttr.reuse_predictions is False and tuned.ttr.reuse_predictions is True
    assert naive.model.input_height == 0 and naive.model.input_width == 0
    n, t = results["configs"]["naive"], results["configs"]["tuned"]
    # overlapping windows: tuned extracts each frame once, naive once per window it is in
    assert t["frames_extracted"] == N
    assert n["frames_extracted"] > N
    assert t["predictions_reused"] > 0 and n["predictions_reused"] == 0


def test_results_hold_the_figures(run):
    *_, results, out = run
    for name in ("naive", "tuned"):
        r = results["configs"][name]
        assert r["frames"] == N and r["published_frames"] == N and r["windows"] == 3
        assert r["refined_frames"] > 0 and r["refinement_steps"] > 0
        assert set(r["stage_shares"]) == set(r["stages_s"]) == set(speed.STAGES)
        assert math.isclose(sum(r["stage_shares"].values()), 1.0, abs_tol=1e-6)
        assert all(v >= 0 for v in r["stages_s"].values())
        assert r["stages_s"]["refinement"] > 0 and r["stages_s"]["prediction"] > 0
        assert r["stages_s"]["feature_extraction"] > 0 and r["stages_s"]["conversion"] > 0
        assert r["conversion_s"]["input_image"] > 0  # the node's decode, inside the clock
        assert r["seconds_per_frame"] == pytest.approx(r["seconds_total"] / N)
        lat = r["latency_s"]
        assert lat["n"] == 3 and 0 < lat["median"] <= lat["max"] <= r["seconds_total"]
        assert r["queued_latency_at_input_rate_s"]["max"] >= lat["max"] - 1e-4
        # 2 per frame (~/depth_refined/image and its camera_info); per window: diagnostics,
        # cloud
        assert 2 * N + 3 <= r["messages"] <= 2 * N + 6
        acc = r["accuracy"]
        assert acc["frames"] == N and 0 < acc["abs_rel"] < 1 and acc["rmse"] > 0
        assert len(acc["per_frame_abs_rel"]) == N and not acc["missing_frames"]
    c = results["comparison"]
    spf = {k: results["configs"][k]["seconds_per_frame"] for k in ("naive", "tuned")}
    assert c["speedup_naive_over_tuned"] == pytest.approx(spf["naive"] / spf["tuned"])
    assert set(c["targets"]) == {"tuned_seconds_per_frame_le_1", "speedup_ge_3",
                                 "abs_rel_within_2_percent"}
    assert results["no_ttr"]["frames"] == N
    saved = json.loads((out / "speed.json").read_text())
    assert saved["configs"]["tuned"]["stage_shares"] == pytest.approx(
        results["configs"]["tuned"]["stage_shares"])
    md = (out / "speed.md").read_text()
    assert "| naive |" in md and "| tuned |" in md and "Speed-up naive/tuned" in md
    assert "| no_ttr (reference) |" in speed_table(saved)


def test_configs_read_the_parameters_as_the_commands_do(tiny_model):
    (cfg,) = speed_configs(args_of(*sets(["refinement.steps=7", "sfm.first_octave=0",
                                          "refinement.lr=1", "refinement.sampling=nearest",
                                          "ttr.predict_batch=3", "model.input_height=64",
                                          "model.input_width=192"])), (W, H), ("tuned",))
    assert cfg.ttr.refinement.steps == 7 and cfg.ttr.sfm.first_octave == 0
    assert type(cfg.ttr.refinement.lr) is float and cfg.ttr.refinement.lr == 1.0
    assert cfg.ttr.refinement.sampling == "nearest" and cfg.ttr.predict_batch == 3
    assert (cfg.model.input_height, cfg.model.input_width) == (64, 192)
    assert cfg.stream.window_size == 15  # params/kitti.yaml
    assert cfg.model.type == TINY
    # the naive run: the paper's refinement (200 steps, whole encoder) at the lr measured best
    # for 200 steps, whatever the file or --set says; the file's windows; --naive-set over it
    (naive,) = speed_configs(args_of("--steps", "9"), (W, H), ("naive",))
    r = naive.ttr.refinement
    assert (r.steps, r.lr, r.frozen_encoder_levels) == (200, speed.NAIVE_LR, 0)
    assert naive.stream.window_size == 15 and not naive.model.channels_last
    (naive,) = speed_configs(args_of("--naive-set", "refinement.steps=3"), (W, H), ("naive",))
    assert naive.ttr.refinement.steps == 3 and "refinement.steps=3" in naive.overrides
    for bad in (["nonsense=1"], ["sfm.no_such_field=1"], ["refinement.steps=-1"], ["steps"],
                ["refinement.stepz=1"]):
        with pytest.raises(InputError):
            speed_configs(args_of(*sets(bad)), (W, H), ("tuned",))
    with pytest.raises(InputError, match="unknown configuration"):
        speed_configs(args_of("--configs", "fast"), (W, H))


def test_street_stream_is_one_continuous_street():
    from sfm_ttr_ros.data.synthetic import render_sequence, sample_scene_params

    stream = StreetStream(sample_scene_params(3, "B"), 5, 64, 32, 3)
    ref = render_sequence(sample_scene_params(3, "B"), 5, 64, 32, seed=3)
    for i, (img, stamp) in enumerate(zip(ref.images, ref.stamps, strict=True)):
        f = stream.frame(i)
        assert np.array_equal(f.image, img) and f.stamp == stamp and stream.gt(f.name) is None
    assert stream.intrinsics == ref.intrinsics
    with pytest.raises(InputError, match="in order"):
        StreetStream(sample_scene_params(3, "B"), 5, 64, 32, 3).frame(2)


def test_memory_stream(tiny_model):
    (cfg,) = speed_configs(args_of(*sets(SMALL)), (W, H), ("tuned",))
    m = speed.run_memory(cfg, frames=8, width=W, height=H, after=4, trace_every=2)
    assert m["frames"] == 8 and m["published_frames"] == 8 and m["windows"] == 3
    first, end = m["rss_after_first"], m["rss_end"]
    assert end["ru_maxrss_kib"] >= first["ru_maxrss_kib"] > 0
    assert end["VmHWM_kib"] >= first["VmHWM_kib"] > 0 and end["VmRSS_kib"] > 0
    assert m["peak_ratio"] == pytest.approx(end["VmHWM_kib"] / first["VmHWM_kib"])
    assert [t["frame"] for t in m["rss_trace"]] == [2, 4, 6, 8]
    assert isinstance(m["within_10_percent"], bool)
