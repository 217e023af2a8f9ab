"""The embedded default network (MODEL_CARD.md): offline, deterministic, and as good as stated."""

from __future__ import annotations

import importlib.resources
import socket

import numpy as np
import pytest
import torch

from sfm_ttr_ros.core.evaluation import EvalConfig, Evaluator
from sfm_ttr_ros.core.models import ModelConfig, build_model
from sfm_ttr_ros.core.models.mobilenet import MobileDepthNet
from sfm_ttr_ros.core.models.registry import (
    DEFAULT_DECODER_FILE,
    DEFAULT_ENCODER_FILE,
    DEFAULT_WEIGHTS_PACKAGE,
    default_weights_available,
)
from sfm_ttr_ros.data.synthetic import make_sequence

# Measured with the weights of scripts/train_default_model.py --seed 0 (see MODEL_CARD.md):
# median-scaled abs rel 0.149 on this frame (domain B, seed 4242, 1242x375), 0.15-0.25 on seeds
# 11-15; an untrained network scores 0.44-0.91 on the same frames. The frame is deterministic, so
# the margin only absorbs numerical differences between CPUs / torch builds.
HELD_OUT_ABS_REL_BOUND = 0.18
# Real footage it never saw: hololens_000's 100 frames, median-scaled abs rel 0.3137 (BENCHMARKS.md
# §1, "no TTR"); one constant depth per frame scores 0.271. A retrained default must not be worse.
REAL_ABS_REL_BOUND = 0.32

pytestmark = pytest.mark.skipif(not default_weights_available(),
                                reason="default weights not trained yet")


@pytest.fixture(scope="module")
def model():
    return build_model(ModelConfig(type="default"))


@pytest.fixture(scope="module")
def held_out_frame():
    return make_sequence(seed=4242, domain="B", num_frames=1, width=1242, height=375)


def test_weights_ship_inside_the_package_and_are_small():
    ref = importlib.resources.files(DEFAULT_WEIGHTS_PACKAGE) / "weights"
    sizes = [(ref / f).stat().st_size if hasattr(ref / f, "stat") else 0
             for f in (DEFAULT_ENCODER_FILE, DEFAULT_DECODER_FILE)]
    total = sum(len((ref / f).read_bytes()) for f in (DEFAULT_ENCODER_FILE, DEFAULT_DECODER_FILE))
    assert total < 12 * 2**20, f"default weights are {total / 2**20:.1f} MiB ({sizes})"


def test_loads_with_no_network_access(monkeypatch):
    def no_network(*args, **kwargs):
        raise AssertionError("the default model tried to open a network connection")

    monkeypatch.setattr(socket.socket, "connect", no_network)
    monkeypatch.setattr(socket, "create_connection", no_network)
    m = build_model(ModelConfig(type="default"))
    assert isinstance(m, MobileDepthNet)
    assert m.input_size == (128, 416)
    assert all(p.dtype == torch.float32 for p in m.parameters())


def test_output_shape_finite_and_in_range(model, held_out_frame):
    img = held_out_frame.images[0]
    depth = model.predict(img)
    assert depth.shape == (1, 375, 1242) and depth.dtype == np.float32
    assert np.isfinite(depth).all()
    assert depth.min() >= 0.1 - 1e-4 and depth.max() <= 100.0 + 1e-3


def test_deterministic_in_eval_mode(model, held_out_frame):
    img = held_out_frame.images[0]
    a = model.predict(img)
    b = model.predict(img)
    np.testing.assert_array_equal(a, b)
    assert not model.training


def test_held_out_domain_abs_rel_below_the_stated_bound(model, held_out_frame):
    ev = Evaluator(EvalConfig(median_scaling=True))
    ev.add("b", model.predict(held_out_frame.images[0])[0], held_out_frame.depths[0])
    abs_rel = ev.summary()["abs_rel"]
    assert abs_rel < HELD_OUT_ABS_REL_BOUND, abs_rel

    random_net = MobileDepthNet((128, 416)).eval()
    ev_rand = Evaluator(EvalConfig(median_scaling=True))
    ev_rand.add("b", random_net.predict(held_out_frame.images[0])[0], held_out_frame.depths[0])
    assert ev_rand.summary()["abs_rel"] > abs_rel + 0.1  # the bound is not trivial


def test_real_footage_abs_rel_below_the_stated_bound(model, shared_data):
    """The judge of the embedded network is real video it never trained on (hololens_000)."""
    from conftest import open_hololens

    seq = open_hololens(shared_data)
    ev = Evaluator(EvalConfig(median_scaling=True))
    for i in range(len(seq)):
        frame = seq.frame(i)
        ev.add(frame.name, model.predict(frame.image)[0], seq.gt(frame.name))
    s = ev.summary()
    assert s["frames"] == 100 and s["abs_rel"] < REAL_ABS_REL_BOUND, s["abs_rel"]
