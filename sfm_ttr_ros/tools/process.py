"""Stopping a node started as a subprocess the way ``ros2 run`` is stopped: SIGINT, then wait."""

from __future__ import annotations

import signal
import subprocess


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
