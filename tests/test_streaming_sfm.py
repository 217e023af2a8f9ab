"""Streaming SfM (core/sfm/frontend.py, map_cache.py, streaming_map.py, source.py; compared with
the batch reconstructor by tests/streaming_compare.py): the front end's matcher against
pycolmap's, windows continued on one map (same SfmResult as the batch reconstructor, one scale
across windows), the fresh mapping with its reason, the store that drops frames, bad input, the
SfM source of each ``sfm.mode``.

Depth error and scale as in tests/test_sfm.py: s = median(D_gt / D_sfm) per window.
"""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import cv2
import numpy as np
import pycolmap
import pytest
from streaming_compare import compare_streaming_with_batch

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import Frame
from sfm_ttr_ros.core.sfm.frontend import sift_matches
from sfm_ttr_ros.core.sfm.result import SfmResult
from sfm_ttr_ros.core.sfm.sfm_config import SfmConfig
from sfm_ttr_ros.core.sfm.source import (
    BatchSfmSource,
    StreamingSfmSource,
    make_sfm_source,
    reconfigure_sfm_source,
)
from sfm_ttr_ros.core.sfm.streaming_map import StreamingSfm

W, H = 640, 192  # the smallest size tests/test_sfm.py found every window registered at
WINDOW, OVERLAP = 4, 3
# batch unless a test asks for streaming; first_octave 0: ~3x faster SIFT
SFM = SfmConfig(mode="batch", first_octave=0, overlap=OVERLAP)


def _frames(seed: int, num: int, first_index: int = 0):
    from sfm_ttr_ros.data.synthetic import make_sequence

    seq = make_sequence(seed=seed, domain="A", num_frames=num, width=W, height=H)
    frames = [Frame(first_index + i, im, stamp=s)
              for i, (im, s) in enumerate(zip(seq.images, seq.stamps, strict=True))]
    return SimpleNamespace(frames=frames, intr=seq.intrinsics,
                           gt={f.name: d for f, d in zip(frames, seq.depths, strict=True)})


@pytest.fixture(scope="module")
def street():
    return _frames(0, 3 * WINDOW)


@pytest.fixture(scope="module")
def compared(street):
    """Three windows of 4 frames side by side, streamed and batch, interleaved."""
    return compare_streaming_with_batch(street.frames, street.intr, WINDOW, street.gt, SFM)


def test_sift_matches_are_pycolmaps(street):
    """The front end's numpy matcher gives exactly pycolmap's SIFT matches (same options)."""
    opts = pycolmap.FeatureExtractionOptions()
    opts.sift.first_octave = 0
    extractor = pycolmap.FeatureExtractor.create(opts, pycolmap.Device.cpu)
    descs = [extractor.extract_from_uint8_array(cv2.cvtColor(f.image, cv2.COLOR_RGB2GRAY))[1]
             for f in street.frames[:3]]
    matcher = pycolmap.FeatureMatcher.create(pycolmap.FeatureMatchingOptions(),
                                             pycolmap.Device.cpu)
    for other in descs[1:]:
        ours = sift_matches(descs[0].data, other.data)
        theirs = matcher.match(None, descs[0], None, other)
        assert len(ours) > 50
        assert {tuple(m) for m in ours.tolist()} == {tuple(m) for m in theirs.tolist()}
    assert sift_matches(descs[0].data[:0], descs[1].data).shape == (0, 2)


def test_windows_continue_one_map_at_one_scale(compared):
    """Window 1 is mapped afresh (no map), windows 2 and 3 continue it: every frame
    registered, depth as accurate as the batch's, and the scale of consecutive windows the
    same (the batch's windows each have their own)."""
    stream, batch = compared["stream"], compared["batch"]
    assert [w["mapping"][0] for w in stream] == ["fresh", "continued", "continued"]
    assert (compared["continuations"], compared["fresh_mappings"]) == (2, 1)
    for s, b in zip(stream, batch, strict=True):
        assert s["ok"] and b["ok"]
        assert s["registered"] == WINDOW
        assert s["points"] >= 100
        assert s["reprojection_error"] < 1.0
        assert s["depth_error"] < 0.03
        assert s["depth_error"] < 2 * b["depth_error"] + 0.005
    for ratio in compared["stream_scale_ratios"]:
        assert abs(ratio - 1) < 0.03
    assert stream[1]["map_on_admit"] > 0  # continued windows registered frames as they came
    assert compared["frontend_mean"]["total"] > 0


def test_window_result_is_the_batch_result_type(compared, street):
    """What a window gets is an SfmResult of its own frames: D_sfm > 0, p_lj inside the
    image, r_lj small, only points its frames observe, a colour per point."""
    results = compared["stream_results"]
    for k, result in enumerate(results):
        assert isinstance(result, SfmResult)
        names = {f.name for f in street.frames[k * WINDOW:(k + 1) * WINDOW]}
        assert set(result.frames) == names
        seen = set()
        for obs in result.frames.values():
            assert (obs.depths > 0).all()
            assert (obs.pixels >= -0.5).all() and (obs.pixels[:, 0] < W).all()
            assert np.median(obs.reproj_errors) < 1.0
            seen.update(obs.point_ids.tolist())
        assert set(result.point_ids.tolist()) == seen
        assert result.points_rgb.shape == (result.num_points, 3)
        assert {"frontend", "map_on_admit", "map"} <= set(result.timings)


def test_front_end_drops_frames_that_left_every_window(compared):
    """After the last window only the map's anchors and the next frames' partners are held."""
    assert compared["frames_held"] <= OVERLAP
    per_frame = compared["frontend"]
    assert len(per_frame) == 3 * WINDOW
    assert all(t.pairs <= OVERLAP and t.verified <= t.pairs for t in per_frame)
    assert per_frame[0].pairs == 0 and per_frame[-1].verified >= 1


def test_a_continuation_that_fails_maps_afresh_with_the_reason(street):
    """A window from another scene cannot continue the map: it is mapped afresh, and the
    result says why; the map then continues from the fresh one."""
    other = _frames(3, WINDOW, first_index=100)
    with StreamingSfm(SFM) as sfm:
        assert sfm.reconstruct(street.frames[:WINDOW], street.intr).ok
        result = sfm.reconstruct(other.frames, street.intr)  # one camera
        mode, reason = result.mapping, result.mapping_reason
        assert result.ok and mode == "fresh"
        assert "continuation" in reason
        assert result.attempts[0] == {"mode": "continue", "rejected": reason}
        assert all(a["mode"] == "fresh" for a in result.attempts[1:])
        assert sfm.rec is not None and sfm.rec.num_reg_images() == OVERLAP


def test_a_fresh_mapping_takes_the_maps_last_frames_as_anchors(street, monkeypatch):
    """A window mapped afresh is mapped with the map's last frames before it: they come back
    as the result's ``anchors`` (what the camera's path chains through), never among its
    frames, points or counts."""
    from sfm_ttr_ros.core.sfm.streaming_map import FRESH_ANCHORS

    first, second = street.frames[:WINDOW], street.frames[WINDOW:2 * WINDOW]
    with StreamingSfm(SFM) as sfm:
        assert sfm.reconstruct(first, street.intr).ok
        monkeypatch.setattr(sfm, "_fit_reason", lambda result, n: "forced for the test")
        result = sfm.reconstruct(second, street.intr)
    names = {f.name for f in second}
    assert (result.mapping, result.mapping_reason) == ("fresh", "forced for the test")
    assert result.ok
    assert set(result.frames) <= names and result.num_frames == WINDOW
    expected = [f.name for f in first][-min(FRESH_ANCHORS, OVERLAP):]
    assert set(result.anchors) and set(result.anchors) <= set(expected)
    seen = np.unique(np.concatenate([o.point_ids for o in result.frames.values()]))
    assert set(result.point_ids.tolist()) <= set(seen.tolist())


def test_the_streaming_sfm_runs_in_a_process_of_its_own(street, caplog):
    """pycolmap keeps the GIL in its extractor and mapper, which stalled live serving: the
    streaming source runs the StreamingSfm in a child process, with the results it gives in
    this one, and its log lines come back to this process's loggers. A child that dies: the
    call raises SfmProcessError, the next call starts a fresh child (the map is lost: its
    window maps afresh), counted in ``restarts``."""
    import logging
    import os
    import signal

    from sfm_ttr_ros.core.sfm.sfm_process import SfmProcessError

    cfg = dataclasses.replace(SFM, mode="streaming", num_threads=1)
    windows = [street.frames[k * WINDOW:(k + 1) * WINDOW] for k in range(3)]
    with StreamingSfm(cfg) as here:
        want = [here.reconstruct(w, street.intr) for w in windows[:2]]
    caplog.set_level(logging.INFO)  # the child takes this process's level when it starts
    caplog.clear()
    source = StreamingSfmSource(cfg)
    try:
        assert source.streaming.pid is None  # started by the warm-up (or the first call)
        source.warm_up()
        child = source.streaming.pid
        assert child is not None and child != os.getpid()
        got = [source.reconstruct(w, street.intr)[0] for w in windows[:2]]
        assert [r.getMessage() for r in caplog.records
                if r.name == "sfm_ttr_ros.core.sfm.streaming_map"] == [
            f"window {windows[0][0].name}..{windows[0][-1].name} mapped afresh: no map to "
            "continue"]
        for g, w in zip(got, want, strict=True):
            assert (g.ok, g.mapping, g.num_registered, g.num_points) == (
                w.ok, w.mapping, w.num_registered, w.num_points)
            assert g.reprojection_error == w.reprojection_error
            for name, obs in w.frames.items():
                np.testing.assert_array_equal(g.frames[name].depths, obs.depths)
        assert source.counters()["sfm_streaming"] == {"continued": 1, "fresh": 1,
                                                      "admitted_unmapped": 0,
                                                      "process_restarts": 0}
        assert source.frames_extracted == 2 * WINDOW
        source.streaming.afresh(cfg)  # as when an assumed focal length settles: same child
        assert source.streaming.pid == child and source.streaming.held_frames() == []
        assert source.counters()["sfm_streaming"]["fresh"] == 1  # the counts go on
        assert source.frames_extracted == 2 * WINDOW
        os.kill(child, signal.SIGKILL)
        with pytest.raises(SfmProcessError, match="map is lost"):
            source.admit(windows[2][0], street.intr)
        third, _ = source.reconstruct(windows[2], street.intr)
        assert third.ok and third.mapping == "fresh"
        assert source.streaming.restarts == 1 and source.streaming.pid not in (None, child)
        assert source.frames_extracted == 3 * WINDOW
        assert source.counters()["sfm_streaming"] == {"continued": 1, "fresh": 2,  # kept
                                                      "admitted_unmapped": 0,
                                                      "process_restarts": 1}
    finally:
        source.close()
    assert source.streaming.pid is None


def test_other_intrinsics_start_the_stream_afresh(street):
    intr2 = type(street.intr)(street.intr.fx * 1.1, street.intr.fy * 1.1, street.intr.cx,
                              street.intr.cy, W, H)
    with StreamingSfm(SFM) as sfm:
        sfm.admit(street.frames[0], street.intr)
        generation = sfm.frontend.generation
        sfm.admit(street.frames[1], intr2)
        assert sfm.frontend.generation == generation + 1
        assert list(sfm.frontend.features) == [street.frames[1].name]
        assert sfm.frontend.pairs == {}


def test_bad_input_is_an_input_error(street):
    with StreamingSfm(SFM) as sfm:
        with pytest.raises(InputError):
            sfm.admit(Frame(0, np.zeros((10, 10, 3), np.uint8)), street.intr)
        with pytest.raises(InputError):
            compare_streaming_with_batch(street.frames[:3], street.intr, WINDOW)
        assert not sfm.reconstruct(street.frames[:1], street.intr).ok


# -- sfm.mode streaming through the stream (WindowRunner + SfmTTR) ------------------------
def _stream_ttr(mode: str):
    from conftest import tiny_model

    from sfm_ttr_ros.core.pipeline import SfmTTR
    from sfm_ttr_ros.core.refinement.refinement_config import RefinementConfig
    from sfm_ttr_ros.core.window_io import TTRConfig

    cfg = TTRConfig(sfm=dataclasses.replace(SFM, mode=mode),
                    refinement=RefinementConfig(steps=4))
    return SfmTTR(tiny_model(), cfg)


def _run_stream(ttr, frames, intr, admitted: list | None = None):
    """Every frame pushed through a WindowRunner of 4-frame windows side by side; with
    ``admitted``, the frames the streaming SfM held when each window began."""
    from sfm_ttr_ros.core.stream.diagnostics import StreamDiagnostics
    from sfm_ttr_ros.core.stream.window_runner import StreamSettings, WindowRunner

    stream = WindowRunner(ttr, StreamSettings(window_size=WINDOW, window_stride=WINDOW,
                                                 keyframe_policy="all", idle_flush_s=0.0))
    if admitted is not None:
        reconstruct = ttr.sfm.reconstruct

        def spy(window, intrinsics):
            admitted.append(set(ttr.sfm.streaming.held_frames()))
            return reconstruct(window, intrinsics)
        ttr.sfm.reconstruct = spy
    outs = []
    for f in frames:
        outs += stream.push(f, intr)
    outs += stream.flush()
    return stream, outs, StreamDiagnostics(stream).values()


@pytest.fixture(scope="module")
def streamed(street):
    """Two windows of the street, then a window of another scene (its stamps after them):
    the third cannot continue the map."""
    other = _frames(3, WINDOW, first_index=100)
    last = street.frames[2 * WINDOW - 1].stamp
    moved = [Frame(f.index, f.image, stamp=last + 0.1 * (k + 1))
             for k, f in enumerate(other.frames)]
    ttr, admitted = _stream_ttr("streaming"), []
    try:
        stream, outs, diag = _run_stream(ttr, street.frames[:2 * WINDOW] + moved, street.intr,
                                         admitted)
        return SimpleNamespace(windows=list(stream.windows), outs=outs, diag=diag,
                               counters=stream.counters(), admitted=admitted,
                               streaming=ttr.sfm.streaming, names=[f.name for f in moved])
    finally:
        ttr.close()


def test_streaming_mode_windows_refine_on_the_carried_map(streamed):
    """sfm.mode streaming through the stream: each keyframe admitted when the stream takes it
    (a window's frames are all held before its SfM runs), windows refined, the second window
    continues the first's map, frames registered as they arrived; counted on /diagnostics."""
    w = streamed.windows
    assert len(w) == 3 and len(streamed.outs) == 3 * WINDOW
    assert [x.sfm_mapping for x in w] == ["fresh", "continued", "fresh"]
    assert w[0].sfm_mapping_reason == "no map to continue" and w[1].sfm_mapping_reason == ""
    assert w[0].refined and w[1].refined
    assert w[1].registered == WINDOW
    assert w[1].timings["sfm_map_on_admit"] > 0  # registered into the map as they came
    for window, held in zip(w, streamed.admitted, strict=True):
        assert set(window.names) <= held  # admitted before the window's SfM began
    d = streamed.diag
    assert (d["sfm.windows_continued"], d["sfm.windows_fresh"]) == (1, 2)
    assert d["sfm.admitted_unmapped"] == 0 and d["sfm.waiting_for_features"] == 0
    assert d["sfm.process_restarts"] == 0
    assert d["last_window.sfm_mapping"] == "fresh"
    assert streamed.counters["sfm_ahead"]["started"] == 0  # nothing begun ahead


def test_streaming_mode_a_bad_continuation_maps_afresh_with_its_reason(streamed):
    """The other scene's window cannot continue the street's map: mapped afresh, the reason
    in the window's record and on /diagnostics, and it is still reconstructed."""
    third = streamed.windows[2]
    assert third.names == streamed.names
    assert "continuation" in third.sfm_mapping_reason
    assert streamed.diag["last_window.sfm_mapping_reason"] == third.sfm_mapping_reason
    assert third.registered >= 2
    assert third.result.summary()["sfm_mapping"] == ["fresh", third.sfm_mapping_reason]


def test_batch_mode_is_the_batch_reconstructors(street):
    """sfm.mode batch (the default): no streaming SfM, nothing admitted, and each window's
    reconstruction is the batch reconstructor's own, called once per window with exactly the
    window's frames after its last frame (today's path)."""
    ttr = _stream_ttr("batch")
    calls, results = [], []
    reconstruct = ttr.sfm.reconstructor.reconstruct

    def spy(window, intrinsics):
        calls.append([f.name for f in window])
        results.append(reconstruct(window, intrinsics))
        return results[-1]
    ttr.sfm.reconstructor.reconstruct = spy
    try:
        assert isinstance(ttr.sfm, BatchSfmSource)
        assert not ttr.sfm.admit(street.frames[0], street.intr)
        stream, _, diag = _run_stream(ttr, street.frames[:2 * WINDOW], street.intr)
    finally:
        ttr.close()
    assert calls == [w.names for w in stream.windows]
    assert all(w.result.sfm is r for w, r in zip(stream.windows, results, strict=True))
    assert all(w.sfm_mapping == "" == w.sfm_mapping_reason for w in stream.windows)
    assert stream.counters()["sfm_streaming"] == {}
    assert not any(k.startswith("sfm.") for k in diag)
    assert all(w.refined for w in stream.windows)


def test_sfm_mode_is_validated():
    with pytest.raises(InputError, match="sfm.mode"):
        SfmConfig(mode="online")
    with pytest.raises(InputError, match="sfm.features colmap"):
        SfmConfig(mode="streaming", features="torch")


def test_one_source_per_mode_made_anew_when_the_mode_changes(street, tmp_path):
    """The factory makes the source ``sfm.mode`` says; options of the same mode keep the source,
    another mode closes it and makes one of that mode (workspace and ``nice`` carried over),
    also through the pipeline's set_config."""
    zeros = {"started": 0, "used": 0, "discarded": 0}
    batch = make_sfm_source(SFM, tmp_path)
    batch.nice = 5
    assert isinstance(batch, BatchSfmSource)
    assert reconfigure_sfm_source(batch, dataclasses.replace(SFM, seed=3)) is batch
    assert batch.config.seed == batch.reconstructor.config.seed == 3
    streaming = reconfigure_sfm_source(batch, dataclasses.replace(SFM, mode="streaming"))
    assert isinstance(streaming, StreamingSfmSource)
    assert (streaming.nice, streaming.workspace) == (5, tmp_path)
    assert not batch.prefetch(street.frames[:WINDOW], street.intr)  # closed: nothing ahead
    assert not streaming.prefetch(street.frames[:WINDOW], street.intr)
    assert streaming.counters() == {"sfm_ahead": zeros, "sfm_streaming": {
        "continued": 0, "fresh": 0, "admitted_unmapped": 0, "process_restarts": 0}}
    back = reconfigure_sfm_source(streaming, SFM)
    assert isinstance(back, BatchSfmSource)
    assert back.counters() == {"sfm_ahead": zeros, "sfm_streaming": {}}
    back.close()
    ttr = _stream_ttr("batch")
    try:
        ttr.set_config(dataclasses.replace(ttr.config, sfm=dataclasses.replace(SFM,
                                                                             mode="streaming")))
        assert isinstance(ttr.sfm, StreamingSfmSource)
    finally:
        ttr.close()


def test_the_stream_admits_keyframes_only_while_no_frame_waits():
    """A keyframe's front end costs more than a 10-Hz frame interval on 2 cores: admitted as
    they arrive, the worker fell behind and the keyframe rule skipped every window's frames.
    The feed admits buffered keyframes oldest first while the queue is empty, each once; the
    window admits the rest itself."""
    from sfm_ttr_ros.core.stream.sfm_feed import SfmFeed

    admitted: list[str] = []
    waiting = [0]

    def admit(frame, intr):  # the streaming source: takes every keyframe
        admitted.append(frame.name)
        return True
    ttr = SimpleNamespace(sfm=SimpleNamespace(admit=admit, retain=lambda names: None))
    feed = SfmFeed(ttr, SimpleNamespace(queued=lambda: waiting[0]), lambda k, m: None)
    frames = [Frame(i, np.zeros((4, 4, 3), np.uint8)) for i in range(4)]
    waiting[0] = 3
    feed.admit_while_idle(frames[:2], None)
    assert admitted == []  # frames wait: nothing admitted now
    waiting[0] = 0
    feed.admit_while_idle(frames[:3], None)
    assert admitted == [f.name for f in frames[:3]]
    feed.retain([frames[2].name])  # 0 and 1 left every future window
    feed.admit_while_idle(frames[2:], None)
    assert admitted == [f.name for f in frames]  # 2 not twice
    asked: list[str] = []  # the batch source: takes none (the window does it all)
    ttr.sfm = SimpleNamespace(admit=lambda f, intr: asked.append(f.name) or False,
                              retain=lambda names: None)
    feed.admit_while_idle([Frame(9, frames[0].image), Frame(10, frames[0].image)], None)
    assert len(admitted) == 4 and asked == [Frame(9, frames[0].image).name]  # asked once
