"""The node's /diagnostics counters and statuses, one per concern, ROS-free
(sfm_ttr_ros.core.stream.diagnostics), and the DiagnosticArray built from them
(sfm_ttr_ros.ros.outputs)."""

from __future__ import annotations

import numpy as np
import pytest

from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.metric.scale import MetricStatus
from sfm_ttr_ros.core.outcomes import Unrefined
from sfm_ttr_ros.core.pipeline import WindowResult
from sfm_ttr_ros.core.sfm.result import FrameObservations, SfmResult
from sfm_ttr_ros.core.stream.diagnostics import StreamDiagnostics
from sfm_ttr_ros.core.stream.health import Health, RateMeter
from sfm_ttr_ros.core.stream.records import WindowStats
from sfm_ttr_ros.core.stream.status import Status
from sfm_ttr_ros.core.stream.window_runner import WindowRunner

INTR = Intrinsics(100.0, 100.0, 15.5, 7.5, 32, 16)
FRAME_KEYS = ["frames_received", "frames_refined", "frames_unrefined", "frames_dropped",
              "frames_pending", "frames_held_no_intrinsics", "frames_live_only",
              "frames_backlog_released", "frames_without_camera_info"]
INPUT_AND_WINDOW_KEYS = ["rejected_bad_image", "rejected_camera_info", "non_monotonic_stamps",
                         "qos_incompatible", "windows_ok", "windows_failed",
                         "windows_skipped_overload", "windows_disabled",
                         "windows_rejected_by_check", "windows_remapped"]
KEYFRAME_KEYS = ["keyframes.policy", "keyframes.interval_s", "keyframes.needed_s",
                 "keyframes.reason", "keyframes.stale", "keyframes.behind_s"]


def frame(i: int) -> Frame:
    return Frame(index=i, image=np.zeros((16, 32, 3), np.uint8), stamp=float(i))


@pytest.fixture
def stream() -> WindowRunner:
    # only the accounting is used: frames are queued and rejected, never processed
    return WindowRunner(ttr=None)


def status_of(diag: StreamDiagnostics, task: str = "stream") -> Status:
    """The status of ``task`` among the diagnostics' statuses now (reporting resets their
    since-last-status counts)."""
    (status,) = [s for s in diag.statuses() if s.task == task]
    return status


def adds_up(v: dict) -> bool:
    return v["frames_received"] == (v["frames_refined"] + v["frames_unrefined"]
                                    + v["frames_dropped"] + v["frames_pending"])


def test_an_idle_stream_is_ok_with_every_counter_at_zero(stream):
    diag = StreamDiagnostics(stream)
    status, worker = diag.statuses()  # no model's scale, no live output, no health
    assert status == Status("ok", "0 refined, 0 window(s) ok", status.values)
    assert worker == Status("ok", "0 fault(s) contained so far", {"faults": 0}, "worker")
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
    status = status_of(diag)
    assert status.level == "warn" and status.message == "no intrinsics: frames held"
    held[0] = 0
    assert status_of(diag).level == "ok"


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
    status = status_of(diag)
    assert status.level == "warn"
    assert status.message == "2 frame(s) passed through unrefined; incompatible QoS"
    assert (status.values["rejected_camera_info"], status.values["qos_incompatible"]) == (1, 2)
    assert diag.qos_incompatible == {"image": 1, "~/depth": 1}
    # the unrefined frames are reported once; the QoS problem stays
    assert status_of(diag).message == "incompatible QoS"


LIVE_COUNTS = {
    "received": 3, "published": 3, "skipped": {}, "pending": 0, "version": 0,
    "weights_age_s": 0.0, "serving_updates": 0, "interim_step": 0, "serving_previews": 0,
    "serving_reverts": 0, "serving_interim_refused": 0,
    **{k: 0.0 for k in ("latency_p50_s", "latency_p95_s", "latency_max_s", "publish_max_s")}}


def test_depth_without_camera_info_is_counted_per_output_and_warned_once(stream):
    diag = StreamDiagnostics(stream, live=lambda: LIVE_COUNTS)
    assert diag.values()["live.without_camera_info"] == 0
    assert diag.camera_info_missing("live") == 1 and diag.camera_info_missing("live") == 2
    diag.camera_info_missing("refined")
    windowed, live, _ = diag.statuses()  # each output's in the status of its concern
    assert (windowed.task, windowed.level, live.task, live.level) == ("stream", "warn", "live",
                                                                      "warn")
    assert live.message == "2 depth image(s) without CameraInfo (no intrinsics yet)"
    assert windowed.message == "1 depth image(s) without CameraInfo (no intrinsics yet)"
    assert live.values["live.without_camera_info"] == 2
    assert windowed.values["frames_without_camera_info"] == 1
    # reported once; the counters stay
    assert [(s.level, s.message) for s in diag.statuses()[:2]] == [
        ("ok", "0 refined, 0 window(s) ok"), ("ok", "3 published, served weights of window 0")]


def test_the_last_window_is_reported_with_its_timings(stream):
    diag = StreamDiagnostics(stream)
    one = np.ones(1)
    registered = FrameObservations("a", np.zeros((1, 2), np.float32), one, one * 0.25, one,
                                   np.zeros(1, np.int64), np.eye(4))
    sfm = SfmResult(False, "too few matches", 3, frames={"a": registered}, attempts=[{}, {}])
    stream.windows.append(WindowStats(index=4, new_frames=3, steps=5, result=WindowResult(
        ["a", "b", "c"], {}, {}, refined=False, reason="SfM failed: too few matches",
        reason_key="sfm_failed", sfm=sfm, timings={"sfm": 1.25, "predict_before": 0.5})))
    status = status_of(diag)
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
    assert status_of(diag) == Status("ok", "0 refined, 0 window(s) ok", diag.stream_values())


@pytest.mark.ros
def test_the_statuses_become_one_diagnostic_array_named_as_diagnostic_updater_names():
    pytest.importorskip("diagnostic_msgs")
    from diagnostic_msgs.msg import DiagnosticStatus

    from msg_adapters import diagnostic_values
    from sfm_ttr_ros.ros import names, outputs

    stream = Status("warn", "incompatible QoS", {"frames_received": 3, "last_window.scale": 0.5,
                                                 "last_window.refined": True})
    worker = Status("ok", "0 fault(s) contained so far", {"faults": 0}, "worker")
    timings: dict[str, float] = {}
    arr = outputs.diagnostics_message([stream, worker], 12.5, timings=timings)
    assert [(s.name, s.hardware_id, s.level, s.message) for s in arr.status] == [
        ("refiner: stream", "/refiner", DiagnosticStatus.WARN, "incompatible QoS"),
        ("refiner: worker", "/refiner", DiagnosticStatus.OK, "0 fault(s) contained so far")]
    assert [s.name for s in arr.status] == [names.DIAG_NAMES["stream"], names.DIAG_NAMES["worker"]]
    assert diagnostic_values(arr, names.DIAG_NAMES["stream"]) == {
        "frames_received": "3", "last_window.scale": "0.5", "last_window.refined": "true"}
    assert diagnostic_values(arr, hardware_id="/refiner")["faults"] == "0"
    assert (arr.header.stamp.sec, arr.header.stamp.nanosec) == (12, 500_000_000)
    assert set(timings) == {"diagnostics"} and timings["diagnostics"] >= 0


class FakeTTR:
    """A model's metric status, as SfmTTR gives it (and an SfM source without counters)."""

    def __init__(self, status: MetricStatus) -> None:
        self.status = status
        self.sfm = SfmWithoutCounters()

    def metric_status(self) -> MetricStatus:
        return self.status


def test_the_scale_has_a_status_of_its_own_warn_until_the_depth_is_in_metres():
    relative = MetricStatus("none", "not_metric", None, float("nan"), 0, 0, 0)
    ttr = FakeTTR(relative)
    diag = StreamDiagnostics(WindowRunner(ttr=ttr))
    scale = status_of(diag, "scale")
    assert (scale.level, scale.message) == ("warn", "depth not in metres (metric.source none, "
                                                    "not_metric)")
    assert list(scale.values) == ["metric.source", "metric.state", "metric.reason",
                                  "metric.metres_per_unit", "metric.spread", "metric.windows",
                                  "metric.odometry_received", "metric.odometry_rejected",
                                  "metric.odometry_resets", "metric.re_anchors"]
    assert status_of(diag).level == "ok"  # the stream is fine: the units are the scale's
    ttr.status = MetricStatus("fixed", "metric", 2.0, 0.0, 0, 0, 0)
    assert status_of(diag, "scale").level == "ok"
    # the node says which topic carries the depth (ros/units.py describe_depth)
    diag = StreamDiagnostics(WindowRunner(ttr=FakeTTR(relative)),
                             scale=lambda s: ("warn", f"depth relative ({s.source})"))
    assert status_of(diag, "scale").message == "depth relative (none)"


def test_every_key_is_in_the_status_of_its_concern_once(stream):
    health = Health(lambda: True, lambda: 5.0)
    diag = StreamDiagnostics(WindowRunner(ttr=FakeTTR(MetricStatus(
        "none", "not_metric", None, float("nan"), 0, 0, 0))), live=lambda: LIVE_COUNTS,
        health=health)
    diag.fault("timer")
    statuses = diag.statuses()
    assert [s.task for s in statuses] == ["stream", "scale", "live", "worker"]
    keys = [k for s in statuses for k in s.values]
    assert keys == list(diag.values())  # the final accounting: every status's keys, in order
    by_task = {s.task: s.values for s in statuses}
    assert "input.silent_s" in by_task["stream"] and "metric.state" in by_task["scale"]
    assert {"rate.image_hz", "live.received", "serving.version"} <= set(by_task["live"])
    assert list(by_task["worker"]) == ["worker_alive", "faults", "faults.timer"]
    assert statuses[-1].level == "warn" and statuses[-1].message == "1 fault(s) contained"


class SfmWithoutCounters:
    def counters(self) -> dict[str, dict]:
        return {"sfm_ahead": {}, "sfm_streaming": {}}


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


def test_health_tells_a_dead_worker_and_a_silent_input():
    clock = FakeClock()
    alive, limit = [True], [2.0]
    health = Health(lambda: alive[0], lambda: limit[0], "/cam1/image", clock=clock)
    assert (health.worker_problem(), health.input_problem()) == (None, None)
    clock.now += 2.5  # no image since start-up
    why = health.input_problem()
    assert "/cam1/image" in why and "none yet" in why
    health.image_received()
    health.published("depth")
    assert health.input_problem() is None
    clock.now += 2.5
    assert "since the last image" in health.input_problem()
    limit[0] = 0.0  # never silent
    assert health.input_problem() is None
    alive[0] = False
    assert "worker has died" in health.worker_problem()
    assert list(health.rate_values()) == ["rate.image_hz", "rate.depth_hz",
                                          "rate.depth_refined_hz"]
    assert health.rate_values()["rate.image_hz"] == pytest.approx(1 / 5.0)
    assert health.rate_values()["rate.depth_refined_hz"] == 0.0
    assert health.input_values() == {"input.silent_s": pytest.approx(2.5)}
    assert health.worker_values() == {"worker_alive": False}


def test_silence_is_a_warning_and_a_dead_worker_an_error_never_stale(stream):
    """STALE is the aggregator's (no status received): the node's own statuses say WARN for a
    silent input and ERROR for a dead worker, first in the message."""
    clock = FakeClock()
    alive = [True]
    health = Health(lambda: alive[0], lambda: 1.0, clock=clock)
    diag = StreamDiagnostics(stream, health=health)
    health.image_received()
    assert [s.level for s in diag.statuses()] == ["ok", "ok", "ok"]  # stream, live, worker
    assert status_of(diag, "worker").values["worker_alive"] is True
    diag.qos_event("image")
    clock.now += 1.5
    status = status_of(diag)
    assert status.level == "warn"
    assert status.message.startswith("no image on image for 1.5 s") and \
        status.message.endswith("; incompatible QoS")
    alive[0] = False
    stream_status, _, worker = diag.statuses()
    assert (stream_status.level, worker.level) == ("error", "error")
    assert stream_status.message.startswith("window worker has died: no window will run")
    assert "; no image on image for" in stream_status.message
    assert worker.message.startswith("window worker has died")


@pytest.mark.ros
def test_each_level_maps_to_its_message_and_the_name_is_the_node_name_and_task():
    pytest.importorskip("diagnostic_msgs")
    from diagnostic_msgs.msg import DiagnosticStatus

    from sfm_ttr_ros.ros import names, outputs

    for level, code in (("ok", DiagnosticStatus.OK), ("warn", DiagnosticStatus.WARN),
                        ("error", DiagnosticStatus.ERROR)):
        (s,) = outputs.diagnostics_message([Status(level, "m", task="scale")], 1.0, "refiner",
                                           "/cam1/refiner").status
        # diagnostic_updater's "<node name>: <task>"; the namespace is in the hardware_id
        assert (s.level, s.name, s.hardware_id) == (code, "refiner: scale", "/cam1/refiner")
    assert names.status_name("cam_node", "live") == "cam_node: live"
    assert names.DIAG_NAMES == {task: f"refiner: {task}" for task in ("stream", "scale", "live",
                                                                       "worker")}


@pytest.mark.ros
def test_a_namespaced_node_warns_of_silence_reports_its_rates_then_errors(context):
    """The node in namespace cam1: its stream status a WARN before any image, its input and
    output rates (the live status) while a (reliable) camera feeds it at ~20 Hz, ERROR (stream
    and worker) once its window worker is gone; never STALE."""
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
        s for s in m.status if s.hardware_id == "/cam1/refiner"), 50)
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

    stream, live, worker = (names.status_name("refiner", t) for t in ("stream", "live", "worker"))
    try:
        s = wait_for(lambda s: s.name == stream and s.level == DiagnosticStatus.WARN
                     and "no image" in s.message, False, "WARN no image")
        assert "no image on /cam1/image" in s.message and "none yet" in s.message
        s = wait_for(lambda s: s.name == live and float(
            diagnostic_values(s)["rate.depth_hz"]) > 5, True, "with the camera's rate")
        assert 5 < float(diagnostic_values(s)["rate.image_hz"]) < 40
        s = wait_for(lambda s: s.name == worker, False, "the worker's status")
        assert diagnostic_values(s)["worker_alive"] == "true"
        refiner.online.stop(10)  # the worker gone: no window will run again
        s = wait_for(lambda s: s.name == worker and s.level == DiagnosticStatus.ERROR, False,
                     "ERROR")
        assert s.message.startswith("window worker has died")
        assert diagnostic_values(s)["worker_alive"] == "false"
        s = wait_for(lambda s: s.name == stream and s.level == DiagnosticStatus.ERROR, False,
                     "the stream's ERROR")
        assert s.message.startswith("window worker has died")
        assert not any(s.level == DiagnosticStatus.STALE for s in statuses)
    finally:
        executor.shutdown()
        refiner.destroy_node()
        camera.destroy_node()


def rclpy_node(name: str, context):
    from rclpy.node import Node

    return Node(name, context=context)
