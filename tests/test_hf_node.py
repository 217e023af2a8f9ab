"""The refiner node running a transformers depth model: ``model_type: hf`` with
``model_path`` = the tiny randomly initialised Depth Anything of test_hf_model, built by the node
from its parameters, in an in-process ROS 2 graph (test_node's Graph: own context, DDS on
localhost, a random domain) and fed generated street frames through DDS.

The directory is loaded offline: nothing is downloaded. With random weights, SfM on the
generated frames may or may not give the window enough supervision: the test asserts the node's
exact frame accounting, not a particular outcome."""

from __future__ import annotations

import os

os.environ["HF_HUB_OFFLINE"] = "1"  # before transformers / huggingface_hub read it

import numpy as np  # noqa: E402
import pytest  # noqa: E402

pytest.importorskip("transformers", reason="extra 'hf' not installed")
pytest.importorskip("rclpy")

import test_hf_model  # noqa: E402
import test_node  # noqa: E402
from test_node import FRAME_ID, HEIGHT, WIDTH, counts_add_up, wait_for  # noqa: E402

from sfm_ttr_ros.core.models.hf import HFDepthModel  # noqa: E402

model_dirs, graph_factory = test_hf_model.model_dirs, test_node.graph_factory  # fixtures shared
sequence = test_node.sequence
pytestmark = pytest.mark.ros

WINDOW, NUM_FRAMES = 4, 8  # two windows


def stamp(msg) -> tuple[int, int]:
    return msg.header.stamp.sec, msg.header.stamp.nanosec


@pytest.mark.slow
def test_node_runs_a_transformers_model_from_a_local_directory(graph_factory, model_dirs,
                                                               sequence):
    g = graph_factory(own_model=True, model_type="hf", model_path=model_dirs["da"],
                      window_size=WINDOW, window_stride=WINDOW,
                      **{"refinement.frozen_encoder_levels": 0})  # the tiny model's 2 maps
    model = g.refiner.ttr.model
    assert isinstance(model, HFDepthModel) and model.output_kind == "relative_inverse_depth"
    sent = []
    for i, (rgb, t) in enumerate(zip(sequence.images[:NUM_FRAMES],
                                     sequence.stamps[:NUM_FRAMES], strict=True)):
        g.send_info(sequence.intrinsics, t)
        sent.append(g.send_image(rgb, t))
        # live: every frame at once, whatever the worker is doing (one at a time: no overflow)
        wait_for(lambda n=i + 1: len(g.live) == n, 30, f"live depth {i}")
    assert [stamp(m) for m in g.live] == [stamp(m) for m in sent]
    for m in g.live:
        assert m.header.frame_id == FRAME_ID
        assert (m.encoding, m.width, m.height) == ("32FC1", WIDTH, HEIGHT)
        assert np.isfinite(np.frombuffer(m.data, np.float32)).mean() > 0.99

    # ~/depth_refined: every frame once more when its window is done, refined or not
    wait_for(lambda: len(g.depths) == NUM_FRAMES, 120, "every frame on ~/depth_refined")
    assert sorted(stamp(m) for m in g.depths) == [stamp(m) for m in sent]
    for m in g.depths:
        assert m.header.frame_id == FRAME_ID
        assert (m.encoding, m.width, m.height) == ("32FC1", WIDTH, HEIGHT)
        depth = np.frombuffer(m.data, np.float32)
        assert np.isfinite(depth).mean() > 0.99 and np.nanmin(depth) > 0

    # two windows, or one when the worker fell a window behind (SIFT on admission, a loaded
    # machine): keyframe_policy newest then skips the older frames as stale, counted
    windows = list(g.refiner.stream.windows)
    assert windows, "no window ran"
    d = wait_for(lambda: (lambda v: v if v.get("frames_pending") == "0"
                          and v.get("live.pending") == "0"
                          and int(v.get("windows_ok", 0)) + int(v.get("windows_failed", 0))
                          == len(windows) else None)(g.last_diag()),
                 15, "final diagnostics")
    assert counts_add_up(d)
    stale = int(d.get("unrefined.stale", 0))
    assert sum(w.new_frames for w in windows) + stale == NUM_FRAMES, (windows, d)
    ok = sum(w.refined for w in windows)
    assert (int(d["windows_ok"]), int(d["windows_failed"])) == (ok, len(windows) - ok)
    assert int(d["windows_ok"]) + int(d["windows_failed"]) >= 1  # the hf model's windows ran
    assert (d["frames_received"], d["frames_dropped"]) == (str(NUM_FRAMES), "0")
    refined = sum(w.new_frames for w in windows if w.refined)
    assert int(d["frames_refined"]) == refined
    assert int(d["frames_unrefined"]) == NUM_FRAMES - refined == sum(
        int(v) for k, v in d.items() if k.startswith("unrefined."))
    assert (d["live.received"], d["live.published"], d["live.skipped"]) == (
        str(NUM_FRAMES), str(NUM_FRAMES), "0")
    assert d["serving.updates"] == str(ok)  # each refined window's weights went live
    assert d["faults"] == "0" and g.refiner.diagnostics.faults == {}
    for w in windows:  # a refined window ran every step and lowered its loss; else a reason
        if w.refined:
            assert w.steps_done == test_node.FAST["refinement.steps"], w
            assert w.loss_after < w.loss_before, w
        else:
            assert w.reason_key and w.reason, w
    assert g.refiner.worker_alive
