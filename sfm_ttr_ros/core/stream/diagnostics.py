"""What the node reports on ``/diagnostics``, ROS-free: the counters the stream does not keep
(rejected CameraInfos, incompatible-QoS events, frames published unrefined since the last
report, faults contained in a callback) and one status per concern built from them and from the
stream's frame accounting (:mod:`.status`): ``stream``, ``scale``, ``live`` and ``worker``.

A *fault* is an exception no check foresaw, caught at a callback boundary of the node (a
subscription, the timer, the parameter callback, the worker, a publication) so that it cannot
end the process: counted per place (``faults.<place>``), logged (throttled) and reported as a
WARN of the ``worker`` status; the frame it concerned, if any, is still accounted for (dropped
with a reason).

``msg_adapters.make_diagnostic_status`` turns each :class:`Status` into a DiagnosticStatus; the
keys are listed in docs/node.md "Diagnostics". The frame accounting of the windowed output
(``~/depth_refined``, the ``stream`` status) always satisfies
``frames_received = frames_refined + frames_unrefined + frames_dropped + frames_pending``
(frames held for want of intrinsics count as received and pending); that of the live output
(``~/depth``, when a ``live`` provider is given; the ``live`` status) ``live.received =
live.published + live.skipped + live.pending``, with the served weights' ``serving.version``
(the window that produced them, 0 = start-up), ``serving.interim_step`` (the refinement step of
interim weights of a window still refining, ``serve_every_steps``; 0 = a finished window's)
and ``serving.age_s``.

A depth image published without a CameraInfo beside it (the node knew no intrinsics for it
yet: no CameraInfo received and no fallback) is counted, per output:
``live.without_camera_info`` and ``frames_without_camera_info`` (the windowed output); the
status of that output is WARN while it happens.

With a :class:`~sfm_ttr_ros.core.stream.health.Health` (the node gives one) the values also hold
the input and output rates (``live``), the input's silence (``stream``: WARN when no image
arrived for ``diagnostics.stale_after_s``) and whether the worker lives (``worker``, and
``stream``: ERROR when it has died).
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Callable

from sfm_ttr_ros.core.metric.scale import MetricStatus
from sfm_ttr_ros.core.outcomes import Dropped, Unrefined
from sfm_ttr_ros.core.stream.health import Health
from sfm_ttr_ros.core.stream.keyframes import keyframe_interval
from sfm_ttr_ros.core.stream.live import LATENCY_KEYS
from sfm_ttr_ros.core.stream.status import LIVE_TASK, SCALE_TASK, WORKER_TASK, Status
from sfm_ttr_ros.core.stream.window_runner import WindowRunner

#: Unrefined frames the keyframe rule passed on by design (below its floor or motion, or skipped
#: behind): counted under their reason, no WARN (a 10-Hz camera on 2 CPU cores under
#: keyframe_policy newest makes them all the time; keyframes.needed_s says what would keep up).
SELECTED_OUT = frozenset({Unrefined.NOT_KEYFRAME, Unrefined.STALE})


#: (level, message) of the ``scale`` status for the outputs' units now
ScaleDescription = Callable[[MetricStatus], tuple[str, str]]


def scale_level(status: MetricStatus) -> str:
    """The level of the depth's scale (the ``scale`` status, ``~/depth_scale``): OK in state
    ``metric``, WARN in every other (the depth not in metres, or in metres not yet confirmed
    by a second window, or whose source stopped)."""
    return "ok" if status.state == "metric" else "warn"


def describe_scale(status: MetricStatus) -> tuple[str, str]:
    """(level, message) of the ``scale`` status without the node's topic names (the node says
    which topic carries the depth: ros/units.py ``describe_depth``)."""
    metres = "in metres" if status.metres_per_unit is not None else "not in metres"
    why = f": {status.reason}" if status.reason else ""
    return scale_level(status), (f"depth {metres} (metric.source {status.source}, "
                                 f"{status.state}{why})")


class StreamDiagnostics:
    """Counters and status of a :class:`WindowRunner` fed by a node. Thread-safe.

    ``held``: how many frames wait outside the stream (for intrinsics); they count as received
    and pending. ``live``: the live output's counts (none: no ``live`` status without
    ``health``). ``health``: rates, silence and the worker (none: no ERROR). ``scale``: (level,
    message) of the ``scale`` status (:func:`describe_scale` by default; the node names its
    topics), given when the stream's model has a metric status.
    """

    def __init__(self, stream: WindowRunner, held: Callable[[], int] = lambda: 0,
                 live: Callable[[], dict] | None = None, health: Health | None = None,
                 scale: ScaleDescription = describe_scale):
        self.stream = stream
        self.health = health
        self._held = held
        self._live = live
        self._describe_scale = scale
        self.rejected_camera_info = 0
        self.qos_incompatible: collections.Counter[str] = collections.Counter()
        self._unrefined_since_status = 0
        self.faults: collections.Counter[str] = collections.Counter()
        self._faults_since_status = 0
        #: depth images published without a CameraInfo, per output ("live", "refined")
        self.without_camera_info: collections.Counter[str] = collections.Counter()
        self._without_camera_info_since_status: collections.Counter[str] = collections.Counter()
        #: where the intrinsics come from, ``intrinsics.*`` (the node's: ros/camera.py)
        self.intrinsics_values: Callable[[], dict[str, object]] | None = None
        self._lock = threading.Lock()

    # -- counting ------------------------------------------------------------------------------
    def camera_info_rejected(self) -> None:
        with self._lock:
            self.rejected_camera_info += 1

    def qos_event(self, what: str) -> None:
        """An incompatible-QoS event on ``what`` (a topic or an input's name)."""
        with self._lock:
            self.qos_incompatible[what] += 1

    def fault(self, place: str) -> int:
        """An exception contained at ``place`` (e.g. ``image_callback``); returns how many
        faults ``place`` has had so far."""
        with self._lock:
            self.faults[place] += 1
            self._faults_since_status += 1
            return self.faults[place]

    def camera_info_missing(self, output: str) -> int:
        """A depth image of ``output`` ("live" or "refined") went out without a CameraInfo;
        returns how many so far on that output."""
        with self._lock:
            self.without_camera_info[output] += 1
            self._without_camera_info_since_status[output] += 1
            return self.without_camera_info[output]

    def output_published(self, refined: bool, reason_key: Unrefined | None = None) -> None:
        """A frame left the windowed output; unrefined ones make the next status a WARN,
        except those the keyframe rule passed on by design (SELECTED_OUT)."""
        if not refined and reason_key not in SELECTED_OUT:
            with self._lock:
                self._unrefined_since_status += 1

    # -- reporting -----------------------------------------------------------------------------
    def values(self) -> dict[str, object]:
        """Every key/value of every status (docs/node.md "Diagnostics"), in publishing order:
        what the final accounting keeps."""
        out = self.stream_values()
        for part in (self.scale_values(), self.live_values(), self.worker_values()):
            out.update(part)
        return out

    def stream_values(self) -> dict[str, object]:
        """The ``stream`` status's key/values: the frames, the input, the windows."""
        c = self.stream.counters()
        held = int(self._held())
        v: dict[str, object] = {
            "frames_received": c["received"] + held,
            "frames_refined": c["refined"],
            "frames_unrefined": c["unrefined"],
            "frames_dropped": c["dropped"],
            "frames_pending": c["pending"] + held,
            "frames_held_no_intrinsics": held,
            # unrefined frames ~/depth already carried, not sent again (republish_unrefined off)
            "frames_live_only": c["live_only"],
            # among those: queued frames whose image the backlog bound released
            # (core/stream/frame_queue.py)
            "frames_backlog_released": c["backlog_released"],
            # ~/depth_refined images published without a CameraInfo beside them
            "frames_without_camera_info": self.without_camera_info["refined"],
        }
        v.update({f"unrefined.{k}": n for k, n in sorted(c["unrefined_by_reason"].items())})
        v.update({f"dropped.{k}": n for k, n in sorted(c["dropped_by_reason"].items())})
        v.update({
            "rejected_bad_image": c["dropped_by_reason"].get(Dropped.BAD_IMAGE, 0),
            "rejected_camera_info": self.rejected_camera_info,
            "non_monotonic_stamps": c["non_monotonic_stamps"],
            "qos_incompatible": sum(self.qos_incompatible.values()),
            "windows_ok": c["windows_ok"],
            "windows_failed": c["windows_failed"],
            "windows_skipped_overload": c["windows_skipped"],
            "windows_disabled": c["windows_disabled"],
            "windows_rejected_by_check": c["windows_rejected"],
            "windows_remapped": c["windows_remapped"],
        })
        if self.health is not None:  # the input's silence
            v.update(self.health.input_values())
        v.update(self._keyframe_values())
        v.update(self._streaming_sfm_values(c.get("sfm_streaming") or {}))
        v.update(self._last_window_values())
        if self.intrinsics_values is not None:
            v.update(self.intrinsics_values())
        return v

    def _metric_status(self) -> MetricStatus | None:
        metric = getattr(self.stream.ttr, "metric_status", None)
        return metric() if metric is not None else None

    def scale_values(self) -> dict[str, object]:
        """The ``scale`` status's key/values: the outputs' units (core/metric/); none without
        a model that has a metric status."""
        metric = self._metric_status()
        if metric is None:
            return {}
        return {f"metric.{k}": x for k, x in metric.values().items()}

    def live_values(self) -> dict[str, object]:
        """The ``live`` status's key/values: ~/depth's counts, the serving weights, the live
        latencies (with a ``live`` provider) and the rates (with ``health``)."""
        out: dict[str, object] = {}
        if self._live is not None:  # ~/depth: received = published + skipped + pending
            out.update(self._live_values())
        if self.health is not None:
            out.update(self.health.rate_values())
        return out

    def worker_values(self) -> dict[str, object]:
        """The ``worker`` status's key/values: alive (with ``health``), faults contained."""
        out: dict[str, object] = self.health.worker_values() if self.health is not None else {}
        out["faults"] = sum(self.faults.values())
        out.update({f"faults.{k}": n for k, n in sorted(self.faults.items())})
        return out

    def _live_values(self) -> dict[str, object]:
        """~/depth's counts, the serving weights and the live latencies."""
        lv = self._live()
        out: dict[str, object] = {
            "live.received": lv["received"], "live.published": lv["published"],
            "live.skipped": sum(lv["skipped"].values()), "live.pending": lv["pending"]}
        out.update({f"live.skipped.{k}": n for k, n in sorted(lv["skipped"].items())})
        out["live.without_camera_info"] = self.without_camera_info["live"]
        out.update({"serving.version": lv["version"], "serving.age_s": lv["weights_age_s"],
                    "serving.updates": lv["serving_updates"],
                    "serving.interim_step": lv["interim_step"],
                    "serving.previews": lv["serving_previews"],
                    "serving.reverts": lv["serving_reverts"],
                    "serving.interim_refused": lv["serving_interim_refused"]})
        out.update({f"live.{k}": lv[k] for k in LATENCY_KEYS})
        return out

    def _keyframe_values(self) -> dict[str, object]:
        """The keyframe rule now (core/stream/keyframes.py)."""
        kf, s = self.stream.keyframes, self.stream.settings
        interval, reason = keyframe_interval(s.min_keyframe_interval_s)
        return {"keyframes.policy": s.keyframe_policy, "keyframes.interval_s": interval,
                "keyframes.needed_s": kf.needed_s(s.window_stride),
                "keyframes.reason": reason, "keyframes.stale": kf.stale,
                "keyframes.behind_s": self.stream.behind_s()}

    def _streaming_sfm_values(self, st: dict[str, int]) -> dict[str, object]:
        """``sfm.mode`` streaming (none in batch mode): windows whose map was continued
        against those mapped afresh, the front end's lag (keyframes admitted but not
        registered into the map yet, frames queued for the worker: waiting for features), and
        the SfM processes that died and were replaced."""
        if not st:
            return {}
        return {"sfm.windows_continued": st["continued"], "sfm.windows_fresh": st["fresh"],
                "sfm.admitted_unmapped": st["admitted_unmapped"],
                "sfm.waiting_for_features": self.stream.queued(),
                "sfm.process_restarts": st["process_restarts"]}

    def _last_window_values(self) -> dict[str, object]:
        """The last window's outcome and timings (none before the first)."""
        w = self.stream.last_window
        if w is None:
            return {}
        out: dict[str, object] = {
            "last_window.index": w.index,
            "last_window.frames": len(w.names),
            "last_window.refined": w.refined,
            "last_window.reason": w.reason,
            "last_window.registered_frames": w.registered,
            "last_window.points_3d": w.points,
            "last_window.mapping_attempts": w.mapping_attempts,
            "last_window.sfm_mapping": w.sfm_mapping,
            "last_window.sfm_mapping_reason": w.sfm_mapping_reason,
            "last_window.reprojection_error_px": w.reprojection_error,
            "last_window.inlier_ratio": w.inlier_ratio,
            "last_window.scale": w.scale,
            "last_window.loss_before": w.loss_before,
            "last_window.loss_after": w.loss_after,
            "last_window.steps": w.steps,
            "last_window.steps_done": w.steps_done,
            "last_window.step_mode": w.step_mode,
            "last_window.unsupported_change": w.unsupported_change,
            "last_window.metric_estimate": w.metric_estimate,
            "last_window.metric_reason": w.metric_reason,
        }
        out.update({f"last_window.predictions.{k}": n for k, n in w.predictions.items()})
        out.update({f"last_window.time.{k}_s": t for k, t in w.timings.items()})
        return out

    def statuses(self) -> list[Status]:
        """One status per concern now: ``stream``, then ``scale`` (with a metric status),
        ``live`` (with a ``live`` provider or ``health``) and ``worker``. What went wrong since
        the last statuses is reported once (their counts reset), what lasts while it lasts."""
        with self._lock:
            out = [self._stream_status(), self._scale_status(), self._live_status(),
                   self._worker_status()]
            self._unrefined_since_status = 0
            self._faults_since_status = 0
            self._without_camera_info_since_status.clear()
        return [s for s in out if s is not None]

    def _stream_status(self) -> Status:
        """ERROR (the worker died: no window will run), else WARN for the input's silence and
        what went wrong since the last status (frames passed through unrefined, the last window
        not refined, frames held, incompatible QoS, ~/depth_refined without CameraInfo), else
        OK."""
        v = self.stream_values()
        w = self.stream.last_window
        problems = []
        if self._unrefined_since_status:
            problems.append(f"{self._unrefined_since_status} frame(s) passed through unrefined")
        if w is not None and not w.refined:
            problems.append(f"last window not refined: {w.reason}")
        if v["frames_held_no_intrinsics"]:
            problems.append("no intrinsics: frames held")
        if v["qos_incompatible"]:
            problems.append("incompatible QoS")
        if self._without_camera_info_since_status["refined"]:
            problems.append(_without_camera_info(
                self._without_camera_info_since_status["refined"]))
        silent = self.health.input_problem() if self.health is not None else None
        dead = self.health.worker_problem() if self.health is not None else None
        problems = [p for p in (dead, silent) if p] + problems
        if problems:
            return Status("error" if dead else "warn", "; ".join(problems), v)
        return Status("ok", f"{v['frames_refined']} refined, {v['windows_ok']} window(s) ok", v)

    def _scale_status(self) -> Status | None:
        """The depth's units (``describe_scale``); while waiting for a scale, why the last
        window gave none."""
        metric = self._metric_status()
        if metric is None:
            return None
        level, message = self._describe_scale(metric)
        w = self.stream.last_window
        if metric.state == "waiting" and w is not None and w.metric_reason:
            message += f"; last window: {w.metric_reason}"
        return Status(level, message, {f"metric.{k}": x for k, x in metric.values().items()},
                      SCALE_TASK)

    def _live_status(self) -> Status | None:
        """WARN while live depths go out without CameraInfo, else OK."""
        if self._live is None and self.health is None:
            return None
        v = self.live_values()
        missing = self._without_camera_info_since_status["live"]
        if missing:
            return Status("warn", _without_camera_info(missing), v, LIVE_TASK)
        if "live.published" not in v:
            return Status("ok", "rates only (no live output counts)", v, LIVE_TASK)
        return Status("ok", f"{v['live.published']} published, served weights of window "
                      f"{v['serving.version']}", v, LIVE_TASK)

    def _worker_status(self) -> Status:
        """ERROR when the worker has died, WARN for faults contained since the last status,
        else OK."""
        v = self.worker_values()
        dead = self.health.worker_problem() if self.health is not None else None
        problems = [dead] if dead else []
        if self._faults_since_status:
            problems.append(f"{self._faults_since_status} fault(s) contained")
        if problems:
            return Status("error" if dead else "warn", "; ".join(problems), v, WORKER_TASK)
        return Status("ok", f"{v['faults']} fault(s) contained so far", v, WORKER_TASK)


def _without_camera_info(n: int) -> str:
    return f"{n} depth image(s) without CameraInfo (no intrinsics yet)"
