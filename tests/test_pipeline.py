"""The whole method on one window (SfmTTR.process_window): SfM → alignment → refinement →
prediction, on a generated street with a deliberately biased small network.

The network is a tiny encoder-decoder fitted for 200 steps to a DISTORTED ground truth of the
window, depth**0.6: near things too far and far things too near relative to each other, a wrong
shape that no single scale (and so neither the evaluation's median scaling) can fix. SfM-TTR's
sparse depths carry the right shape, so the refined encoder must come out closer to the truth.
"""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from helpers import paper_config
from torch import nn

import sfm_ttr_ros.core.pipeline as pipeline_module
from sfm_ttr_ros.core.evaluation import Evaluator
from sfm_ttr_ros.core.frames import Frame
from sfm_ttr_ros.core.models.base import EncoderDecoder
from sfm_ttr_ros.core.outcomes import Stop
from sfm_ttr_ros.core.pipeline import SfmTTR, TTRConfig

W, H = 640, 192  # the SfM stage's reliable small size (see test_sfm.py)
INPUT = (48, 160)  # the network's input size
GAMMA = 0.6  # the bias: the network learns depth ** GAMMA
STEPS, LR = 80, 1e-3


class CoordEncoder(nn.Module):
    """RGB plus two coordinate channels (where a pixel is says a lot about street depth)."""

    def __init__(self):
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(5, 16, 3, 2, 1), nn.BatchNorm2d(16), nn.ReLU(),
            nn.Conv2d(16, 32, 3, 2, 1), nn.BatchNorm2d(32), nn.ReLU(),
            nn.Conv2d(32, 32, 3, 1, 2, dilation=2), nn.ReLU())

    def forward(self, x):
        n, _, h, w = x.shape
        ys = torch.linspace(-1, 1, h).view(1, 1, h, 1).expand(n, 1, h, w)
        xs = torch.linspace(-1, 1, w).view(1, 1, 1, w).expand(n, 1, h, w)
        return self.body(torch.cat([x, ys, xs], 1))


class SigmoidHead(nn.Module):
    def __init__(self):
        super().__init__()
        self.head = nn.Conv2d(32, 1, 3, 1, 1)

    def forward(self, f):
        up = F.interpolate(self.head(f), scale_factor=4, mode="bilinear", align_corners=False)
        return torch.sigmoid(up)  # Monodepth2-style sigmoid disparity


def street_model(state=None) -> EncoderDecoder:
    """A small net that can learn street depth (CoordEncoder + SigmoidHead), seeded."""
    torch.manual_seed(0)
    model = EncoderDecoder(CoordEncoder(), SigmoidHead(), INPUT)
    if state is not None:
        model.load_state_dict(state)
    return model.eval()


@pytest.fixture(scope="module")
def scene(one_thread):
    from sfm_ttr_ros.data.synthetic import make_sequence

    seq = make_sequence(seed=0, domain="A", num_frames=10, width=W, height=H)
    frames = [Frame(i, im, stamp=s) for i, (im, s) in
              enumerate(zip(seq.images, seq.stamps, strict=True))]
    # An 11th frame SfM cannot register: another street (a cut in the video).
    other = make_sequence(seed=11, domain="B", num_frames=1, width=W, height=H)
    alien = Frame(10, other.images[0], stamp=seq.stamps[-1] + 0.1)
    return SimpleNamespace(seq=seq, frames=frames, alien=alien, window=[*frames, alien],
                           gt={f.name: seq.depths[f.index] for f in frames})


@pytest.fixture(scope="module")
def biased_state(scene):
    """Weights of the tiny network fitted to depth ** GAMMA of the window's frames."""
    model = street_model()
    x = model.preprocess(scene.seq.images)
    gt = F.interpolate(torch.from_numpy(np.stack(scene.seq.depths))[:, None], size=INPUT,
                       mode="nearest")
    valid = gt > 0  # 0 = sky
    target = torch.where(valid, gt.clamp(min=1e-3) ** GAMMA, torch.ones_like(gt))
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    model.train()
    for _ in range(200):
        loss = (torch.log(model(x)) - torch.log(target))[valid].abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return {k: v.detach().clone() for k, v in model.eval().state_dict().items()}


def config(seed: int = 0) -> TTRConfig:
    """The paper's method (params/paper.yaml: batch SfM, Eq. (5) on the whole encoder, every
    window from the start-up weights), with fewer steps at a higher rate for the tiny network."""
    cfg = paper_config()
    cfg.refinement.steps = STEPS
    cfg.refinement.lr = LR
    cfg.refinement.seed = seed
    return cfg


@pytest.fixture(scope="module")
def run(scene, biased_state):
    """One full window (11 frames) with a spy on what the refinement is given."""
    supervised: list[list[str]] = []
    real = pipeline_module.refine_encoder

    def spy(model, supervision, *args, **kwargs):
        supervised.append([s.name for s in supervision])
        return real(model, supervision, *args, **kwargs)

    model = street_model(biased_state)
    ttr = SfmTTR(model, config())
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(pipeline_module, "refine_encoder", spy)
        res = ttr.process_window(scene.window, scene.seq.intrinsics)
    yield SimpleNamespace(ttr=ttr, model=model, res=res, supervised=supervised,
                          window=scene.window, intr=scene.seq.intrinsics)
    ttr.close()


def abs_rel(depths: dict[str, np.ndarray], gt: dict[str, np.ndarray]) -> float:
    ev = Evaluator()  # median scaling, 1e-3 < gt < 80 m, mean over frames
    for name, g in gt.items():
        ev.add(name, depths[name], g)
    summary = ev.summary()
    assert summary["frames"] == len(gt) and summary["skipped"] == 0
    return summary["abs_rel"]


def pinned(run, monkeypatch) -> SfmTTR:
    """The same SfmTTR back at its original weights, with the first run's SfM result.

    The refinement is deterministic; COLMAP's multi-threaded mapper is not promised to be
    (point counts vary between processes), so the checks below hold the SfM result fixed."""
    run.ttr.weights.reset()
    monkeypatch.setattr(run.ttr.sfm.reconstructor, "reconstruct", lambda *a, **k: run.res.sfm)
    return run.ttr


@pytest.mark.slow
def test_refinement_clearly_lowers_abs_rel_of_a_biased_network(scene, biased_state, run):
    res = run.res
    assert res.refined and res.reason == "", res.reason
    assert res.sfm.num_registered == 10 and res.alignment.ok and res.scale > 0
    assert set(res.depths) == set(res.depths_before) == {f.name for f in scene.window}
    before = abs_rel(res.depths_before, scene.gt)
    after = abs_rel(res.depths, scene.gt)
    # Measured: abs rel 0.264 before -> 0.144 after 80 steps at lr 1e-3 (-46 %; 60 or 100
    # steps: -46 %, -45 %); a milder bias (GAMMA 0.7) gave -18 % to -30 % depending on the fit.
    # ~7560 of ~7860 SfM observations supervise. The 11th, unregistered frame is in the window
    # but not in the evaluation (it has no GT).
    assert before > 0.2  # the network really is biased
    assert after < 0.75 * before
    for k, v in run.model.decoder.state_dict().items():  # only the encoder was refined
        assert torch.equal(v, biased_state[f"decoder.{k}"]), k


@pytest.mark.slow
def test_unregistered_frames_are_not_used_for_training(scene, run):
    res, alien = run.res, scene.alien.name
    assert alien not in res.sfm.frames
    registered = set(res.sfm.frames)
    assert run.supervised == [[f.name for f in scene.frames if f.name in registered]]
    assert res.refinement.frames_used == len(registered) == 10
    # ... but it is still predicted, by the refined network.
    assert res.depths[alien].shape == (H, W)
    assert not np.array_equal(res.depths[alien], res.depths_before[alien])


@pytest.mark.slow
def test_loss_history_decreases(run):
    res = run.res
    hist = np.array(res.refinement.loss_history)
    assert res.refinement.steps_done == len(hist) == STEPS and not res.refinement.cancelled
    assert np.all(np.isfinite(hist))
    # Measured: mean of the first 10 steps 0.97, of the last 10 0.49; Eq. (5) averaged over
    # the registered frames 1.17 before and 0.48 after.
    assert hist[-10:].mean() < 0.75 * hist[:10].mean()
    assert res.loss_after < 0.75 * res.loss_before


@pytest.mark.slow
def test_deterministic_under_a_seed(run, monkeypatch):
    ttr = pinned(run, monkeypatch)
    again = ttr.process_window(run.window, run.intr)
    for name in run.res.names:
        np.testing.assert_array_equal(again.depths_before[name], run.res.depths_before[name])
        np.testing.assert_array_equal(again.depths[name], run.res.depths[name])
    assert again.refinement.loss_history == run.res.refinement.loss_history
    # Another seed shuffles the frames differently: other weights, other depths.
    ttr.weights.reset()
    ttr.set_config(config(seed=1))
    other = ttr.process_window(run.window, run.intr)
    ttr.set_config(config())
    assert other.refined
    assert not np.array_equal(other.depths[run.res.names[0]], run.res.depths[run.res.names[0]])


@pytest.mark.slow
def test_cancellation_between_steps(run, monkeypatch):
    ttr = pinned(run, monkeypatch)
    calls = []

    def should_stop() -> bool:
        calls.append(1)
        return len(calls) > 5  # polled before every step: 5 steps run

    res = ttr.process_window(run.window, run.intr, should_stop=should_stop)
    assert res.refinement.cancelled and res.refinement.steps_done == 5
    assert len(res.refinement.loss_history) == 5
    assert not res.refined and res.reason == "refinement cancelled"
    for name in res.names:  # a cancelled window publishes the unrefined depths
        np.testing.assert_array_equal(res.depths[name], res.depths_before[name])

    # SfmTTR.cancel() (what the node calls from another thread) stops at the next step too.
    ttr.weights.reset()
    calls.clear()

    def cancel_at_third() -> bool:
        calls.append(1)
        if len(calls) == 3:
            ttr.cancel()
        return False

    res = ttr.process_window(run.window, run.intr, should_stop=cancel_at_third)
    assert res.refinement.cancelled and res.refinement.steps_done == 3
    assert res.reason == "refinement cancelled"


@pytest.mark.slow
def test_window_summary_is_plain_numbers(run):
    res = run.res
    s = res.summary()
    assert s == {"frames": len(res.names), "refined": True, "reason": "", "reason_key": None,
                 "registered": res.sfm.num_registered, "points": res.sfm.num_points,
                 "scale": res.scale, "loss_before": res.loss_before,
                 "loss_after": res.loss_after, "check": res.check.summary(),
                 "step_mode": ["eager", "not on CUDA (cpu)"],
                 "sfm_mapping": ["", ""], "predictions": dict(res.predictions)}
    assert s["loss_after"] < s["loss_before"]
    # the sanity checks ran and passed
    c = s["check"]
    assert c["reason_key"] is None and c["parallax"] > 0.1 and c["reprojection_error"] < 2.0
    assert res.reason_key is None
    json.dumps(s)


def _encoder_equals(model, state) -> bool:
    return all(torch.equal(v, state[k]) for k, v in model.encoder.state_dict().items())


@pytest.mark.slow
def test_a_window_that_moves_depth_far_from_its_points_is_rejected(run, monkeypatch):
    """The unsupported-change check: measured on every refined window; with τ made
    tiny every pixel far from the SfM points that moved at all counts, and a threshold below
    the measured share refuses the refined weights: the window publishes the depths before it
    and the encoder is back to the weights before it."""
    import sfm_ttr_ros.core.checks.measures as verification

    ttr = pinned(run, monkeypatch)
    ttr.checks.unsupported.clear()  # the accepted windows of the tests before
    original = {k: v.clone() for k, v in ttr.model.encoder.state_dict().items()}
    measured = ttr.process_window(run.window, run.intr)  # off (0): measured, never refuses
    u = measured.check.unsupported_change
    assert measured.refined and 0.0 <= u < 0.5
    pixels = {n: measured.sfm.frames[n].pixels for n in measured.names
              if n in measured.sfm.frames}
    assert u == pytest.approx(verification.unsupported_change(
        measured.depths_before, measured.depths, pixels))
    ttr.weights.reset()
    monkeypatch.setattr(verification, "UNSUPPORTED_FACTOR", 1.0 + 1e-6)
    monkeypatch.setattr(ttr.config.check, "max_unsupported_change", 1e-6)
    res = ttr.process_window(run.window, run.intr)
    c = res.check
    assert not res.refined and res.reason_key == c.reason_key == "check_unsupported_change"
    assert c.unsupported_change > 1e-6 and "far from every SfM point" in res.reason
    assert all(np.array_equal(res.depths[n], res.depths_before[n]) for n in res.names)
    assert res.depths_candidate and _encoder_equals(ttr.model, original)
    assert res.timings["check"] < 0.1 * res.timings["refine"]
    # the reference of check.unsupported_change_ratio: U of the accepted windows only
    assert list(ttr.checks.unsupported) == [pytest.approx(u)]
    monkeypatch.setattr(ttr.config.check, "unsupported_change_ratio",
                        4 * c.unsupported_change / u)  # far above this stream's usual: refused
    res = ttr.process_window(run.window, run.intr)  # ... unless the stream's usual is as high
    assert res.refined and res.check.unsupported_change > 1e-6, res.reason
    assert len(ttr.checks.unsupported) == 2


@pytest.mark.slow
def test_a_failed_sanity_check_refuses_the_window_before_refining(run, monkeypatch):
    ttr = pinned(run, monkeypatch)
    original = {k: v.clone() for k, v in ttr.model.encoder.state_dict().items()}
    monkeypatch.setattr(ttr.config.check, "max_reprojection_error", 1e-6)
    res = ttr.process_window(run.window, run.intr)
    assert res.reason_key == "check_reprojection" and res.refinement is None
    assert res.reason.startswith("check: mean reprojection error")
    assert res.check.reprojection_error > 1e-6 and _encoder_equals(ttr.model, original)
    assert 1.0 <= res.check.scale_spread < 2.0 and res.check.track_length >= 2.0
    # the summary carries the key beside the text; the refinement's inputs stop at the check too
    assert res.summary()["reason_key"] == "check_reprojection" == res.reason_key
    assert json.loads(json.dumps(res.summary()))["reason_key"] == "check_reprojection"
    stop = ttr.refinement_inputs(run.window, run.intr)
    assert isinstance(stop, Stop) and stop.key == "check_reprojection"


@pytest.mark.slow
def test_a_reconstruction_whose_frames_disagree_in_scale_shows_it_in_its_statistics(
        run, monkeypatch):
    """A wrong reconstruction, made by hand: half the registered frames' SfM depths doubled (as
    if the window were two reconstructions glued at different scales). The per-frame scale
    spread, measured and reported without a threshold, shows it; the intact one's does not."""
    import copy

    ttr = pinned(run, monkeypatch)
    intact = ttr.process_window(run.window, run.intr)
    assert intact.refined and intact.check.scale_spread < 1.5
    ttr.weights.reset()
    bent = copy.deepcopy(run.res.sfm)
    for name in sorted(bent.frames)[::2]:
        bent.frames[name].depths = bent.frames[name].depths * 2.0
    monkeypatch.setattr(ttr.sfm.reconstructor, "reconstruct", lambda *a, **k: bent)
    res = ttr.process_window(run.window, run.intr)
    assert res.check.scale_spread > 1.5


@pytest.mark.slow
def test_a_refused_window_leaves_the_continued_weights_untouched(run, monkeypatch):
    """continue: an accepted window's weights carry on; a window a check refuses after
    refining puts back the weights it started from, so only accepted weights are carried."""
    import sfm_ttr_ros.core.checks.measures as verification

    ttr = pinned(run, monkeypatch)
    monkeypatch.setattr(ttr.config, "weight_policy", "continue")
    first = ttr.process_window(run.window, run.intr)  # accepted: the weights move on
    assert first.refined
    kept = {k: v.clone() for k, v in ttr.model.encoder.state_dict().items()}
    monkeypatch.setattr(verification, "UNSUPPORTED_FACTOR", 1.0 + 1e-6)
    monkeypatch.setattr(ttr.config.check, "max_unsupported_change", 1e-6)
    second = ttr.process_window(run.window, run.intr)
    assert second.reason_key == "check_unsupported_change"
    assert _encoder_equals(ttr.model, kept)


@pytest.mark.slow
def test_continue_starts_each_window_from_the_last_accepted_weights(run, monkeypatch):
    """continue: a window after an accepted one starts from its weights; reset starts every
    window from the start-up weights."""
    ttr = pinned(run, monkeypatch)
    original = {k: v.clone() for k, v in ttr.model.encoder.state_dict().items()}
    monkeypatch.setattr(ttr.config, "weight_policy", "continue")
    monkeypatch.setattr(ttr.config, "max_loss_ratio", 0.0)  # this test's lr is for speed only
    first = ttr.process_window(run.window, run.intr)
    assert first.refined and first.refinement.steps_done == STEPS
    carried = {k: v.clone() for k, v in ttr.model.encoder.state_dict().items()}
    seen = []
    real = pipeline_module.refine_encoder

    def spy(model, *args, **kwargs):
        seen.append(_encoder_equals(model, carried))
        return real(model, *args, **kwargs)

    monkeypatch.setattr(pipeline_module, "refine_encoder", spy)
    assert ttr.process_window(run.window, run.intr).refined
    monkeypatch.setattr(ttr.config, "weight_policy", "reset")
    carried = original
    assert ttr.process_window(run.window, run.intr).refined
    assert seen == [True, True]  # from the carried weights, then from the start-up ones
