"""The hand-over of live depths to the window (core/prediction.py LiveDepths): a frame served
live with the very weights a window starts from is not predicted again; anything else is."""

from __future__ import annotations

import gc
import threading
from functools import partial

import numpy as np
import pytest
import torch
from conftest import tiny_model

from sfm_ttr_ros.core.frames import Frame, image_digest
from sfm_ttr_ros.core.prediction import LiveDepths, Predictor, same_weights
from sfm_ttr_ros.core.refinement.encoder import snapshot_encoder
from sfm_ttr_ros.core.stream.live import LiveServer
from sfm_ttr_ros.core.stream.serving import ServingModel

small_model = partial(tiny_model, (32, 48), downsample=False)


def images(n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 255, (32, 48, 3), dtype=np.uint8) for _ in range(n)]


def served_pair():
    """The window model's predictor and a serving copy holding the same weights, with the
    hand-over attached to the predictor and bound to the serving's current generation."""
    predictor = Predictor(small_model(seed=0), batch=1)
    serving = ServingModel(predictor.model)
    live = LiveDepths(capacity=4)
    predictor.live_depths = live
    generation = serving.update(snapshot_encoder(predictor.model), 1)
    assert live.bind(generation, predictor, serving.model)
    return predictor, serving, live


def serve(serving: ServingModel, live: LiveDepths, ims: list[np.ndarray]) -> None:
    for im in ims:
        s = serving.serve(im)
        live.record(im, s.generation, s.raw)


def test_a_frame_served_with_the_bound_weights_is_not_predicted_again(one_thread):
    predictor, serving, live = served_pair()
    ims = images(3)
    serve(serving, live, ims[:2])
    tally: dict[str, int] = {}
    got = predictor.predict(ims, tally)
    assert tally == {"computed": 1, "reused_live": 2, "reused": 0}
    assert (predictor.computed, predictor.reused_live) == (1, 2)
    assert live.figures()["handed"] == 2 and len(live) == 0  # handed over once, then gone
    # the same numbers as the window's own prediction: bit for bit with one thread team and
    # a batch of 1 (the live server's); another batch composition rounds differently
    own = Predictor(small_model(seed=0), batch=1, reuse=False).predict(ims)
    assert all(np.array_equal(a, b) for a, b in zip(got, own, strict=True))
    pairs = Predictor(small_model(seed=0), batch=2, reuse=False).predict(ims)
    for a, b in zip(got, pairs, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=0)
    assert predictor.predict(ims[:2], tally) and tally["reused"] == 2  # now from the cache


def test_interim_reverted_and_older_weights_are_predicted_again(one_thread):
    predictor, serving, live = served_pair()
    other = snapshot_encoder(small_model(seed=1))
    ims = images(4)
    serving.preview(other, 2, 5)  # a refining window's interim weights
    serve(serving, live, ims[:1])
    serving.revert()  # the window was not accepted: the bound weights again, a new generation
    serve(serving, live, ims[1:2])
    tally: dict[str, int] = {}
    predictor.predict(ims[:2], tally)
    assert tally["reused_live"] == 0 and tally["computed"] == 2
    # served with the bound generation, but the window model changed since (a refinement step)
    gen = serving.update(snapshot_encoder(predictor.model), 3)
    live.bind(gen, predictor, serving.model)
    serve(serving, live, ims[2:3])
    with torch.no_grad():
        next(predictor.model.encoder.parameters()).add_(0.0)  # in place: a new version
    tally = {}
    predictor.predict(ims[2:3], tally)
    assert tally == {"computed": 1, "reused_live": 0, "reused": 0}


def test_a_bind_is_refused_for_other_weights_or_with_reuse_off(one_thread):
    predictor, serving, live = served_pair()
    other = small_model(seed=1)
    assert same_weights(predictor.model, serving.model)
    assert not same_weights(predictor.model, other)
    assert not live.bind(serving.generation, predictor, other)
    serve(serving, live, images(2))
    assert len(live) == 0  # nothing bound: nothing recorded
    predictor.reuse_live = False
    assert not live.bind(serving.generation, predictor, serving.model)
    assert live.figures()["binds_refused"] == 2
    cl = small_model(seed=0).to(memory_format=torch.channels_last)  # rounds differently
    predictor.reuse_live = True
    assert not same_weights(predictor.model, cl)


def test_the_hand_over_holds_at_most_the_next_window(one_thread):
    predictor, serving, live = served_pair()
    ims = images(6)
    serve(serving, live, ims)
    f = live.figures()
    assert (f["held"], f["recorded"], f["dropped_overflow"]) == (4, 6, 2)
    tally: dict[str, int] = {}
    predictor.predict(ims[:2], tally)  # the oldest two were dropped
    assert tally["reused_live"] == 0
    # newer weights served: the older weights' depths go at once
    gen = serving.update(snapshot_encoder(small_model(seed=1)), 2)
    serve(serving, live, images(1, seed=9))
    f = live.figures()
    assert (f["held"], f["dropped_stale_weights"]) == (0, 4)  # unbound weights: not recorded
    assert gen == serving.generation


def test_a_released_image_drops_its_entry(one_thread):
    predictor, serving, live = served_pair()
    im = images(1)[0]
    serve(serving, live, [im])
    digest = image_digest(im)
    assert len(live) == 1
    del im
    gc.collect()
    assert len(live) == 0 and live.figures()["dropped_released"] == 1
    assert live.take(digest, predictor.weights_key()) is None


def test_the_live_server_hands_over_the_raw_depth_before_the_metres_factor(one_thread):
    predictor, serving, live = served_pair()
    serving.set_metres_per_unit(2.0)
    published = []
    server = LiveServer(serving, published.append, live_depths=live)
    im = images(1)[0]
    server.serve_one(Frame(0, im, stamp=0.0, name="a"), 0.0)
    tally: dict[str, int] = {}
    raw = predictor.predict([im], tally)[0]
    assert tally["reused_live"] == 1
    np.testing.assert_array_equal(published[0].depth, raw * np.float32(2.0))


def test_records_and_takes_from_several_threads_stay_bounded(one_thread):
    predictor, serving, live = served_pair()
    depth = np.ones((32, 48), np.float32)
    ims = images(40)
    key = predictor.weights_key()

    def writer():
        for im in ims:
            live.record(im, serving.generation, depth)

    def reader():
        for im in ims:
            live.take(image_digest(im), key)

    threads = [threading.Thread(target=t) for t in (writer, reader, writer)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    f = live.figures()
    assert f["held"] <= 4 and f["recorded"] == 80
    assert f["held"] + f["handed"] + f["dropped_overflow"] + f["replaced"] == 80, f


@pytest.mark.parametrize("capacity", [0, 3])
def test_a_bind_sets_the_capacity(one_thread, capacity):
    predictor, serving, live = served_pair()
    live.bind(serving.generation, predictor, serving.model, capacity=capacity)
    ims = images(5)  # held: a freed image would drop its entry
    serve(serving, live, ims)
    assert len(live) == max(1, capacity)
