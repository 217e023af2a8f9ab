"""The stream core logging through rclpy's real logger: rclpy refuses one call site logging at
two severities (``ValueError: Logger severity cannot be changed between calls``), so every log
call site of the stream has one fixed severity, and a verdict is carried out before it is
logged. Each admission verdict (core/stream/admission.py) and each frame outcome the stream logs
is driven at least twice, in orders that mix the severities, and every frame is accounted for."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_stream import INTR, H, ScriptedTTR, W, check_accounting, frames

from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.stream.frame_queue import RELEASED_IMAGE
from sfm_ttr_ros.core.stream.settings import StreamSettings
from sfm_ttr_ros.core.stream.window_runner import WindowRunner

FALLBACK = Intrinsics(70.0, 70.0, 31.5, 15.5, W, H)
OTHER_FOCAL = Intrinsics(60.0, 60.0, 31.5, 15.5, W, H)
BIG = Intrinsics(100.0, 100.0, 63.5, 31.5, 2 * W, 2 * H)


@pytest.fixture
def rclpy_logger(context):
    """rclpy's own logger (no node needed), fresh per test: its call sites start unseen."""
    import rclpy.logging

    return rclpy.logging.get_logger("sfm_ttr_rclpy_logger_test")


class FailingPredictionTTR(ScriptedTTR):
    """ScriptedTTR whose prediction of unrefined frames fails while ``fail`` is set."""

    fail = False

    def predict(self, images):
        if self.fail:
            raise RuntimeError("no memory")
        return super().predict(images)


def stamped(start: float, n: int = 1, size=(W, H), *, fallback: bool = False) -> list[Frame]:
    fs = frames(n, start=start, size=size, seed=int(start * 10))
    for f in fs:
        f.fallback_intrinsics = fallback
    return fs


def admission_round(stream: WindowRunner, ttr: FailingPredictionTTR, policy: dict,
                    t: float) -> list:
    """Every admission verdict and logged frame outcome once, from stamp ``t`` on: the
    fallback replaced (info), a stamp back (warning), a duplicate stamp (dropped), an
    intrinsics change and a size change (warnings), an intrinsics mismatch, a released image
    (throttled warning), a stale frame, a failed window (error), a failed prediction (error),
    the end of the stream."""
    outs = []
    for f in stamped(t, 2, fallback=True):  # frames before their first CameraInfo
        outs += stream.push(f, FALLBACK)
    outs += stream.push(stamped(t + 0.2)[0], INTR)  # info: the received K replace the fallback
    outs += stream.push(stamped(t - 0.5)[0], INTR)  # warning: the stamp went back
    dup = stamped(t - 0.5)[0]
    outs += stream.push(dup, INTR)  # the same stamp again: dropped
    outs += stream.push(stamped(t + 1.0)[0], OTHER_FOCAL)  # warning: intrinsics changed
    outs += stream.push(stamped(t + 1.1, size=(2 * W, 2 * H))[0], BIG)  # warning: size changed
    outs += stream.push(stamped(t + 1.2)[0], BIG)  # intrinsics for another size: unrefined
    released = stamped(t + 1.3, size=(2 * W, 2 * H))[0]
    released.image = RELEASED_IMAGE  # the backlog bound took its image (keyframe_policy all)
    policy["now"] = "all"
    outs += stream.push(released, BIG)
    policy["now"] = "newest"
    for f in stamped(t + 1.4, 7, size=(2 * W, 2 * H)):  # queued at once: the first is stale
        stream.submit(f, BIG)
    outs += stream.process_available()  # the window over the last ones raises: an error
    outs += stream.push(stamped(t + 2.5)[0], OTHER_FOCAL)  # warning: size changed back
    stream.reject("bad_image", "truncated image")
    ttr.fail = True
    outs += stream.flush()  # end of stream: its prediction fails, the frame dropped (an error)
    ttr.fail = False
    return outs


def test_every_admission_verdict_through_the_real_rclpy_logger(rclpy_logger):
    ttr = FailingPredictionTTR(outcomes=("raise",))
    policy = {"now": "newest"}
    stream = WindowRunner(ttr, settings_provider=lambda: StreamSettings(
        window_size=4, window_stride=4, keyframe_policy=policy["now"], overload_pending=50,
        max_pending=50), logger=rclpy_logger)
    outs = admission_round(stream, ttr, policy, 10.0)
    outs += admission_round(stream, ttr, policy, 20.0)  # each call site again, after the others
    c = check_accounting(stream, outs, 2 * 18)  # every frame published or dropped, once
    assert c["pending"] == 0 and c["non_monotonic_stamps"] == 2 and c["windows_failed"] == 2
    assert c["dropped_by_reason"] == {"duplicate_stamp": 2, "prediction_error": 2,
                                      "bad_image": 2}
    assert c["unrefined_by_reason"] == {
        "stamp_jump_back": 6, "intrinsics_change": 2, "resolution_change": 2,
        "intrinsics_mismatch": 2, "overload": 4, "stale": 6, "window_error": 8}


def test_the_refiner_serving_interim_weights_through_the_real_rclpy_logger(rclpy_logger,
                                                                          one_thread):
    """StreamRefiner (core/stream/refiner.py) on the real logger: a window rolled back after
    its interim weights were served (a warning, then an info line), a refined window, a stamp
    that went back and a duplicate; every frame accounted for."""
    from test_live import fake_sfm, small_model

    from sfm_ttr_ros.core.pipeline import SfmTTR, TTRConfig
    from sfm_ttr_ros.core.sfm.sfm_config import SfmConfig
    from sfm_ttr_ros.core.stream.refiner import StreamRefiner

    lr = {"now": 50.0}

    def config():
        cfg = TTRConfig(weight_policy="reset", min_supervision_points=10,
                        sfm=SfmConfig(mode="batch"))  # the fake stands in for the batch mapper
        cfg.refinement.steps, cfg.refinement.lr = 4, lr["now"]
        cfg.check.min_parallax = 0.0  # the fake SfM's cameras do not move
        return cfg

    ttr = SfmTTR(small_model(), config())
    rng = np.random.default_rng(3)
    fs = [Frame(i, rng.integers(0, 255, (32, 48, 3), dtype=np.uint8), stamp=0.1 * i,
                name=f"{i:04d}") for i in range(9)]
    ttr.sfm.reconstructor.reconstruct = lambda frames, *a, **k: fake_sfm(
        [f.name for f in frames], rng)
    outs = []
    online = StreamRefiner(ttr, StreamSettings(window_size=3, window_stride=3,
                                               serve_every_steps=1),
                           on_refined=outs.append, config_provider=config, logger=rclpy_logger)
    k = Intrinsics(40.0, 40.0, 24.0, 16.0, 48, 32)
    try:
        for f in fs[:3]:  # exploding steps: rolled back, its interim weights withdrawn
            online.stream.push(f, k)
        lr["now"] = 1e-3
        for f in fs[3:6]:  # refined
            online.stream.push(f, k)
        for f in (fs[6], fs[7], fs[1], fs[1], fs[8], fs[0], fs[2]):  # stamps back, the same
            online.stream.push(dataclasses.replace(f), k)  # stamp twice: a fresh message each
        online.stream.flush()
    finally:
        ttr.close()
    assert [w.refined for w in online.stream.windows][:2] == [False, True]
    assert online.counters_live()["serving_reverts"] == 1
    c = check_accounting(online.stream, outs, 13)
    assert c["pending"] == 0 and c["dropped_by_reason"] == {"duplicate_stamp": 1}
