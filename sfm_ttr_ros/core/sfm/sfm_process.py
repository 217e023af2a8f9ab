"""The streaming SfM in a process of its own (:class:`StreamingSfmProcess`).

pycolmap keeps Python's GIL in its SIFT extractor and its incremental mapper (the shared
notes on pycolmap's incremental mapper list what releases it and what does not): while the
window worker extracted a keyframe's features (~45-110 ms) or mapped a window (~0.35 s), no
other thread of the process ran Python, so the live server's frames waited behind it (a 10-Hz
generated drive on 2 cores: live latency p95 0.34 s, up to 0.7 s while SfM ran, under 0.1 s
the rest of the time; BENCHMARKS.md §4) and so did the ROS callbacks. Here the stream's
:class:`~sfm_ttr_ros.core.sfm.streaming_map.StreamingSfm` lives in a child process; each call is
sent over a pipe and the calling thread waits for the answer without the GIL. Same inputs,
same code, same results: only where it runs changes.

The child is started by the first call or by :meth:`StreamingSfmProcess.start` (the window
worker's warm-up): ``python -m sfm_ttr_ros.core.sfm.sfm_process`` on one end of a socket pair
(a fresh interpreter: no copy of the parent's torch threads, and unlike multiprocessing's
``spawn`` it never imports the parent's main script, which a script without a ``__main__``
guard would not survive), at the OS priority ``nice`` (the window worker's). It ignores SIGINT
(the parent ends it: :meth:`close`) and ends when the parent's end of the pair closes. A child
that dies (pycolmap crashed, killed) is counted (``restarts``) and the call raises
:class:`SfmProcessError`; the next call starts a fresh child, whose map is empty (the next
window maps afresh).
"""

from __future__ import annotations

import logging
import os
import pickle
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Sequence
from multiprocessing.connection import Connection

from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.sfm.frontend import AdmitTimings
from sfm_ttr_ros.core.sfm.result import SfmResult
from sfm_ttr_ros.core.sfm.sfm_config import SfmConfig
from sfm_ttr_ros.core.sfm.streaming_map import STATS_COUNTS, STATS_KEYS

#: How long :meth:`StreamingSfmProcess.close` waits for the child to end before killing it, s.
CLOSE_WAIT_S = 5.0


class SfmProcessError(RuntimeError):
    """The SfM process ended during a call (its map is lost)."""


class _Records(logging.Handler):
    """The child's log records, sent with each answer and logged again by the parent."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        record.msg, record.args, record.exc_info = record.getMessage(), None, None
        self.records.append(record)

    def take(self) -> list[logging.LogRecord]:
        taken, self.records = self.records, []
        return taken


def _serve(conn: Connection) -> None:
    """The child: one StreamingSfm (its options, OS priority and log level the first
    message; ``afresh`` replaces it), a call at a time, each answered with (ok, value, stats,
    log records). Ends when asked or when the parent's end closes."""
    from sfm_ttr_ros.core.sfm.streaming_map import StreamingSfm

    try:
        config, nice, level = conn.recv()
    except (EOFError, OSError):
        return
    if nice > 0:
        os.nice(nice)
    records = _Records()
    root = logging.getLogger()
    root.addHandler(records)
    root.setLevel(level)
    sfm = StreamingSfm(config)
    while True:
        try:
            name, args = conn.recv()
        except (EOFError, OSError):
            return
        if name == "close":
            return
        try:
            if name == "afresh":
                sfm, value = StreamingSfm(*args), None
            else:
                value = getattr(sfm, name)(*args)
            answer = (True, value)
        except Exception as exc:  # noqa: BLE001 - raised again in the parent
            answer = (False, exc)
        try:
            try:
                conn.send((*answer, sfm.stats(), records.take()))
            except (pickle.PicklingError, TypeError, AttributeError) as exc:  # not picklable
                conn.send((False, RuntimeError(f"{type(exc).__name__}: {exc}"), sfm.stats(),
                           records.take()))
        except OSError:  # the parent is gone
            return


class StreamingSfmProcess:
    """:class:`~sfm_ttr_ros.core.sfm.streaming_map.StreamingSfm`'s methods, run in a child
    process (module docstring). Thread-safe: one call at a time."""

    def __init__(self, config: SfmConfig | None = None, nice: int = 0) -> None:
        self.config = config or SfmConfig()
        self.nice = nice
        self.restarts = 0  # children that died and were replaced
        self._lock = threading.Lock()
        self._proc = None
        self._conn = None
        self._stats = dict.fromkeys(STATS_KEYS, 0)  # the child's, after its last answer
        # the counts of the StreamingSfm objects gone (a child that died, afresh): they only grow
        self._before = dict.fromkeys(STATS_COUNTS, 0)

    # -- the child ---------------------------------------------------------------------------
    def start(self) -> None:
        """Start the child now and wait until it answers (its imports paid)."""
        self._call("stats")

    def _start(self) -> None:
        ours, theirs = socket.socketpair()
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
        with theirs:
            self._proc = subprocess.Popen(
                [sys.executable, "-m", __name__, str(theirs.fileno())],
                pass_fds=[theirs.fileno()], env=env, stdin=subprocess.DEVNULL)
        self._conn = Connection(ours.detach())
        self._conn.send((self.config, int(self.nice), logging.getLogger().getEffectiveLevel()))

    def _call(self, name: str, *args):
        with self._lock:
            try:
                if self._proc is None:
                    self._start()
                self._conn.send((name, args))
                ok, value, stats, records = self._conn.recv()
            except (EOFError, OSError) as exc:
                code = self._end(kill=True)
                self.restarts += 1
                self._carry_counts(dict.fromkeys(STATS_KEYS, 0))
                raise SfmProcessError(f"the SfM process ended (exit code {code}) during "
                                      f"{name}: its map is lost, the next call starts a "
                                      "fresh one") from exc
            if name == "afresh" and ok:
                self._carry_counts(stats)
            else:
                self._stats = stats
        for record in records:
            logging.getLogger(record.name).handle(record)
        if not ok:
            raise value
        return value

    def _carry_counts(self, stats: dict[str, int]) -> None:
        """The StreamingSfm behind :attr:`_stats` is gone: its counts carried over, ``stats``
        the new one's."""
        for key in self._before:
            self._before[key] += self._stats[key]
        self._stats = stats

    def _end(self, kill: bool) -> int | None:
        """Forget the child (joined, killed when ``kill`` or when it does not end)."""
        proc, self._proc = self._proc, None
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        if proc is None:
            return None
        if kill:
            proc.kill()
        try:
            return proc.wait(CLOSE_WAIT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            return proc.wait()

    @property
    def pid(self) -> int | None:
        """The child's process id (None: not started)."""
        return self._proc.pid if self._proc is not None else None

    # -- StreamingSfm's methods ----------------------------------------------------------------
    def admit(self, frame: Frame, intrinsics: Intrinsics) -> AdmitTimings:
        return self._call("admit", frame, intrinsics)

    def reconstruct(self, frames: Sequence[Frame], intrinsics: Intrinsics) -> SfmResult:
        return self._call("reconstruct", list(frames), intrinsics)

    def retain(self, names: Sequence[str]) -> None:
        self._call("retain", list(names))

    def set_config(self, config: SfmConfig) -> None:
        self.config = config
        if self._proc is not None:
            self._call("set_config", config)

    def afresh(self, config: SfmConfig) -> None:
        """A new, empty StreamingSfm with ``config`` in the same child (the counts go on)."""
        self.config = config
        if self._proc is not None:
            self._call("afresh", config)

    def held_frames(self) -> list[str]:
        return self._call("held_frames")

    def stats(self) -> dict[str, int]:
        """The child's :meth:`StreamingSfm.stats` after its last answer (no call: never waits
        behind a running one); the counts include those of children that died."""
        stats = self._stats
        return {k: stats[k] + self._before.get(k, 0) for k in STATS_KEYS}

    def close(self) -> None:
        """End the child (asked first, killed after :data:`CLOSE_WAIT_S`)."""
        with self._lock:
            if self._proc is None:
                return
            try:
                self._conn.send(("close", ()))
            except OSError:
                pass
            self._end(kill=False)

    def __enter__(self) -> StreamingSfmProcess:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


if __name__ == "__main__":
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _serve(Connection(int(sys.argv[1])))
