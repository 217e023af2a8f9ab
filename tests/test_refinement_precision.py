"""``refinement.precision`` (core/refinement/objective.py): "fp32" is the step of before the
option, bit for bit; "bf16" runs the network's forward pass under bfloat16 autocast in the eager
and the static step alike (loss, weights and Adam in fp32); a device without native bf16 runs
fp32 and says why, once."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch
from conftest import tiny_model
from test_frozen_stages import mobile
from test_refinement_loss import INPUT, photometric_frames, supervision

import sfm_ttr_ros.core.refinement.objective as objective
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.geometry import normalized_grid, sample_depth
from sfm_ttr_ros.core.refinement.encoder import refine_encoder, set_bn_mode
from sfm_ttr_ros.core.refinement.photometric import photometric_objective, scale_outputs
from sfm_ttr_ros.core.refinement.refinement_config import RefinementConfig
from sfm_ttr_ros.core.refinement.supervision import FrameSupervision, weighted_l1
from sfm_ttr_ros.core.refinement.trainable import select_trainable
from sfm_ttr_ros.data.synthetic import render_sequence, sample_scene_params

STEPS = 4
N_FRAMES = 3


@pytest.fixture(scope="module")
def drive(one_thread):
    seq = render_sequence(sample_scene_params(1, "A"), N_FRAMES, 256, 80, blur_sigma=0.8)
    return seq, [f"{i:010d}" for i in range(N_FRAMES)]


@pytest.fixture
def bf16_device(monkeypatch):
    """The CPU taken for one with native bf16 (this machine's may lack it: the autocast still
    runs, emulated), warnings forgotten."""
    monkeypatch.setattr(objective, "bf16_unsupported", lambda device: "")
    monkeypatch.setattr(objective, "_WARNED", set())


def refine(drive, loss: str, **kw):
    seq, names = drive
    model = tiny_model(INPUT, batch_norm=1)
    ph = photometric_frames(model, seq, names) if loss != "sfm" else []
    cfg = RefinementConfig(steps=STEPS, lr=1e-3, loss=loss, **kw)
    return model, refine_encoder(model, supervision(seq, names), cfg, photometric=ph)


def encoder_dtypes(model) -> list[torch.dtype]:
    """The dtype of every encoder output the forward passes produce (a hook, kept on)."""
    seen: list[torch.dtype] = []
    model.encoder.register_forward_hook(lambda _m, _i, out: seen.append(out.dtype))
    return seen


def reference(drive, loss: str) -> tuple[torch.nn.Module, list[float]]:
    """The step as it was before the option, written out without core/refinement/objective.py:
    Eq. (5) (+ 10 x Ph-TTR in the hybrid, Eq. (5) relative) from the plain forward pass, Adam on
    the encoder, the frames shuffled per pass with the seed."""
    seq, names = drive
    cfg = RefinementConfig(steps=STEPS, lr=1e-3, loss=loss)
    model = tiny_model(INPUT, batch_norm=1)
    ph = {f.name: f for f in photometric_frames(model, seq, names)} if loss != "sfm" else {}
    sup = supervision(seq, names)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    opt = torch.optim.Adam(select_trainable(model, "encoder", cfg.lora_rank, 0), lr=cfg.lr)
    set_bn_mode(model, cfg.bn_mode)
    losses, order = [], []
    for _ in range(cfg.steps):
        order = order or list(rng.permutation(len(sup)))
        s = sup[order.pop()]
        weight = s.weights / (np.abs(s.target) if loss == "hybrid" else 1.0)
        x = model.preprocess(s.image)
        outputs = scale_outputs(model, model.encoder(x), cfg.photometric_config().scales)
        grid = normalized_grid(s.pixels, s.image.shape[1], s.image.shape[0])
        value = weighted_l1(sample_depth(outputs[0].depth, grid, cfg.sampling),
                            torch.as_tensor(s.target, dtype=torch.float32),
                            torch.as_tensor(weight, dtype=torch.float32))
        if loss == "hybrid":
            f = ph[s.name]
            value = value + cfg.photometric_weight * photometric_objective(
                outputs, f.target, f.sources, f.K_device, f.poses_device,
                cfg.photometric_config(), f.identity, f.ssim_target, K_inv=f.K_inv).total
        opt.zero_grad(set_to_none=True)
        value.backward()
        opt.step()
        losses.append(float(value.detach()))
    return model, losses


@pytest.mark.parametrize("loss", ["sfm", "hybrid"])
def test_fp32_is_the_step_of_before_bit_for_bit(drive, loss):
    model, res = refine(drive, loss, precision="fp32", step_mode="eager")
    ref, losses = reference(drive, loss)
    assert res.precision == "fp32" and res.precision_reason == ""
    assert res.loss_history == losses
    for (k, a), b in zip(model.state_dict().items(), ref.state_dict().values(), strict=True):
        assert torch.equal(a, b), k
    assert RefinementConfig().precision == "fp32"


@pytest.mark.parametrize("loss", ["sfm", "hybrid"])
def test_bf16_runs_the_forward_in_bf16_in_both_step_modes(drive, bf16_device, loss):
    """The eager and the static step enter the same autocast: the encoder computes bf16, the
    losses stay close to fp32's without being equal, the weights stay fp32, and the two modes
    agree with each other as closely as fp32's do."""
    _, fp32 = refine(drive, loss, precision="fp32", step_mode="eager")
    runs = {}
    for mode in ("eager", "static"):
        model = tiny_model(INPUT, batch_norm=1)
        seen = encoder_dtypes(model)
        seq, names = drive
        ph = photometric_frames(model, seq, names) if loss != "sfm" else []
        cfg = RefinementConfig(steps=STEPS, lr=1e-3, loss=loss, precision="bf16",
                               step_mode=mode)
        runs[mode] = res = refine_encoder(model, supervision(seq, names), cfg, photometric=ph)
        assert (res.step_mode, res.precision, res.precision_reason) == (mode, "bf16", "")
        assert set(seen[-STEPS:]) == {torch.bfloat16}
        assert all(p.dtype == torch.float32 for p in model.parameters())
        assert res.loss_history == pytest.approx(fp32.loss_history, rel=3e-2)
        assert res.loss_history != fp32.loss_history
    assert runs["static"].loss_history == pytest.approx(runs["eager"].loss_history, rel=1e-2)


def test_bf16_caches_frozen_stages_in_bf16_and_decodes_in_fp32(bf16_device):
    """Frozen leading stages computed once per frame under the same autocast; the decoder's
    output, hence depth and the loss, in fp32."""
    rng = np.random.default_rng(0)
    sup = [FrameSupervision("0000", rng.integers(0, 255, (64, 96, 3), dtype=np.uint8),
                            np.c_[rng.uniform(0, 95, 200), rng.uniform(0, 63, 200)],
                            rng.uniform(2.0, 30.0, 200), np.ones(200))]
    for precision, dtype in (("fp32", torch.float32), ("bf16", torch.bfloat16)):
        cfg = RefinementConfig(steps=2, loss="sfm", frozen_encoder_levels=2, precision=precision)
        model = mobile()
        x = objective.step_input(model, sup[0], 2, cfg)
        assert x[0].dtype == dtype
        seen: list[torch.dtype] = []
        model.decoder.register_forward_hook(  # before the cast back to fp32
            lambda _m, _i, out, seen=seen: seen.append(out[("disp", 0)].dtype))
        with objective.network_precision(model, cfg), torch.no_grad():
            depth = objective.forward(model, x, 2)
        assert depth.dtype == torch.float32 and seen == [dtype]
        assert refine_encoder(model, sup, cfg).precision == precision


def test_bf16_without_native_support_runs_fp32_and_says_why_once(drive, monkeypatch, caplog):
    monkeypatch.setattr(objective, "bf16_unsupported", lambda device: "no bf16 on this test")
    monkeypatch.setattr(objective, "_WARNED", set())
    _, fp32 = refine(drive, "sfm", precision="fp32")
    with caplog.at_level(logging.WARNING, logger=objective.__name__):
        results = [refine(drive, "sfm", precision="bf16")[1] for _ in range(2)]
    for res in results:
        assert res.precision == "fp32"
        assert res.precision_reason == "precision bf16 runs as fp32: no bf16 on this test"
        assert res.loss_history == fp32.loss_history
    assert [r.getMessage() for r in caplog.records
            if r.name == objective.__name__] == [results[0].precision_reason]


def test_native_bf16_is_read_from_torch(monkeypatch):
    """The CPU's bf16 is native with AVX-512 BF16 or AMX, as torch reports them."""
    cpu = torch.device("cpu")
    for avx512_bf16, amx, native in ((False, False, False), (True, False, True),
                                     (False, True, True)):
        monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda v=avx512_bf16: v)
        monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda v=amx: v)
        why = objective.bf16_unsupported(cpu)
        assert (why == "") == native
        assert native or torch.backends.cpu.get_cpu_capability() in why
    assert objective.bf16_unsupported(torch.device("meta")) == "no bf16 autocast on meta"
    with pytest.raises(InputError, match="precision"):
        RefinementConfig(precision="fp16")
