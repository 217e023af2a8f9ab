"""One diagnostic status of the node, ROS-free, and the concerns it reports one status each
(docs/node.md "Diagnostics"): ``stream`` (frames, windows, the accounting, the input),
``scale`` (the depth's units), ``live`` (live serving: its accounting, latencies and the
rates) and ``worker`` (the window worker alive, faults contained). ROS names each status
``<node name>: <task>`` as diagnostic_updater does (ros/names.py ``status_name``)."""

from __future__ import annotations

from dataclasses import dataclass, field

STREAM_TASK = "stream"
SCALE_TASK = "scale"
LIVE_TASK = "live"
WORKER_TASK = "worker"
#: every concern with a status, in publishing order
TASKS = (STREAM_TASK, SCALE_TASK, LIVE_TASK, WORKER_TASK)


@dataclass(frozen=True)
class Status:
    """One diagnostic status: ``level`` ``"ok"``, ``"warn"`` or ``"error"``, a one-line
    message, the key/values in the order they are published and the ``task`` (one of
    :data:`TASKS`) it reports on."""

    level: str
    message: str
    values: dict[str, object] = field(default_factory=dict)
    task: str = STREAM_TASK
