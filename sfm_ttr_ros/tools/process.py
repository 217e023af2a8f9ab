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
