"""The online refiner without ROS: live depth in front, windowed SfM-TTR behind.

One object the ROS node and the benchmark's live mode both drive, so they run the same code:

* :meth:`StreamRefiner.submit_live` — every frame, at once, to the
  :class:`~sfm_ttr_ros.core.stream.live.LiveServer` (its own thread): depth from the serving copy of
  the network (:class:`~sfm_ttr_ros.core.stream.serving.ServingModel`), no intrinsics needed.
* :meth:`StreamRefiner.submit` — frames with intrinsics to the
  :class:`~sfm_ttr_ros.core.stream.window_runner.WindowRunner`, stepped by a background worker
  thread at a lower OS priority (``StreamSettings.worker_nice``) with an OpenMP team of its own
  (``StreamSettings.worker_threads``, :mod:`~sfm_ttr_ros.core.threads`): keyframes, windows,
  SfM, alignment, refinement; each window's frames come out again on ``on_refined`` (today's
  windowed output).
* When a window is refined (and not rolled back) its encoder is swapped into the serving copy:
  version = window index + 1 (0 = the start-up weights). A window that fails, is skipped or
  is rolled back leaves the served weights unchanged.
* With ``StreamSettings.serve_every_steps = N`` the refining window's weights are also served
  after N/4 and N/2 steps, then every N (:func:`~sfm_ttr_ros.core.stream.serving.interim_due`,
  :meth:`~sfm_ttr_ros.core.stream.serving.ServingModel.preview`, same version,
  ``interim_step`` = the step), so a frame gets part of a window's gain seconds before the window
  ends; when the window then ends without being accepted the weights from before it are served
  again (:meth:`~sfm_ttr_ros.core.stream.serving.ServingModel.revert`). The pipeline calls the step
  hook only when no check after refinement can still refuse the window.

No prediction twice: under the ``continue`` weight policy the weights an accepted window leaves
are the next window's starting weights, and the serving copy gets the same ones; from then on
the live server's depth of each frame (network units) is handed to the window that takes it
(:class:`~sfm_ttr_ros.core.prediction.LiveDepths`), so the window does not predict it again
(``ttr.reuse_live_predictions``; counted in the window's ``predictions``). Frames served with
interim, reverted or older weights are predicted again.

Weights across windows follow ``TTRConfig.weight_policy`` (reset, continue, continual: see
:mod:`sfm_ttr_ros.core.pipeline`); whatever the policy, the serving copy keeps only weights
of a window that finished refined (interim ones are withdrawn when their window is not).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from sfm_ttr_ros.core import threads
from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.pipeline import SfmTTR, TTRConfig
from sfm_ttr_ros.core.prediction import LiveDepths
from sfm_ttr_ros.core.refinement.encoder import warm_up_optimiser
from sfm_ttr_ros.core.stream.live import WARM_UP_WAIT_S, LiveOutput, LiveServer
from sfm_ttr_ros.core.stream.records import FrameOutput, WindowStats
from sfm_ttr_ros.core.stream.serving import ServingModel, interim_due
from sfm_ttr_ros.core.stream.settings import StreamSettings
from sfm_ttr_ros.core.stream.window_runner import WindowRunner

#: Windows whose serving times :attr:`StreamRefiner.served_at` keeps.
SERVED_HISTORY = 1000


class StreamRefiner:
    """Live serving plus background windows over one network (see the module docstring).

    ``on_live(LiveOutput)``, ``on_refined(FrameOutput)``, ``on_window(WindowStats)`` and
    ``on_drop(frame, key, message)`` are the sinks; ``config_provider`` /
    ``settings_provider`` give the live parameters (read at each window / frame); ``on_fault
    (place, exc)`` hears of an exception the worker survived (default: logged)."""

    def __init__(self, ttr: SfmTTR, settings: StreamSettings | None = None, *,
                 on_live: Callable[[LiveOutput], None] | None = None,
                 on_refined: Callable[[FrameOutput], None] | None = None,
                 on_window: Callable[[WindowStats], None] | None = None,
                 on_drop: Callable[[Frame | None, str, str], None] | None = None,
                 config_provider: Callable[[], TTRConfig] | None = None,
                 settings_provider: Callable[[], StreamSettings] | None = None,
                 on_fault: Callable[[str, Exception], None] | None = None,
                 logger=None) -> None:
        settings = settings or StreamSettings()
        self.log = logger or logging.getLogger(__name__)
        self.ttr = ttr
        self.on_window = on_window
        self.on_fault = on_fault
        self.stream = WindowRunner(ttr, settings, config_provider=config_provider,
                                      settings_provider=settings_provider,
                                      on_output=on_refined, on_window=self._window_done,
                                      on_drop=on_drop, logger=self.log)
        self.serving = ServingModel(ttr.model)
        # metric.source fixed: at once
        self.serving.set_metres_per_unit(ttr.metres_per_unit)
        # the live depths handed to the windows (at most the next window's frames)
        self.live_depths = LiveDepths(settings.window_size)
        ttr.predictor.live_depths = self.live_depths
        # the start-up weights serve the first frames: the first window may take their depths
        self.live_depths.bind(self.serving.generation, ttr.predictor, self.serving.model,
                              settings.window_size)
        self.live = LiveServer(self.serving, on_live or (lambda out: None),
                               max_queue=settings.live_max_queue, logger=self.log,
                               live_depths=self.live_depths)
        self._nice = settings.worker_nice
        ttr.sfm.nice = settings.worker_nice  # SfM ahead runs at the worker's priority
        self._threads = settings.worker_threads
        self._stop = threading.Event()
        self._worker: threading.Thread | None = None
        self.warm_up_s = float("nan")  # the worker's warm-up (SfmTTR.warm_up), s
        self.serving_updates = 0
        self.serving_update_errors = 0
        self.serving_previews = 0
        self.serving_reverts = 0
        self.serving_interim_refused = 0  # interim weights the window check kept from serving
        # window index -> {"interim": first interim swap, "final": accepted weights swapped in,
        # "withdrawn": interim weights taken back} (time.monotonic()) and "names": the window's
        # frames; the newest SERVED_HISTORY windows: the time line of sfm_ttr_live
        self.served_at: dict[int, dict] = {}
        ttr.on_refine_step = self._refine_step

    # -- input (any thread) ---------------------------------------------------------------------
    def submit_live(self, frame: Frame, arrival: float | None = None) -> None:
        """Serve this frame's depth as soon as possible (no intrinsics needed)."""
        self.live.submit(frame, arrival)

    def submit(self, frame: Frame, intrinsics: Intrinsics) -> None:
        """Queue a frame for the windowed refinement."""
        self.stream.submit(frame, intrinsics)

    # -- threads --------------------------------------------------------------------------------
    def start(self) -> None:
        """Start the worker and serving, each after paying its path's one-time costs in its own
        thread (:func:`~sfm_ttr_ros.core.refinement.encoder.warm_up_optimiser` here; then the
        worker's
        :meth:`~sfm_ttr_ros.core.pipeline.SfmTTR.warm_up`, then the serving copy's first
        forward pass), so that no live frame and no first window waits behind them. Returns when
        both are ready (``warm_up_s`` holds the worker's seconds)."""
        warm_up_optimiser()
        ready = threading.Event()
        self._worker = threading.Thread(target=self._work, args=(ready,), name="refiner-worker",
                                        daemon=True)
        self._worker.start()
        if not ready.wait(WARM_UP_WAIT_S):
            self.log.warning(f"worker: warm-up still running after {WARM_UP_WAIT_S:.0f} s")
        self.live.start(warm_up=self.serving.warm_up)

    def _work(self, ready: threading.Event | None = None) -> None:
        threads.lower_thread_priority(self._nice)  # before torch / pycolmap start threads from here
        try:
            self.warm_up_s = self.ttr.warm_up()
        except Exception as exc:  # noqa: BLE001 - a failed warm-up only costs the first window
            self.log.warning(f"worker: warm-up failed ({type(exc).__name__}: {exc}); the first "
                             f"window pays the one-time costs")
        finally:
            # this thread's own OpenMP team (core/threads.py), set after the warm-up: a path's
            # first use in a thread (oneDNN's convolution) resets the team to torch's count
            if self._threads:
                threads.set_thread_team(self._threads)
            if ready is not None:
                ready.set()
        while not self._stop.is_set():
            if not self.step_contained(timeout=0.1):
                time.sleep(0.1)

    def step_contained(self, timeout: float | None = 0.1) -> bool:
        """One step of the worker (:meth:`WindowRunner.step`); an exception is a fault: counted
        (``on_fault("worker", exc)``), then the frames the worker held are published unrefined
        (``worker_fault``) and the window state reset (:meth:`WindowRunner.recover`), any
        interim weights of the window withdrawn from serving. False after a fault."""
        try:
            self.stream.step(timeout=timeout)
            return True
        except Exception as exc:  # noqa: BLE001 - never let the worker die
            if self._stop.is_set():
                return False
            self._fault(exc)
            reason = f"worker fault: {type(exc).__name__}: {exc}"
        try:
            self.stream.recover(reason)
        except Exception as exc:  # noqa: BLE001 - the frames are counted all the same
            self._fault(exc)
        if self.serving.revert():
            self.serving_reverts += 1
        return False

    def _fault(self, exc: Exception) -> None:
        if self.on_fault is not None:
            self.on_fault("worker", exc)
        else:
            self.log.error(f"worker: {type(exc).__name__}: {exc}")

    def stop(self, timeout: float | None = 3.0) -> bool:
        """Cancel the running window, stop serving; True when the worker has ended
        (``timeout`` None: wait for it; the SfM workspace must not be closed under a worker
        still inside pycolmap)."""
        self._stop.set()
        self.stream.cancel()
        self.live.stop(timeout)
        if self._worker is not None:
            self._worker.join(timeout)
            return not self._worker.is_alive()
        return True

    @property
    def worker_alive(self) -> bool:
        return self._worker is not None and self._worker.is_alive()

    # -- windows --------------------------------------------------------------------------------
    def _refine_step(self, step: int) -> None:
        """After each refinement step (worker thread): on the interim schedule
        (:func:`interim_due`), serve the window's weights as they are (non-finite ones are not
        served), once the window check can vouch for them (:meth:`WindowJudge.interim_refusal`)."""
        if not interim_due(step, self.stream.settings.serve_every_steps):
            return
        why = self.ttr.checks.interim_refusal()
        if why:
            self.serving_interim_refused += 1
            self.log.info(f"interim weights after step {step} not served: {why}")
            return
        try:
            self.serving.preview(self.ttr.model.encoder.state_dict(),
                                 self.stream.windows_started, step)
            self.serving_previews += 1
            self._mark(self.stream.windows_started - 1, "interim")
        except ValueError as exc:
            self.log.warning(f"interim weights after step {step} not served: {exc}")

    def _window_done(self, stats: WindowStats) -> None:
        if stats.refined:
            try:
                generation = self.serving.update(self.ttr.model.encoder.state_dict(),
                                                 stats.index + 1,
                                                 self.ttr.metres_per_unit)
                self.serving_updates += 1
                self._hand_over_from(generation)
                self._mark(stats.index, "final")
            except Exception as exc:  # noqa: BLE001 - keep serving the previous weights
                self.serving_update_errors += 1
                self.log.error(f"window {stats.index}: weights not served: "
                               f"{type(exc).__name__}: {exc}")
                self._revert(stats)
        else:
            self._revert(stats)
            # the weights before the window stay; a parameter may have changed the factor
            self.serving.set_metres_per_unit(self.ttr.metres_per_unit)
        if self.on_window is not None:
            self.on_window(stats)

    def _hand_over_from(self, generation: int) -> None:
        """The served weights are now the window model's: under ``continue`` (the next window
        starts from them) the live depths of ``generation`` go to the next window."""
        if self.ttr.config.weight_policy == "continue":
            self.live_depths.bind(generation, self.ttr.predictor, self.serving.model,
                                  self.stream.settings.window_size)
        else:
            self.live_depths.unbind()

    def _mark(self, window: int, what: str) -> None:
        """Note when ``window``'s weights were first swapped into serving (``what``: interim
        or final); keeps the newest :data:`SERVED_HISTORY` windows."""
        marks = self.served_at.setdefault(window, {})
        marks.setdefault(what, time.monotonic())
        if "names" not in marks:
            marks["names"] = self.stream.running_names
        while len(self.served_at) > SERVED_HISTORY:
            del self.served_at[min(self.served_at)]

    def _revert(self, stats: WindowStats) -> None:
        """A window that ends not accepted: serve the weights from before its interim ones."""
        if self.serving.revert():
            self.serving_reverts += 1
            self._mark(stats.index, "withdrawn")
            self.log.info(f"window {stats.index} not accepted ({stats.reason}): its interim "
                          "weights withdrawn from serving")

    def counters_live(self) -> dict[str, object]:
        """The live server's counters, the served weights' version, interim step and age, the
        swaps (window ends, interim previews, reverts)."""
        return {**self.live.counters(), "serving_updates": self.serving_updates,
                "serving_update_errors": self.serving_update_errors,
                "serving_previews": self.serving_previews,
                "serving_reverts": self.serving_reverts,
                "serving_interim_refused": self.serving_interim_refused,
                "interim_step": self.serving.interim_step,
                "live_depths": self.live_depths.figures()}

    def counters(self) -> dict[str, object]:
        """The stream's counters plus the live server's under ``live``."""
        return {**self.stream.counters(), "live": self.counters_live()}
