"""Containment of the ``refiner`` node's callbacks: an exception no check foresaw is counted
and logged, never fatal (docs/node.md, "Fault containment").

:func:`contained` wraps a callback of the node (subscriptions, QoS events, the timer, the
worker's publications): the exception becomes a fault of its place (``faults.<place>`` on
/diagnostics), logged with :func:`where` it was raised, and the node goes on.
:class:`ThrottledLog` writes such lines at most once per ``WARN_PERIOD_S`` per key.
"""

from __future__ import annotations

import functools
import traceback
from pathlib import Path

from sfm_ttr_ros.core.stream.throttle import Throttle


def where(exc: BaseException) -> str:
    """``file:line in function`` where ``exc`` was raised (its innermost frame), for a one-line
    log without a traceback."""
    frames = traceback.extract_tb(exc.__traceback__)
    if not frames:
        return "?"
    f = frames[-1]
    return f"{Path(f.filename).name}:{f.lineno} in {f.name}"


def contained(place: str):
    """Decorator of a node callback: an exception is handed to the node's ``fault(place, exc)``
    (counted and logged, throttled) instead of reaching the executor or the worker."""
    def wrap(method):
        @functools.wraps(method)
        def call(self, *args):
            try:
                return method(self, *args)
            except Exception as exc:
                self.fault(place, exc)
                return None
        return call
    return wrap


def fault_message(place: str, exc: BaseException, count: int) -> str:
    """The log line of the ``count``-th fault contained at ``place``."""
    return (f"{place}: contained {type(exc).__name__}: {exc} (at {where(exc)}; {count} so "
            "far); the node goes on")


class ThrottledLog:
    """A logger's warnings and errors, at most one per ``WARN_PERIOD_S`` per key. Each
    severity has its own call site: rclpy refuses one call site logging at two severities."""

    def __init__(self, logger) -> None:
        self._logger = logger
        self._throttle = Throttle()

    def warn_every(self, key: str, message: str) -> None:
        """Log the warning ``message`` unless ``key`` logged one within the period."""
        if not self._throttle.due(key):
            return
        try:
            self._logger.warning(message)
        except Exception:  # noqa: S110 - a log that cannot be written must not become a fault
            pass

    def error_every(self, key: str, message: str) -> None:
        """Log the error ``message`` unless ``key`` logged one within the period."""
        if not self._throttle.due(key):
            return
        try:
            self._logger.error(message)
        except Exception:  # noqa: S110 - a log that cannot be written must not become a fault
            pass
