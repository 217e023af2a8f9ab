"""What the node reports on ``/diagnostics``, ROS-free: the counters the stream does not keep
(rejected CameraInfos, incompatible-QoS events, frames published unrefined since the last
report, faults contained in a callback) and the status built from them and from the stream's
frame accounting.

A *fault* is an exception no check foresaw, caught at a callback boundary of the node (a
subscription, the timer, the parameter callback, the worker, a publication) so that it cannot
end the process: counted per place (``faults.<place>``), logged (throttled) and reported as a
WARN status; the frame it concerned, if any, is still accounted for (dropped with a reason).

``msg_adapters.make_diagnostic_array`` turns a :class:`Status` into a DiagnosticArray; the keys
are listed in README "Diagnostics". The frame accounting of the windowed output
(``~/depth_refined``) always satisfies
``frames_received = frames_refined + frames_unrefined + frames_dropped + frames_pending``
(frames held for want of intrinsics count as received and pending); that of the live output
(``~/depth``, when a ``live`` provider is given) ``live.received = live.published +
live.skipped + live.pending``, with the served weights' ``serving.version`` (the window that
produced them, 0 = start-up), ``serving.interim_step`` (the refinement step of interim weights
of a window still refining, ``serve_every_steps``; 0 = a finished window's) and
``serving.age_s``.

A depth image published without a CameraInfo beside it (the node knew no intrinsics for it
yet: no CameraInfo received and no fallback) is counted, per output:
``live.without_camera_info`` and ``frames_without_camera_info`` (the windowed output); the
status is WARN while it happens.

With a :class:`~sfm_ttr_ros.core.stream.health.Health` (the node gives one) the values also hold
the input and output rates, and the status is ERROR when the window worker has died and STALE
when no image arrived for ``diagnostics.stale_after_s`` (core/stream/health.py).
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Callable
from dataclasses import dataclass, field

from sfm_ttr_ros.core.outcomes import Dropped, Unrefined
from sfm_ttr_ros.core.stream.health import Health
from sfm_ttr_ros.core.stream.keyframes import keyframe_interval
from sfm_ttr_ros.core.stream.live import LATENCY_KEYS
from sfm_ttr_ros.core.stream.window_runner import WindowRunner

#: Unrefined frames the keyframe rule passed on by design (below its floor or motion, or skipped
#: behind): counted under their reason, no WARN (a 10-Hz camera on 2 CPU cores under
#: keyframe_policy newest makes them all the time; keyframes.needed_s says what would keep up).
SELECTED_OUT = frozenset({Unrefined.NOT_KEYFRAME, Unrefined.STALE})


@dataclass(frozen=True)
class Status:
    """One diagnostic status: ``level`` ``"ok"``, ``"warn"``, ``"error"`` or ``"stale"``, a
    one-line message and the key/values in the order they are published."""

    level: str
    message: str
    values: dict[str, object] = field(default_factory=dict)


class StreamDiagnostics:
    """Counters and status of a :class:`WindowRunner` fed by a node. Thread-safe.

    ``held``: how many frames wait outside the stream (for intrinsics); they count as received
    and pending. ``health``: rates, ERROR and STALE (none: OK or WARN only).
    """

    def __init__(self, stream: WindowRunner, held: Callable[[], int] = lambda: 0,
                 live: Callable[[], dict] | None = None, health: Health | None = None):
        self.stream = stream
        self.health = health
        self._held = held
        self._live = live
        self.rejected_camera_info = 0
        self.qos_incompatible: collections.Counter[str] = collections.Counter()
        self._unrefined_since_status = 0
        self.faults: collections.Counter[str] = collections.Counter()
        self._faults_since_status = 0
        #: depth images published without a CameraInfo, per output ("live", "refined")
        self.without_camera_info: collections.Counter[str] = collections.Counter()
        self._without_camera_info_since_status = 0
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
            self._without_camera_info_since_status += 1
            return self.without_camera_info[output]

    def output_published(self, refined: bool, reason_key: Unrefined | None = None) -> None:
        """A frame left the windowed output; unrefined ones make the next status a WARN,
        except those the keyframe rule passed on by design (SELECTED_OUT)."""
        if not refined and reason_key not in SELECTED_OUT:
            with self._lock:
                self._unrefined_since_status += 1

    # -- reporting -----------------------------------------------------------------------------
    def values(self) -> dict[str, object]:
        """Every key/value of the status (README "Diagnostics"), in publishing order."""
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
            "faults": sum(self.faults.values()),
        })
        v.update({f"faults.{k}": n for k, n in sorted(self.faults.items())})
        if self.health is not None:  # rates, silence, the worker
            v.update(self.health.values())
        if self._live is not None:  # ~/depth: received = published + skipped + pending
            v.update(self._live_values())
        v.update(self._keyframe_values())
        v.update(self._streaming_sfm_values(c.get("sfm_streaming") or {}))
        metric = getattr(self.stream.ttr, "metric_status", None)
        if metric is not None:  # the outputs' units (core/metric/)
            v.update({f"metric.{k}": x for k, x in metric().values().items()})
        v.update(self._last_window_values())
        if self.intrinsics_values is not None:
            v.update(self.intrinsics_values())
        return v

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
        against those mapped afresh, and the front end's lag: keyframes admitted but not
        registered into the map yet, frames queued for the worker (waiting for features)."""
        if not st:
            return {}
        return {"sfm.windows_continued": st["continued"], "sfm.windows_fresh": st["fresh"],
                "sfm.admitted_unmapped": st["admitted_unmapped"],
                "sfm.waiting_for_features": self.stream.queued()}

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

    def status(self) -> Status:
        """The status now: ERROR (the worker died) or STALE (no input) first in the message,
        then what went wrong since the last status (frames passed through unrefined, the last
        window not refined, frames held, incompatible QoS, faults contained) at WARN, else OK.
        Resets the since-last-status counts."""
        with self._lock:
            v = self.values()
            w = self.stream.last_window
            problems = []
            if self._unrefined_since_status:
                problems.append(f"{self._unrefined_since_status} frame(s) passed through "
                                "unrefined")
            if w is not None and not w.refined:
                problems.append(f"last window not refined: {w.reason}")
            if v.get("metric.state") == "waiting" and w is not None:
                problems.append("depth not metric yet" + (f": {w.metric_reason}"
                                                          if w.metric_reason else ""))
            if v["frames_held_no_intrinsics"]:
                problems.append("no intrinsics: frames held")
            if v["qos_incompatible"]:
                problems.append("incompatible QoS")
            if self._faults_since_status:
                problems.append(f"{self._faults_since_status} fault(s) contained")
            if self._without_camera_info_since_status:
                problems.append(f"{self._without_camera_info_since_status} depth image(s) "
                                "without CameraInfo (no intrinsics yet)")
            self._unrefined_since_status = 0
            self._faults_since_status = 0
            self._without_camera_info_since_status = 0
        severe = self.health.problem() if self.health is not None else None
        if severe is not None:
            return Status(severe[0], "; ".join([severe[1], *problems]), v)
        if problems:
            return Status("warn", "; ".join(problems), v)
        return Status("ok", f"{v['frames_refined']} refined, {v['windows_ok']} window(s) ok", v)
