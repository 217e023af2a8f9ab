"""The node's /diagnostics counters and status, ROS-free (sfm_ttr_ros.core.stream.diagnostics), and
the DiagnosticArray built from them (sfm_ttr_ros.ros.outputs)."""

from __future__ import annotations

import numpy as np
import pytest

from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.outcomes import Unrefined
from sfm_ttr_ros.core.pipeline import WindowResult
from sfm_ttr_ros.core.sfm.result import FrameObservations, SfmResult
from sfm_ttr_ros.core.stream.diagnostics import Status, StreamDiagnostics
from sfm_ttr_ros.core.stream.health import Health, RateMeter
from sfm_ttr_ros.core.stream.records import WindowStats
from sfm_ttr_ros.core.stream.window_runner import WindowRunner

INTR = Intrinsics(100.0, 100.0, 15.5, 7.5, 32, 16)
FRAME_KEYS = ["frames_received", "frames_refined", "frames_unrefined", "frames_dropped",
              "frames_pending", "frames_held_no_intrinsics", "frames_live_only",
              "frames_backlog_released", "frames_without_camera_info"]
INPUT_AND_WINDOW_KEYS = ["rejected_bad_image", "rejected_camera_info", "non_monotonic_stamps",
                         "qos_incompatible", "windows_ok", "windows_failed",
                         "windows_skipped_overload", "windows_disabled",
                         "windows_rejected_by_check", "windows_remapped", "faults"]
KEYFRAME_KEYS = ["keyframes.policy", "keyframes.interval_s", "keyframes.needed_s",
                 "keyframes.reason", "keyframes.stale", "keyframes.behind_s"]


def frame(i: int) -> Frame:
    return Frame(index=i, image=np.zeros((16, 32, 3), np.uint8), stamp=float(i))


@pytest.fixture
def stream() -> WindowRunner:
    # only the accounting is used: frames are queued and rejected, never processed
    return WindowRunner(ttr=None)


def adds_up(v: dict) -> bool:
    return v["frames_received"] == (v["frames_refined"] + v["frames_unrefined"]
                                    + v["frames_dropped"] + v["frames_pending"])


def test_an_idle_stream_is_ok_with_every_counter_at_zero(stream):
    diag = StreamDiagnostics(stream)
    status = diag.status()
    assert status == Status("ok", "0 refined, 0 window(s) ok", status.values)
    assert list(status.values) == FRAME_KEYS + INPUT_AND_WINDOW_KEYS + KEYFRAME_KEYS
    assert {status.values[k] for k in FRAME_KEYS + INPUT_AND_WINDOW_KEYS} == {0}
    # the keyframe rule, before any frame: every frame a keyframe, nothing behind
    assert [status.values[k] for k in KEYFRAME_KEYS] == ["newest", 0.0, 0.0, "every_frame", 0,
                                                         0.0]


def test_held_frames_count_as_received_and_pending(stream):
    held = [2]
    diag = StreamDiagnostics(stream, held=lambda: held[0])
    for i in range(3):
        stream.submit(frame(i), INTR)
    stream.reject("bad_image", "image rejected: test")
    v = diag.values()
    assert (v["frames_received"], v["frames_pending"], v["frames_dropped"]) == (6, 5, 1)
    assert v["frames_held_no_intrinsics"] == 2 and adds_up(v)
    assert v["dropped.bad_image"] == v["rejected_bad_image"] == 1
    # per-reason keys sit between the frame keys and the input keys, sorted
    stream.reject("no_intrinsics", "held frame dropped")
    keys = list(diag.values())
    assert keys[len(FRAME_KEYS):len(FRAME_KEYS) + 2] == ["dropped.bad_image",
                                                          "dropped.no_intrinsics"]
    status = diag.status()
    assert status.level == "warn" and status.message == "no intrinsics: frames held"
    held[0] = 0
    assert diag.status().level == "ok"


def test_input_problems_and_unrefined_frames_make_a_warning_once(stream):
    diag = StreamDiagnostics(stream)
    diag.camera_info_rejected()
    diag.qos_event("image")
    diag.qos_event("~/depth")
    diag.output_published(refined=False, reason_key=Unrefined.SFM_FAILED)
    diag.output_published(refined=False)
    diag.output_published(refined=True)
    # frames the keyframe rule passed on by design are no problem
    diag.output_published(refined=False, reason_key=Unrefined.NOT_KEYFRAME)
    diag.output_published(refined=False, reason_key=Unrefined.STALE)
    status = diag.status()
    assert status.level == "warn"
    assert status.message == "2 frame(s) passed through unrefined; incompatible QoS"
    assert (status.values["rejected_camera_info"], status.values["qos_incompatible"]) == (1, 2)
    assert diag.qos_incompatible == {"image": 1, "~/depth": 1}
    # the unrefined frames are reported once; the QoS problem stays
    assert diag.status().message == "incompatible QoS"


def test_depth_without_camera_info_is_counted_per_output_and_warned_once(stream):
    diag = StreamDiagnostics(stream, live=lambda: {
        "received": 3, "published": 3, "skipped": {}, "pending": 0, "version": 0,
        "weights_age_s": 0.0, "serving_updates": 0, "interim_step": 0, "serving_previews": 0,
        "serving_reverts": 0, "serving_interim_refused": 0,
        **{k: 0.0 for k in ("latency_p50_s", "latency_p95_s", "latency_max_s",
                            "publish_max_s")}})
    assert diag.values()["live.without_camera_info"] == 0
    assert diag.camera_info_missing("live") == 1 and diag.camera_info_missing("live") == 2
    diag.camera_info_missing("refined")
    status = diag.status()
    assert status.level == "warn"
    assert status.message == "3 depth image(s) without CameraInfo (no intrinsics yet)"
    assert status.values["live.without_camera_info"] == 2
    assert status.values["frames_without_camera_info"] == 1
    assert diag.status().level == "ok"  # reported once; the counters stay


def test_the_last_window_is_reported_with_its_timings(stream):
    diag = StreamDiagnostics(stream)
    one = np.ones(1)
    registered = FrameObservations("a", np.zeros((1, 2), np.float32), one, one * 0.25, one,
                                   np.zeros(1, np.int64), np.eye(4))
    sfm = SfmResult(False, "too few matches", 3, frames={"a": registered}, attempts=[{}, {}])
    stream.windows.append(WindowStats(index=4, new_frames=3, steps=5, result=WindowResult(
        ["a", "b", "c"], {}, {}, refined=False, reason="SfM failed: too few matches",
        reason_key="sfm_failed", sfm=sfm, timings={"sfm": 1.25, "predict_before": 0.5})))
    status = diag.status()
    assert status.level == "warn"
    assert status.message == "last window not refined: SfM failed: too few matches"
    v = status.values
    assert (v["last_window.index"], v["last_window.frames"], v["last_window.refined"]) == \
        (4, 3, False)
    assert (v["last_window.steps"], v["last_window.steps_done"]) == (5, 0)
    assert (v["last_window.mapping_attempts"], v["last_window.reprojection_error_px"]) == (2, 0.25)
    assert v["last_window.time.sfm_s"] == 1.25 and v["last_window.time.predict_before_s"] == 0.5
    assert list(v)[-2:] == ["last_window.time.sfm_s", "last_window.time.predict_before_s"]
    stream.windows.append(WindowStats(index=5, new_frames=1,
                                      result=WindowResult(["c", "d"], {}, {}, refined=True)))
    assert diag.status() == Status("ok", "0 refined, 0 window(s) ok", diag.values())


@pytest.mark.ros
def test_the_status_becomes_a_diagnostic_array():
    pytest.importorskip("diagnostic_msgs")
    from diagnostic_msgs.msg import DiagnosticStatus

    from msg_adapters import diagnostic_values
    from sfm_ttr_ros.ros import names, outputs

    status = Status("warn", "incompatible QoS", {"frames_received": 3, "last_window.scale": 0.5,
                                                 "last_window.refined": True})
    timings: dict[str, float] = {}
    arr = outputs.diagnostics_message(status, 12.5, timings=timings)
    (s,) = arr.status
    assert (s.name, s.hardware_id, s.level, s.message) == (
        "sfm_ttr_ros: refiner", "/refiner", DiagnosticStatus.WARN, "incompatible QoS")
    assert s.name == names.DIAG_NAME
    assert diagnostic_values(arr) == {"frames_received": "3", "last_window.scale": "0.5",
                                      "last_window.refined": "true"}
    assert (arr.header.stamp.sec, arr.header.stamp.nanosec) == (12, 500_000_000)
    assert set(timings) == {"diagnostics"} and timings["diagnostics"] >= 0


class FakeClock:
    """A steady clock the test moves by hand."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_rates_are_taken_over_the_recent_interval():
    clock = FakeClock()
    meter = RateMeter(interval_s=5.0, clock=clock)
    assert (meter.hz(), meter.silent_s()) == (0.0, 0.0)
    for _ in range(10):  # 10 Hz for 1 s: the interval so far is 1 s long
        clock.now += 0.1
        meter.tick()
    assert meter.hz() == pytest.approx(10.0)
    clock.now += 3.0  # silent for 3 s: 10 events over 4 s
    assert meter.hz() == pytest.approx(2.5) and meter.silent_s() == pytest.approx(3.0)
    clock.now += 2.0  # the events fall out of the 5-s interval
    assert meter.hz() == 0.0 and meter.count == 10


def test_health_is_error_when_the_worker_died_and_stale_when_the_input_is_silent():
    clock = FakeClock()
    alive, limit = [True], [2.0]
    health = Health(lambda: alive[0], lambda: limit[0], "/cam1/image", clock=clock)
    assert health.problem() is None
    clock.now += 2.5  # no image since start-up
    level, why = health.problem()
    assert level == "stale" and "/cam1/image" in why and "none yet" in why
    health.image_received()
    health.published("depth")
    assert health.problem() is None
    clock.now += 2.5
    assert health.problem()[0] == "stale" and "since the last image" in health.problem()[1]
    limit[0] = 0.0  # never stale
    assert health.problem() is None
    alive[0] = False
    assert health.problem()[0] == "error" and "worker has died" in health.problem()[1]
    v = health.values()
    assert list(v) == ["rate.image_hz", "rate.depth_hz", "rate.depth_refined_hz",
                       "input.silent_s", "worker_alive"]
    assert v["rate.image_hz"] == pytest.approx(1 / 5.0) and v["rate.depth_refined_hz"] == 0.0
    assert v["input.silent_s"] == pytest.approx(2.5) and v["worker_alive"] is False


def test_error_and_stale_lead_the_status_before_the_warnings(stream):
    clock = FakeClock()
    alive = [True]
    health = Health(lambda: alive[0], lambda: 1.0, clock=clock)
    diag = StreamDiagnostics(stream, health=health)
    health.image_received()
    assert diag.status().level == "ok" and diag.status().values["worker_alive"] is True
    diag.qos_event("image")
    clock.now += 1.5
    status = diag.status()
    assert status.level == "stale"
    assert status.message.startswith("no image on image for 1.5 s") and \
        status.message.endswith("; incompatible QoS")
    alive[0] = False
    assert diag.status().level == "error"
    # the rates come after the counters, before the per-window values
    keys = list(status.values)
    assert keys.index("faults") < keys.index("rate.image_hz") < keys.index("keyframes.policy")


@pytest.mark.ros
def test_each_level_maps_to_its_message_and_the_name_follows_the_namespace():
    pytest.importorskip("diagnostic_msgs")
    from diagnostic_msgs.msg import DiagnosticStatus

    from sfm_ttr_ros.ros import names, outputs

    for level, code in (("ok", DiagnosticStatus.OK), ("warn", DiagnosticStatus.WARN),
                        ("error", DiagnosticStatus.ERROR), ("stale", DiagnosticStatus.STALE)):
        (s,) = outputs.diagnostics_message(Status(level, "m"), 1.0, "/cam1/refiner").status
        assert (s.level, s.name, s.hardware_id) == (code, "sfm_ttr_ros: cam1/refiner",
                                                    "/cam1/refiner")
    assert names.status_name("/cam2/refiner") != names.status_name("/cam1/refiner")
    assert names.status_name(names.NODE_FQN) == names.DIAG_NAME == "sfm_ttr_ros: refiner"


@pytest.mark.ros
def test_a_namespaced_node_goes_stale_reports_its_rates_then_errors(context):
    """The node in namespace cam1: STALE before any image, its input and output rates while a
    (reliable) camera feeds it at ~20 Hz, ERROR once its window worker is gone."""
    import threading
    import time

    from builtin_interfaces.msg import Time
    from conftest import tiny_model
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import Image
    from std_msgs.msg import Header

    from msg_adapters import diagnostic_values, numpy_to_image
    from sfm_ttr_ros.ros import names
    from sfm_ttr_ros.ros.node import RefinerNode

    params = {"diagnostics_period_s": 0.2, "diagnostics.stale_after_s": 1.0,
              "fallback_intrinsics": "100.0 100.0 0 0", "refinement.steps": 0}
    refiner = RefinerNode(model=tiny_model(), context=context, namespace="cam1",
                          parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
    camera = rclpy_node("camera", context)
    statuses: list[DiagnosticStatus] = []
    camera.create_subscription(DiagnosticArray, names.DIAGNOSTICS_TOPIC, lambda m: statuses.extend(
        s for s in m.status if s.name == "sfm_ttr_ros: cam1/refiner"), 50)
    pub = camera.create_publisher(Image, "/cam1/image", 10)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(refiner)
    executor.add_node(camera)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    rgb = np.random.default_rng(0).integers(0, 255, (48, 160, 3), np.uint8)

    def wait_for(pred, feed: bool, what: str) -> DiagnosticStatus:
        deadline, n = time.monotonic() + 30, 0
        while time.monotonic() < deadline:
            if feed:
                n += 1
                stamp = Time(sec=n // 20, nanosec=n % 20 * 50_000_000)
                header = Header(frame_id="cam", stamp=stamp)
                pub.publish(numpy_to_image(rgb, "rgb8", header))
            found = [s for s in list(statuses) if pred(s)]
            if found:
                return found[-1]
            time.sleep(0.05)
        raise AssertionError(f"no status {what}; last: {statuses[-1:]}")

    try:
        s = wait_for(lambda s: s.level == DiagnosticStatus.STALE, False, "STALE")
        assert "no image on /cam1/image" in s.message and "none yet" in s.message
        assert s.hardware_id == "/cam1/refiner"
        s = wait_for(lambda s: s.level < DiagnosticStatus.ERROR and float(
            diagnostic_values(s)["rate.depth_hz"]) > 5, True, "with the camera's rate")
        v = diagnostic_values(s)
        assert 5 < float(v["rate.image_hz"]) < 40 and v["worker_alive"] == "true"
        refiner.online.stop(10)  # the worker gone: no window will run again
        s = wait_for(lambda s: s.level == DiagnosticStatus.ERROR, False, "ERROR")
        assert s.message.startswith("window worker has died")
        assert diagnostic_values(s)["worker_alive"] == "false"
    finally:
        executor.shutdown()
        refiner.destroy_node()
        camera.destroy_node()


def rclpy_node(name: str, context):
    from rclpy.node import Node

    return Node(name, context=context)
