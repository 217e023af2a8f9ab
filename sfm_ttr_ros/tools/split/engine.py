"""Where a split's tasks run: in this process one after the other, or as Ray tasks.

* In process (``--workers 1`` without ``--ray-address``; Ray not needed): each sequence in turn,
  as ``sfm-ttr benchmark`` runs one today.
* Ray: ``--workers N`` starts a local Ray instance for the command (N x threads CPUs) and stops
  it at the end; ``--ray-address ADDRESS`` joins a running cluster (its CPUs decide how many
  tasks run at once) and leaves it running. One task per sequence (all of its modes: they share
  the opened sequence and the network), declaring ``threads`` CPUs and, with a CUDA device,
  ``gpus`` GPUs. Ray's own retries are off: a task whose worker died (killed, out of memory, its
  node lost) is submitted again here, at most ``retries`` times, and counted; a task that
  answers ``failed`` (its data, or an error of the method) is not retried.
* Ctrl-C (KeyboardInterrupt): the tasks still running are cancelled, the outcomes already in are
  kept (each was stored when it arrived) and :class:`Interrupted` carries the statistics.
"""

from __future__ import annotations

import logging
import socket
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.tools.split.spec import SequenceSpec
from sfm_ttr_ros.tools.split.task import (
    TASK_ERROR,
    WORKER_LOST,
    SequenceOutcome,
    SplitJob,
    run_sequence,
)

log = logging.getLogger("sfm_ttr_ros.tools.split")

OnOutcome = Callable[[SequenceSpec, SequenceOutcome, int], None]


@dataclass
class EngineConfig:
    """``workers`` tasks at once on a local instance (1 without ``address``: in process),
    ``threads`` CPUs per task, ``gpus`` GPUs per task (0: none), ``retries`` new attempts of a
    task whose worker died, ``address`` of a running Ray cluster (None: local)."""

    workers: int = 1
    threads: int = 1
    gpus: float = 0.0
    retries: int = 2
    address: str | None = None

    def __post_init__(self) -> None:
        if self.workers < 1 or self.threads < 1 or self.retries < 0 or self.gpus < 0:
            raise InputError("--workers and the threads per worker must be >= 1, --retries and "
                             "the GPUs per task >= 0")

    @property
    def uses_ray(self) -> bool:
        return self.workers > 1 or self.address is not None


@dataclass
class EngineStats:
    """What happened besides the outcomes: the attempts that died and were retried (sequence
    id -> retries), where it ran."""

    retried: dict[str, int] = field(default_factory=dict)
    where: str = "in process"
    seconds: float = 0.0

    @property
    def retries(self) -> int:
        return sum(self.retried.values())


class Interrupted(Exception):  # noqa: N818 - raised for a KeyboardInterrupt, named as one
    """Ctrl-C during a split: ``stats`` as far as it went."""

    def __init__(self, stats: EngineStats) -> None:
        super().__init__("interrupted")
        self.stats = stats


def sequence_task(spec: SequenceSpec, job: SplitJob) -> SequenceOutcome:
    """The Ray task (named ``sequence_task:<id>``: its worker's process title is
    ``ray::sequence_task:<id>`` while it runs, as ``ray list tasks`` shows it)."""
    return run_sequence(spec, job)


def run_tasks(specs: Sequence[SequenceSpec], job: SplitJob, config: EngineConfig,
              on_outcome: OnOutcome) -> EngineStats:
    """Run every spec; ``on_outcome(spec, outcome, attempts)`` as each one ends (in the order
    they end). :class:`Interrupted` on Ctrl-C."""
    if config.uses_ray:
        return _run_ray(specs, job, config, on_outcome)
    stats = EngineStats(where="in process")
    t0 = time.perf_counter()
    try:
        for spec in specs:
            on_outcome(spec, run_sequence(spec, job), 1)
    except KeyboardInterrupt:
        stats.seconds = time.perf_counter() - t0
        raise Interrupted(stats) from None
    stats.seconds = time.perf_counter() - t0
    return stats


def import_ray():
    """The ray module; :class:`InputError` with the install command when it is missing."""
    try:
        import ray
    except ImportError as exc:
        raise InputError("--workers > 1 and --ray-address need Ray: pip install -e '.[cluster]' "
                         f"(or run with --workers 1, in this process): {exc}") from exc
    return ray


#: How long :func:`check_cluster_address` waits for the cluster's port to answer, s.
REACH_TIMEOUT_S = 5.0


def check_cluster_address(address: str | None, timeout: float = REACH_TIMEOUT_S) -> None:
    """:class:`InputError` unless something listens at ``--ray-address`` (``HOST:PORT`` or
    ``ray://HOST:PORT``; ``auto`` is left to Ray). Checked before any work: ``ray.init`` towards
    an address where nothing answers retries for minutes before it raises."""
    if not address or address == "auto":
        return
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise InputError(f"--ray-address {address!r}: expected HOST:PORT (the head node's GCS "
                         "address, e.g. 10.0.0.1:6379), ray://HOST:PORT or auto")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout).close()
    except OSError as exc:
        why = exc.strerror or type(exc).__name__
        raise InputError(f"--ray-address {address}: no Ray cluster answers there ({why}); "
                         f"start its head (ray start --head --port {port}) or check the "
                         "address") from None


def _start(ray, config: EngineConfig) -> str:
    common = {"include_dashboard": False, "log_to_driver": False,
              "logging_level": logging.WARNING, "configure_logging": True}
    if config.address:  # something answers there: checked before any work (command.py)
        try:
            ray.init(address=config.address, **common)
        except (ConnectionError, TimeoutError) as exc:  # something answers, not a Ray head
            raise InputError(f"--ray-address {config.address}: cannot join a Ray cluster "
                             f"there: {str(exc).splitlines()[0] if str(exc) else exc!r}") from None
        res = ray.cluster_resources()
        if res.get("CPU", 0) < config.threads:
            raise InputError(f"the cluster at {config.address} has {res.get('CPU', 0):g} CPUs: "
                             f"a task needs {config.threads} (lower --threads-per-worker)")
        if config.gpus and res.get("GPU", 0) < config.gpus:
            raise InputError(f"the cluster at {config.address} has {res.get('GPU', 0):g} GPUs: "
                             f"a task needs {config.gpus:g} (device cuda)")
        return (f"Ray cluster {config.address}: {res.get('CPU', 0):g} CPUs, "
                f"{res.get('GPU', 0):g} GPUs, {len(ray.nodes())} node(s)")
    # address="local": a new instance even where RAY_ADDRESS names a running cluster
    ray.init(address="local", num_cpus=config.workers * config.threads, **common)
    res = ray.cluster_resources()
    if config.gpus and res.get("GPU", 0) < config.gpus:
        raise InputError(f"device cuda: this machine's Ray instance sees {res.get('GPU', 0):g} "
                         "GPUs")
    return f"local Ray: {config.workers} workers x {config.threads} threads"


def _run_ray(specs: Sequence[SequenceSpec], job: SplitJob, config: EngineConfig,
             on_outcome: OnOutcome) -> EngineStats:
    ray = import_ray()
    from ray import exceptions as rx

    stats = EngineStats()
    t0 = time.perf_counter()
    pending: dict = {}
    try:
        stats.where = _start(ray, config)
        task = ray.remote(sequence_task)
        job_ref = ray.put(job)

        def submit(spec: SequenceSpec, attempt: int) -> None:
            ref = task.options(num_cpus=config.threads, num_gpus=config.gpus, max_retries=0,
                               retry_exceptions=False, name=f"sequence_task:{spec.id}"
                               ).remote(spec, job_ref)
            pending[ref] = (spec, attempt)

        for spec in specs:
            submit(spec, 1)
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
            for ref in ready:
                spec, attempt = pending.pop(ref)
                try:
                    outcome = ray.get(ref)
                except rx.RayTaskError as exc:  # raised in the task, past run_sequence's net
                    outcome = SequenceOutcome(spec.id, "failed", reason_key=TASK_ERROR,
                                              reason=f"task error: {exc.cause!r}")
                except rx.TaskCancelledError:
                    continue
                except rx.RayError as exc:  # the worker or its node died: not the data
                    what = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
                    if attempt <= config.retries:
                        stats.retried[spec.id] = stats.retried.get(spec.id, 0) + 1
                        log.warning("%s: worker lost (%s); attempt %d of %d", spec.id, what,
                                    attempt + 1, config.retries + 1)
                        submit(spec, attempt + 1)
                        continue
                    outcome = SequenceOutcome(spec.id, "failed", reason_key=WORKER_LOST,
                                              reason=f"worker lost on each of {attempt} "
                                              f"attempts (last: {what})")
                on_outcome(spec, outcome, attempt)
    except KeyboardInterrupt:
        for ref in pending:
            try:
                ray.cancel(ref, force=True)
            except Exception as exc:  # noqa: BLE001 - cancelling is best effort
                log.debug("cancel: %s", exc)
        stats.seconds = time.perf_counter() - t0
        raise Interrupted(stats) from None
    finally:
        if ray.is_initialized():
            ray.shutdown()
    stats.seconds = time.perf_counter() - t0
    return stats
