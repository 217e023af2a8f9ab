"""How frames leave the stream: each :class:`~.records.FrameOutput` counted (the
:class:`~.frame_queue.FrameQueue`'s ledger) before it goes to the sink, a frame no window refines
predicted again with the latest weights unless the live output served it (docs/node.md, "How
frames flow", rule 5), each dropped frame counted and reported (a throttled warning, the
sink)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from sfm_ttr_ros.core.frames import Frame
from sfm_ttr_ros.core.metric.scale import in_metres
from sfm_ttr_ros.core.outcomes import Dropped, Unrefined
from sfm_ttr_ros.core.pipeline import SfmTTR, WindowResult
from sfm_ttr_ros.core.stream.admission import Verdict
from sfm_ttr_ros.core.stream.frame_queue import RELEASED_IMAGE, FrameQueue
from sfm_ttr_ros.core.stream.records import FrameOutput, WindowStats
from sfm_ttr_ros.core.stream.throttle import Throttle


class FrameOutlet:
    """The outputs of one stream, on the worker's thread (module docstring).

    ``republish``: whether unrefined frames the live output served are predicted again
    (``StreamSettings.republish_unrefined``, read at each call). Sinks: ``on_output``,
    ``on_drop(frame_or_None, reason_key, message)``."""

    def __init__(self, ttr: SfmTTR, queue: FrameQueue, republish: Callable[[], bool],
                 on_output: Callable[[FrameOutput], None] | None,
                 on_drop: Callable[[Frame | None, str, str], None] | None, log) -> None:
        self.ttr = ttr
        self.queue = queue
        self.republish = republish
        self.on_output = on_output
        self.on_drop = on_drop
        self.log = log
        self._throttle = Throttle()

    def window(self, new: Sequence[Frame], res: WindowResult, stats: WindowStats,
               ran: bool) -> list[FrameOutput]:
        """The ``new`` frames of window ``stats``: with the depths of the core's ``res`` when
        the window ``ran``, else unrefined with its reason."""
        if not ran:
            return self.unrefined(new, stats.reason_key, stats.reason, window=stats.index)
        k = None if self.ttr is None else self.ttr.metres_per_unit
        outs = [FrameOutput(f, in_metres(res.depths[f.name], k), res.refined, stats.reason_key,
                            stats.reason, window=stats.index, metres_per_unit=k) for f in new]
        self._account(outs)
        return outs

    def unrefined(self, frames: Sequence[Frame], key: Unrefined, reason: str,
                  window: int | None = None) -> list[FrameOutput]:
        """Publish ``frames`` unrefined, predicted with the latest weights - except the frames
        the live output already served, unless ``republish``: those come out with ``depth``
        None (:attr:`FrameOutput.live_only`), counted under ``key`` all the same. Under
        overload this is most frames, and predicting them again took ~40 % of the worker's
        time that windows then lacked (BENCHMARKS.md "Live latency and the live share")."""
        if not frames:
            return []
        again = self.republish()
        todo = [f for f in frames
                if f.image is not RELEASED_IMAGE and (again or not f.served_live)]
        depths: dict[int, np.ndarray] = {}
        failure = ""
        if todo:
            try:
                depths = dict(zip(map(id, todo),
                                  self.ttr.predictor.predict([f.image for f in todo]),
                                  strict=True))
            except Exception as exc:
                failure = f"prediction failed ({type(exc).__name__}: {exc}): frame(s) dropped"
                self.queue.drop_taken(todo, Dropped.PREDICTION_ERROR)
                for f in todo:
                    self.drop(f, Dropped.PREDICTION_ERROR, failure)
                failed = set(map(id, todo))
                frames = [f for f in frames if id(f) not in failed]
        k = None if self.ttr is None else self.ttr.metres_per_unit
        outs = [FrameOutput(f, in_metres(depths.get(id(f)), k), False, key, reason, window,
                            metres_per_unit=k) for f in frames]
        self._account(outs)
        if failure:  # logged once every frame is out: a log that fails loses none
            self.log.error(failure)
        return outs

    def release_taken(self, key: Unrefined, reason: str) -> list[FrameOutput]:
        """Every frame in the worker's hands (:meth:`FrameQueue.taken`) published unrefined
        under ``key``, oldest first; those the outlet itself failed to put out are counted
        under ``key`` all the same, without a depth (never left pending)."""
        try:
            return self.unrefined(self.queue.taken(), key, reason)
        finally:
            left = self.queue.taken()
            if left:
                self.queue.settle([FrameOutput(f, None, False, key, reason) for f in left])

    def verdict(self, frame: Frame, v: Verdict, flushed: Sequence[Frame]) -> list[FrameOutput]:
        """What an admission verdict says, in its order (:class:`~.admission.Verdict`): the
        ``flushed`` keyframes unrefined under ``v.flush``, the frame dropped or published
        unrefined, then its log lines (each at its one severity), so a log that fails loses no
        frame."""
        outs: list[FrameOutput] = []
        if v.drop is not None:
            self.queue.drop_taken([frame], v.drop)
            self.drop(frame, v.drop, v.reason)
        else:
            outs = self.unrefined(flushed, v.flush, v.reason) if flushed else []
            if v.unrefined is not None:
                outs += self.unrefined([frame], v.unrefined, v.reason)
        if v.throttle:
            self.warn(v.throttle, v.warning)
        elif v.warning:
            self.log.warning(v.warning)
        if v.info:
            self.log.info(v.info)
        return outs

    def _account(self, outs: list[FrameOutput]) -> None:
        """Count ``outs``, then hand each to the sink; a sink that raises on one output still
        gets the others, and the first exception is raised after the last (a fault of the
        worker: :meth:`WindowRunner.recover`)."""
        self.queue.settle(outs)
        if self.on_output is None:
            return
        failed: Exception | None = None
        for o in outs:
            try:
                self.on_output(o)
            except Exception as exc:  # noqa: BLE001 - raised once every output is out
                failed = failed or exc
        if failed is not None:
            raise failed

    def overflow(self, frame: Frame, max_pending: int) -> None:
        """Report the frame the full queue dropped (counted by the queue)."""
        with self.queue.locked() as ledger:
            n = ledger.dropped[Dropped.OVERFLOW]
        self.drop(frame, Dropped.OVERFLOW,
                  f"input queue full (max_pending={max_pending}): dropped the oldest pending "
                  f"frame (stamp {frame.stamp:.6f}); {n} dropped so far")

    def drop(self, frame: Frame | None, key: Dropped, message: str) -> None:
        """Report a dropped frame (already counted): the sink, then a throttled warning."""
        if self.on_drop is not None:
            self.on_drop(frame, key, message)
        self.warn(f"drop:{key}", message)

    def warn(self, key: str, message: str) -> None:
        """Log a warning at most once per :data:`~sfm_ttr_ros.core.stream.throttle.WARN_PERIOD_S`
        per key."""
        if self._throttle.due(key):
            self.log.warning(message)
