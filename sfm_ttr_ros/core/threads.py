"""A thread's share of the cores: its OS priority and its OpenMP team size.

:func:`lower_thread_priority` raises the calling thread's nice value (Linux keeps nice per
thread): the window worker and the SfM begun ahead run nicer than live serving, so a live
prediction gets the cores as soon as a frame arrives.

The OpenMP team size of one thread is the window worker's thread budget.

torch runs its intra-op parallel regions on OpenMP (libgomp in the PyPI wheels), and every
thread that opens a parallel region gets a team of its own. In the node two threads do: the
live server and the window worker. Measured on 2 cores (BENCHMARKS.md "Live latency and the live
share", the live-latency study, docs/decisions.md "Studies"): a window's refinement takes
3.7-4.8 s with two threads in the main thread, 8.6-8.8 s with two threads in the background worker,
and 5.6-5.9 s with ONE thread in the worker. Once the process holds more OpenMP threads than cores,
libgomp stops spin-waiting and every parallel region pays a futex wake-up; the refinement's many
small ops (416x128 maps) lose more to that than they gain from the second core. So the worker runs
``worker_threads`` (1) and the live server keeps torch's default.

``omp_set_num_threads`` sets the calling thread's team size only (an OpenMP ICV per thread),
whereas ``torch.set_num_threads`` also changes a process-wide number: hence the runtime is
called directly. Without an OpenMP runtime (another platform, a torch built without it) the
functions do nothing and say so by their return value.
"""

from __future__ import annotations

import ctypes
import functools
import os
import threading


def lower_thread_priority(nice: int) -> bool:
    """Raise the calling thread's nice value by ``nice`` (0 = leave it). True when applied.
    Linux keeps nice per thread; elsewhere (or when refused) nothing changes."""
    if nice <= 0 or not hasattr(os, "setpriority"):
        return False
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + int(nice))
    except OSError:
        return False
    return True


#: Shared objects of the OpenMP runtimes torch may load (GNU, LLVM, Intel).
RUNTIME_NAMES = ("libgomp", "libomp", "libiomp5")


@functools.cache
def runtime() -> ctypes.CDLL | None:
    """torch's OpenMP runtime in this process, or None. pycolmap brings a copy of its own
    (``pycolmap.libs/libgomp-*.so``), which is not the one torch's ops use."""
    import torch

    torch_dir = torch.__file__.rsplit("/", 1)[0]
    try:
        with open("/proc/self/maps") as maps:
            paths = sorted({line.split()[-1] for line in maps if "/" in line})
    except OSError:
        return None
    # torch's own copy first, then any runtime found (a torch linked to the system's)
    ranked = sorted((p for p in paths if p.rsplit("/", 1)[-1].startswith(RUNTIME_NAMES)),
                    key=lambda p: not p.startswith(torch_dir))
    for path in ranked:
        try:
            lib = ctypes.CDLL(path)
            lib.omp_get_max_threads  # noqa: B018 - the runtime's API is there
            return lib
        except (OSError, AttributeError):
            continue
    return None


def thread_team_size() -> int | None:
    """The calling thread's OpenMP team size (``omp_get_max_threads``), None without OpenMP."""
    lib = runtime()
    return int(lib.omp_get_max_threads()) if lib is not None else None


def set_thread_team(threads: int) -> bool:
    """Set the calling thread's OpenMP team size to ``threads`` (>= 1); True when applied."""
    if threads < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    lib = runtime()
    if lib is None:
        return False
    lib.omp_set_num_threads(int(threads))
    return True


__all__ = ["runtime", "set_thread_team", "thread_team_size"]
