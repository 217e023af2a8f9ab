"""Processes the tools start and watch: stopping a node started as a subprocess the way ``ros2
run`` is stopped (SIGINT, then wait), and reading a process's memory from /proc."""

from __future__ import annotations

import signal
import subprocess
from pathlib import Path


def interrupt(proc: subprocess.Popen, timeout: float = 20.0) -> int:
    """SIGINT ``proc`` if it still runs, wait up to ``timeout`` s (then SIGKILL); its exit code."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode


def close_client_and_node(client, proc: subprocess.Popen, timeout: float = 30.0) -> int:
    """End an outside test client (anything with ``executor`` and ``node``, or None) and rclpy,
    then :func:`interrupt` the node process; its exit code (the fuzz and soak scripts)."""
    import rclpy

    if client is not None:
        client.executor.shutdown(timeout_sec=2)
        client.node.destroy_node()
    rclpy.try_shutdown()
    return interrupt(proc, timeout)


def memory_kib(pid: int | str = "self") -> dict[str, int]:
    """``VmRSS_kib`` (resident now) and ``VmHWM_kib`` (its peak) of a process, from
    ``/proc/<pid>/status`` (KiB); empty when the process is gone or there is no /proc. The one
    reader of a process's memory for the benchmark's memory run, the soak and the fuzz
    harness."""
    out = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            key, _, rest = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                out[f"{key}_kib"] = int(rest.split()[0])
    except (OSError, ValueError, IndexError):
        pass
    return out


def rss_mib(pid: int | str = "self") -> float:
    """Resident set size of a process (:func:`memory_kib`), MiB; NaN when it is gone."""
    kib = memory_kib(pid).get("VmRSS_kib")
    return float("nan") if kib is None else kib / 1024.0


def own_memory_kib() -> dict[str, int]:
    """This process's :func:`memory_kib` with ``ru_maxrss_kib`` (``getrusage``; KiB on Linux)
    beside it."""
    import resource

    return {"ru_maxrss_kib": int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss),
            **memory_kib("self")}
