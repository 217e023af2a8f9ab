"""The refinement step on static, padded buffers (core/refinement/graph_step.py): what a CUDA
graph captures and replays must give the eager loop's numbers. On the CPU: the same body run
eagerly ("static") against today's eager step, from the same weights and seed; the fallbacks
and how they are reported; the replay loop with a stand-in graph."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import tiny_model
from test_frozen_stages import mobile
from test_refinement_loss import INPUT, N_FRAMES, photometric_frames, supervision

import sfm_ttr_ros.core.refinement.graph_cache as graph_cache
import sfm_ttr_ros.core.refinement.graph_step as graph_step
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.refinement.encoder import refine_encoder
from sfm_ttr_ros.core.refinement.refinement_config import RefinementConfig
from sfm_ttr_ros.core.refinement.supervision import FrameSupervision
from sfm_ttr_ros.data.synthetic import render_sequence, sample_scene_params

#: Tolerance of the static step's losses against the eager step's: the two differ only in the
#: order of Eq. (5)'s sum over the (padded) points (measured: <= 1.3e-7 relative over 6 steps).
RTOL = 1e-5
STEPS = 5


@pytest.fixture(autouse=True)
def no_kept_graphs():
    """Each test starts without graphs or refusals kept by another."""
    graph_cache.forget_captures()
    yield
    graph_cache.forget_captures()


@pytest.fixture(scope="module")
def drive(one_thread):
    seq = render_sequence(sample_scene_params(0, "A"), N_FRAMES, 256, 80, blur_sigma=0.8)
    return seq, [f"{i:010d}" for i in range(N_FRAMES)]


def uneven(sup: list[FrameSupervision]) -> list[FrameSupervision]:
    """Each frame with its own number of points (300, 263, 226, 189): padding is needed."""
    for k, s in enumerate(sup):
        n = len(s) - 37 * k
        s.pixels, s.target, s.weights = s.pixels[:n], s.target[:n], s.weights[:n]
    return sup


def refine(drive, mode: str, loss: str, registered=None, **kw):
    seq, names = drive
    model = tiny_model(INPUT, batch_norm=1)
    reg = set(names) if registered is None else registered
    ph = photometric_frames(model, seq, names, registered=reg)
    cfg = RefinementConfig(steps=STEPS, lr=1e-3, loss=loss, step_mode=mode, **kw)
    res = refine_encoder(model, uneven(supervision(seq, names)), cfg, photometric=ph)
    return model, res


def state(model) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in model.encoder.state_dict().items()}


@pytest.mark.parametrize("loss, kw", [
    ("sfm", {}), ("sfm", {"bn_mode": "train"}), ("hybrid", {}), ("hybrid", {"bn_mode": "train"}),
    ("photometric", {})])
def test_static_step_equals_the_eager_step(drive, loss, kw):
    """Frames 0, 1, 3 registered in the hybrid: frame 3 has no registered neighbour, so its
    photometric term is the zero-weighted stand-in, and frames have 1 or 2 sources."""
    _, names = drive
    reg = {names[0], names[1], names[3]} if loss == "hybrid" else None
    m_eager, eager = refine(drive, "eager", loss, reg, **kw)
    m_static, static = refine(drive, "static", loss, reg, **kw)
    assert (eager.step_mode, static.step_mode) == ("eager", "static")
    assert eager.steps_done == static.steps_done == STEPS
    assert static.loss_history == pytest.approx(eager.loss_history, rel=RTOL)
    a, b = state(m_eager), state(m_static)
    for k in a:
        torch.testing.assert_close(b[k], a[k], rtol=RTOL, atol=1e-6)
    # deterministic for a seed on the CPU
    assert refine(drive, "static", loss, reg, **kw)[1].loss_history == static.loss_history


def test_static_step_with_frozen_leading_stages():
    """Frozen encoder levels: the step input is the cached (output, features) of the frozen
    stages, a nested structure of tensors in the static buffers."""
    rng = np.random.default_rng(0)
    sup = [FrameSupervision(f"{i:04d}", rng.integers(0, 255, (64, 96, 3), dtype=np.uint8),
                            np.c_[rng.uniform(0, 95, n), rng.uniform(0, 63, n)],
                            rng.uniform(2.0, 30.0, n), rng.uniform(0.2, 1.0, n))
           for i, n in enumerate((200, 150, 120))]
    out = {}
    for mode in ("eager", "static"):
        model = mobile()
        cfg = RefinementConfig(steps=STEPS, lr=1e-3, loss="sfm", frozen_encoder_levels=2,
                               step_mode=mode)
        out[mode] = refine_encoder(model, sup, cfg).loss_history
    assert out["static"] == pytest.approx(out["eager"], rel=RTOL)


def test_auto_is_eager_on_the_cpu(drive):
    """The default ("auto") runs today's eager loop on the CPU, and says why."""
    _, eager = refine(drive, "eager", "hybrid")
    _, auto = refine(drive, "auto", "hybrid")
    assert auto.step_mode == "eager" and auto.step_mode_reason == "not on CUDA (cpu)"
    assert auto.loss_history == eager.loss_history  # bit for bit: the same loop
    assert RefinementConfig().step_mode == "auto"
    with pytest.raises(InputError, match="step_mode"):
        RefinementConfig(step_mode="graph")


class _FakeGraph:
    """A stand-in CUDA graph on the CPU: replay runs the captured body. The gradients are None
    before each replay as in a real graph, whose backward pass writes them afresh (the capture
    began with them None) instead of adding to them."""

    def __init__(self, body, params):
        self.body, self.params = body, list(params)
        self.replays = 0

    def replay(self):
        self.replays += 1
        for p in self.params:
            p.grad = None
        self.body()


def _on_cuda(monkeypatch):
    """plan_step_mode as if the model were on CUDA."""
    real = graph_step.plan_step_mode

    def plan(model, frames, cfg):
        mode, why = real(model, frames, cfg)
        return ("graph", "") if why.startswith("not on CUDA") else (mode, why)

    import sfm_ttr_ros.core.refinement.encoder as encoder
    monkeypatch.setattr(encoder, "plan_step_mode", plan)


def test_the_replay_loop_with_a_stand_in_graph(drive, monkeypatch):
    """The graph path's control flow on the CPU: warm-up steps, one capture, then each step
    loads its frame and replays; the losses read once at the end equal the eager loop's;
    on_step sees every step."""
    graphs = []
    seq, names = drive
    model = tiny_model(INPUT, batch_norm=1)

    def capture(body, device, stream=None):
        graphs.append(_FakeGraph(body, model.parameters()))
        return graphs[-1]

    _on_cuda(monkeypatch)
    monkeypatch.setattr(graph_step, "capture_step", capture)
    seen = []
    cfg = RefinementConfig(steps=8, lr=1e-3, loss="hybrid")
    res = refine_encoder(model, uneven(supervision(seq, names)), cfg,
                         photometric=photometric_frames(model, seq, names), on_step=seen.append)
    assert (res.step_mode, res.step_mode_reason) == ("graph", "")
    assert len(graphs) == 1 and graphs[0].replays == 8 - graph_step.GRAPH_WARM_UP_STEPS
    assert seen == list(range(1, 9))
    m_eager = tiny_model(INPUT, batch_norm=1)
    eager = refine_encoder(m_eager, uneven(supervision(seq, names)),
                           RefinementConfig(steps=8, lr=1e-3, loss="hybrid", step_mode="eager"),
                           photometric=photometric_frames(m_eager, seq, names))
    assert res.loss_history == pytest.approx(eager.loss_history, rel=RTOL)


def test_a_refused_capture_falls_back_and_says_so(drive, monkeypatch):
    """A capture that raises (here the CPU build's CUDAGraph itself): the remaining steps run the
    same body eagerly, every step is done, and the result names the path and the reason."""
    _on_cuda(monkeypatch)
    _, res = refine(drive, "auto", "sfm")
    _, eager = refine(drive, "eager", "sfm")
    assert res.step_mode == "static" and res.step_mode_reason.startswith("capture failed: ")
    assert res.steps_done == STEPS
    assert res.loss_history == pytest.approx(eager.loss_history, rel=RTOL)


def test_why_a_window_is_not_captured(drive):
    """The reasons of plan_step_mode: asked for eager, LoRA, off CUDA, frames of different
    shapes (then even "static" runs eagerly)."""
    from sfm_ttr_ros.core.refinement.objective import frame_terms

    seq, names = drive
    model = tiny_model(INPUT)
    cfg = RefinementConfig(steps=STEPS, loss="sfm")
    terms = [frame_terms(model, s, 0, cfg, None) for s in supervision(seq, names)]
    plan = graph_step.plan_step_mode
    assert plan(model, terms, RefinementConfig(step_mode="eager")) == ("eager", "step_mode eager")
    assert plan(model, terms, RefinementConfig(trainable="lora"))[1].startswith("LoRA")
    assert plan(model, terms, cfg) == ("eager", "not on CUDA (cpu)")
    assert plan(model, terms, RefinementConfig(step_mode="static"))[0] == "static"
    terms[1].x = torch.zeros(1, 3, 32, 64)
    mode, why = plan(model, terms, RefinementConfig(step_mode="static"))
    assert mode == "eager" and "differ in shape" in why


def test_step_inputs_of_any_structure():
    """A staged encoder's cached input may nest tuples, lists, named tuples and constants (a
    transformer's patch grid): the tensors go to buffers, the rest is kept as it is."""
    from collections import namedtuple

    Grid = namedtuple("Grid", "tokens size")
    x = (torch.ones(2), [torch.zeros(3), 7, "patch", None], Grid(torch.ones(1, 4), (3, 5)))
    leaves = graph_step._leaves(x)
    assert [tuple(t.shape) for t in leaves] == [(2,), (3,), (1, 4)]
    again = graph_step._rebuild(x, iter([t + 1 for t in leaves]))
    assert torch.equal(again[0], torch.full((2,), 2.0)) and again[1][1:] == [7, "patch", None]
    assert isinstance(again[2], Grid) and again[2].size == (3, 5)
    other = (torch.ones(2), [torch.zeros(3), 8, "patch", None], Grid(torch.ones(1, 4), (3, 5)))
    assert graph_step._signature(x) != graph_step._signature(other)


def _stand_in_captures(monkeypatch, model, fail: bool = False) -> list:
    """capture_step replaced by a stand-in graph (or a refusal); the calls listed."""
    calls = []

    def capture(body, device, stream=None):
        calls.append(stream)
        if fail:
            raise RuntimeError("operation not permitted when stream is capturing")
        return _FakeGraph(body, model.parameters())

    monkeypatch.setattr(graph_step, "capture_step", capture)
    return calls


def test_one_graph_serves_every_window_of_a_layout(drive, monkeypatch):
    """Two windows from the same start weights (restored in place, as the weight policy does):
    the second replays the first's graph from its first step (no warm-up, no capture), with
    Adam's state reset: its losses are the eager loop's of a fresh start."""
    from sfm_ttr_ros.core.refinement.encoder import restore_encoder, snapshot_encoder

    seq, names = drive
    model = tiny_model(INPUT, batch_norm=1)
    calls = _stand_in_captures(monkeypatch, model)
    _on_cuda(monkeypatch)
    start = snapshot_encoder(model)
    cfg = RefinementConfig(steps=8, lr=1e-3, loss="hybrid")
    runs = []
    for _ in range(2):
        restore_encoder(model, start)
        runs.append(refine_encoder(model, uneven(supervision(seq, names)), cfg,
                                   photometric=photometric_frames(model, seq, names)))
    first, second = runs
    assert len(calls) == 1 and (first.graph_reused, second.graph_reused) == (False, True)
    assert second.step_mode == "graph" and second.steps_done == 8
    assert all(p.grad is None for p in model.parameters())  # kept by the graph, not the model
    m_eager = tiny_model(INPUT, batch_norm=1)
    eager = refine_encoder(m_eager, uneven(supervision(seq, names)),
                           RefinementConfig(steps=8, lr=1e-3, loss="hybrid", step_mode="eager"),
                           photometric=photometric_frames(m_eager, seq, names))
    assert second.loss_history == pytest.approx(eager.loss_history, rel=RTOL)
    assert first.loss_history == pytest.approx(eager.loss_history, rel=RTOL)
    # another layout (more points per frame than the cap): a graph of its own
    more = supervision(seq, names)
    for s in more:
        s.pixels, s.target, s.weights = (np.concatenate([a] * 2) for a in
                                         (s.pixels, s.target, s.weights))
    restore_encoder(model, start)
    third = refine_encoder(model, more, cfg, photometric=photometric_frames(model, seq, names))
    assert len(calls) == 2 and not third.graph_reused


def test_a_refused_capture_is_not_tried_again(drive, monkeypatch, caplog):
    """The first window's capture fails: its reason is logged once; the next window of the
    same model and objective does not try again and carries the reason."""
    seq, names = drive
    model = tiny_model(INPUT, batch_norm=1)
    calls = _stand_in_captures(monkeypatch, model, fail=True)
    _on_cuda(monkeypatch)
    cfg = RefinementConfig(steps=6, lr=1e-3, loss="sfm")
    with caplog.at_level("WARNING", logger=graph_cache.__name__):
        runs = [refine_encoder(model, uneven(supervision(seq, names)), cfg) for _ in range(3)]
    assert len(calls) == 1
    assert runs[0].step_mode_reason.startswith("capture failed: RuntimeError")
    for r in runs[1:]:
        assert r.step_mode == "static" and r.steps_done == 6
        assert r.step_mode_reason.startswith("capture failed earlier") and "capturing" in \
            r.step_mode_reason
    assert sum("not captured" in m for m in caplog.messages) == 1


def test_the_pacer_bounds_the_replays_in_flight():
    """With an event factory: every replay marked, the host waits for the oldest once more
    than ``in_flight`` are queued (in launch order); without one it does nothing."""
    log = []

    class Event:
        def __init__(self):
            self.n = len([e for e in log if e[0] == "record"])

        def record(self):
            log.append(("record", self.n))

        def synchronize(self):
            log.append(("wait", self.n))

    pacer = graph_cache.ReplayPacer(2, Event)
    for _ in range(5):
        pacer.launched()
    assert [n for kind, n in log if kind == "wait"] == [0, 1, 2]
    assert pacer.waits == 3 and pacer.queued == 2
    assert log.index(("wait", 0)) == log.index(("record", 2)) + 1  # waits after the 3rd launch
    off = graph_cache.ReplayPacer(2, None)
    for _ in range(5):
        off.launched()
    assert off.waits == off.queued == 0
    with pytest.raises(ValueError):
        graph_cache.ReplayPacer(0, Event)


def test_point_caps_are_few():
    assert [graph_cache.point_cap(n) for n in (1, 256, 257, 600, 1024, 1025)] == \
        [256, 256, 512, 1024, 1024, 2048]


def test_the_eager_cpu_path_is_the_plain_loop(drive):
    """The CPU reference, bit for bit: refine_encoder's eager steps are Sec. 3.3's loop written
    out (step_loss, zero_grad, backward, Adam; frames shuffled per pass with the seed)."""
    from sfm_ttr_ros.core.refinement.encoder import set_bn_mode
    from sfm_ttr_ros.core.refinement.objective import frame_terms, step_loss
    from sfm_ttr_ros.core.refinement.trainable import select_trainable

    seq, names = drive
    cfg = RefinementConfig(steps=6, lr=1e-3, loss="sfm", step_mode="auto")
    model = tiny_model(INPUT, batch_norm=1)
    res = refine_encoder(model, uneven(supervision(seq, names)), cfg)
    ref = tiny_model(INPUT, batch_norm=1)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    params = select_trainable(ref, cfg.trainable, cfg.lora_rank, 0)
    set_bn_mode(ref, cfg.bn_mode)
    terms = [frame_terms(ref, s, 0, cfg, None) for s in uneven(supervision(seq, names))]
    opt = torch.optim.Adam(params, lr=cfg.lr)
    losses, order = [], []
    for _ in range(cfg.steps):
        order = order or list(rng.permutation(len(terms)))
        loss = step_loss(ref, terms[order.pop()], 0, cfg, cfg.photometric_config())
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert res.loss_history == losses
    for (k, a), b in zip(model.state_dict().items(), ref.state_dict().values(), strict=True):
        assert torch.equal(a, b), k
