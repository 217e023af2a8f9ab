"""A fault at any step of a window never costs a frame nor the stream: the real SfmTTR (a tiny
network, a stand-in SfM) behind StreamRefiner's worker step, each stage made to raise once in
the first window. Afterwards every frame received is accounted with nothing pending, the
faulted window's frames went out unrefined with their reason, and the next window refines."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import tiny_model
from test_live import fake_sfm

from sfm_ttr_ros.core import pipeline
from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.outcomes import Unrefined
from sfm_ttr_ros.core.pipeline import SfmTTR, TTRConfig
from sfm_ttr_ros.core.refinement.encoder import snapshot_encoder
from sfm_ttr_ros.core.stream.refiner import StreamRefiner
from sfm_ttr_ros.core.stream.settings import StreamSettings

INTR = Intrinsics(40.0, 40.0, 24.0, 16.0, 48, 32)
WINDOW = 3


class Once:
    """Wraps ``call``: raises on its first call (``after``: once that call is done), then
    calls through."""

    def __init__(self, call, after: bool = False):
        self.call, self.after, self.raised = call, after, False

    def __call__(self, *args, **kwargs):
        if self.raised:
            return self.call(*args, **kwargs)
        self.raised = True
        if self.after:
            self.call(*args, **kwargs)
        raise RuntimeError("injected fault")


def _refiner(outs, windows, faults):
    cfg = TTRConfig(weight_policy="continue", min_supervision_points=10)
    cfg.refinement.steps, cfg.refinement.lr = 10, 1e-3
    cfg.check.min_parallax = 0.0  # the stand-in SfM's cameras do not move
    cfg.sfm.mode = "batch"  # the stand-in replaces the batch mapper
    ttr = SfmTTR(tiny_model((32, 48), downsample=False), cfg)
    # each window's stand-in SfM from its own frames only: the same whatever came before
    ttr.sfm.reconstructor.reconstruct = lambda frames, *a, **k: fake_sfm(
        [f.name for f in frames], np.random.default_rng(int(frames[0].name)))
    return StreamRefiner(ttr, StreamSettings(window_size=WINDOW, window_stride=WINDOW),
                         on_refined=lambda o: outs.append(o), on_window=windows.append,
                         on_fault=lambda place, exc: faults.append((place, str(exc))))


def _inject(stage: str, online: StreamRefiner, monkeypatch) -> None:
    ttr, runner = online.ttr, online.stream
    if stage == "sfm":
        ttr.sfm.reconstructor.reconstruct = Once(ttr.sfm.reconstructor.reconstruct)
    elif stage == "alignment":
        monkeypatch.setattr(pipeline, "align_window", Once(pipeline.align_window))
    elif stage == "refinement":  # raises after the weights moved: they must come back
        real, calls = pipeline.refine_encoder, []

        def half_refined(model, *a, **k):
            if calls:
                return real(model, *a, **k)
            calls.append(model)
            with torch.no_grad():
                for p in model.encoder.parameters():
                    p.add_(1.0)
            raise RuntimeError("injected fault")
        monkeypatch.setattr(pipeline, "refine_encoder", half_refined)
    elif stage == "prediction":
        ttr.predictor.predict = Once(ttr.predictor.predict)
    elif stage == "output":  # the window's frames as outputs, before any is counted
        runner._out.window = Once(runner._out.window)
    elif stage == "camera_path":  # after the window's outputs are out
        runner.path.window = Once(runner.path.window)
    elif stage == "sink":  # the consumer of the outputs
        runner._out.on_output = Once(runner._out.on_output, after=True)
    elif stage == "window_sink":
        online.stream.on_window = Once(online.stream.on_window)


#: stage -> (the faulted window's frames' key: None = refined, whether the worker saw a fault)
STAGES = {
    "sfm": (Unrefined.WINDOW_ERROR, False),
    "alignment": (Unrefined.WINDOW_ERROR, False),
    "refinement": (Unrefined.WINDOW_ERROR, False),
    "prediction": (Unrefined.WINDOW_ERROR, False),
    "output": (Unrefined.WORKER_FAULT, True),
    "camera_path": (None, True),  # its frames were out, counted, before the fault
    "sink": (None, True),
    "window_sink": (None, True),
}


@pytest.mark.parametrize("stage", list(STAGES))
def test_a_fault_at_any_step_of_a_window_loses_no_frame(stage, monkeypatch, one_thread):
    outs, windows, faults = [], [], []
    online = _refiner(outs, windows, faults)
    start = snapshot_encoder(online.ttr.model)
    _inject(stage, online, monkeypatch)
    rng = np.random.default_rng(0)
    sent = 3 * WINDOW
    try:
        for i in range(sent):
            online.submit(Frame(i, rng.integers(0, 255, (32, 48, 3), np.uint8), 0.1 * i), INTR)
            while online.stream.queued():
                online.step_contained(timeout=0.0)
            if i == WINDOW - 1 and stage == "refinement":  # the weights before the window
                assert all(torch.equal(v, start[k])
                           for k, v in snapshot_encoder(online.ttr.model).items())
        online.stream.flush()  # the end of the stream
    finally:
        online.ttr.close()
    key, fault = STAGES[stage]
    assert [place for place, _ in faults] == (["worker"] if fault else [])
    c = online.stream.counters()
    assert c["pending"] == 0 and c["received"] == sent
    assert c["received"] == c["refined"] + c["unrefined"] + c["dropped"]
    names = [o.frame.name for o in outs]
    assert len(names) == len(set(names)), "a frame was counted twice"
    first = outs[:WINDOW]
    assert [o.frame.name for o in first] == [f"{i:010d}" for i in range(WINDOW)]
    assert all(o.reason_key == key and o.refined == (key is None) for o in first), \
        [(o.reason_key, o.reason) for o in first]
    if key is not None:
        assert c["unrefined_by_reason"] == {key: WINDOW}
    # the next windows refine as if nothing happened
    later = [o for o in outs if o.window is not None and o.window >= 1]
    assert len(later) == 2 * WINDOW and all(o.refined for o in later)
    assert [w.refined for w in windows if w.index >= 1] == [True, True]


def test_the_window_state_is_reset_after_a_fault(one_thread):
    """A fault while a keyframe is admitted: the frame in the worker's hands and the buffered
    keyframes go out unrefined (worker_fault), no window is left running, and the following
    frames make a whole new window."""
    outs, windows, faults = [], [], []
    online = _refiner(outs, windows, faults)
    runner = online.stream
    runner._window_if_due = Once(runner._window_if_due)
    rng = np.random.default_rng(0)
    frames = [Frame(i, rng.integers(0, 255, (32, 48, 3), np.uint8), 0.1 * i) for i in range(5)]
    try:
        for f in frames:
            online.submit(f, INTR)
            while runner.queued():
                online.step_contained(timeout=0.0)
    finally:
        online.ttr.close()
    # frame 0's admission raised: it alone was held; frames 1-3 make the next window
    assert [(o.frame.name, o.reason_key) for o in outs[:1]] == [
        ("0000000000", Unrefined.WORKER_FAULT)]
    assert runner.running_names == [] and len(faults) == 1
    assert [o.refined for o in outs[1:]] == [True] * WINDOW
    c = runner.counters()
    assert c["pending"] == 1 and c["received"] == 5  # frame 4 waits for its window

