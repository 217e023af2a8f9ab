"""Give the C heap's free memory back to the operating system after a window.

A window allocates hundreds of MB for a few seconds (SfM's features and matches, the refinement's
activations and gradients, the window's frames and depths) and frees them; glibc's malloc keeps
most of the freed pages mapped for reuse, so between windows the node's RSS stays near the
window's peak and creeps up as the arenas fragment. ``malloc_trim(0)`` returns every free page it
can (also from the middle of the arenas), at ~15-40 ms in the window worker after each window
that ran SfM (a window skipped for overload frees next to nothing);
in a 2.5-min soak of the node at 10 Hz the RSS between windows fell from ~1.6 GB to ~1.0 GB and
the final RSS from 1663 to 990 MiB (BENCHMARKS.md "Live latency and the live share"). On mimalloc
and jemalloc (core/allocator.py) the same call collects and purges their free pages
(``mi_collect(true)``, ``mallctl("arena.<all>.purge")``; glibc's ``malloc_trim`` would find an
empty glibc heap there). Another C library (musl, macOS): a no-op.

:func:`limit_arenas` caps glibc's per-thread arenas (``mallopt(M_ARENA_MAX)``, by default up to
8 per core): the node's threads (executor, live server, worker, DDS, OpenMP) each fragment an
arena of their own. The node sets 2 at start-up (:data:`NODE_ARENAS`) unless the environment
sets ``MALLOC_ARENA_MAX``: in a 2.5-min soak the peak RSS fell from 1618 to 1500 MiB and the
final from 1048 to 825 MiB, live latency unchanged (BENCHMARKS.md "Memory").

:func:`in_own_mapping` keeps a large long-lived buffer (the node's decoded frames) out of the
heap altogether, in an anonymous mapping of its own.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import mmap
import os

import numpy as np

#: glibc's ``M_ARENA_MAX`` option of ``mallopt``.
M_ARENA_MAX = -8
#: Arenas the node allows (:func:`limit_arenas`).
NODE_ARENAS = 2
#: Arrays at least this large get a mapping of their own (:func:`in_own_mapping`); a mapping
#: costs a system call and its page faults, so small frames stay in the heap.
OWN_MAPPING_MIN_BYTES = 256 * 1024
#: jemalloc's control name that purges the dirty pages of all arenas (MALLCTL_ARENAS_ALL = 4096).
JEMALLOC_PURGE_ALL = b"arena.4096.purge"


@functools.cache
def _libc_function(name: str):
    """A glibc function by name, or None (another C library, no such symbol)."""
    try:
        return getattr(ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6"), name)
    except (OSError, AttributeError):
        return None


@functools.cache
def _malloc_trim():
    trim = _libc_function("malloc_trim")
    if trim is not None:
        trim.argtypes = [ctypes.c_size_t]
        trim.restype = ctypes.c_int
    return trim


def limit_arenas(arenas: int = NODE_ARENAS) -> bool:
    """At most ``arenas`` malloc arenas from now on (threads that have one keep it: call this
    before starting threads). Left alone when ``MALLOC_ARENA_MAX`` is in the environment (the
    user's choice) or the C library has no ``mallopt``; True when set."""
    if arenas < 1:
        raise ValueError(f"arenas must be >= 1, got {arenas}")
    mallopt = _libc_function("mallopt")
    if mallopt is None or "MALLOC_ARENA_MAX" in os.environ:
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return bool(mallopt(M_ARENA_MAX, int(arenas)))


def _preloaded_function(name: str):
    """A function of the process' global namespace (an allocator preloaded by
    core/allocator.py defines its own), or None."""
    try:
        return getattr(ctypes.CDLL(None), name)
    except (OSError, AttributeError):
        return None


@functools.cache
def _jemalloc_mallctl():
    """jemalloc's ``mallctl`` when this process runs on jemalloc, else None."""
    mallctl = _preloaded_function("mallctl")
    if mallctl is not None:
        mallctl.argtypes = [ctypes.c_char_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p,
                            ctypes.c_size_t]
        mallctl.restype = ctypes.c_int
    return mallctl


@functools.cache
def _mimalloc_collect():
    """mimalloc's ``mi_collect(bool force)`` when this process runs on mimalloc, else None."""
    collect = _preloaded_function("mi_collect")
    if collect is not None:
        collect.argtypes = [ctypes.c_bool]
        collect.restype = None
    return collect


def release_free_heap() -> bool:
    """The free heap back to the operating system: on mimalloc its free pages collected and
    purged at once (``mi_collect(true)``), on jemalloc every arena's dirty pages
    (``mallctl("arena.<MALLCTL_ARENAS_ALL>.purge")``), True when done; on glibc
    ``malloc_trim(0)`` (True when memory was returned); False when none applies."""
    collect = _mimalloc_collect()
    if collect is not None:
        collect(True)
        return True
    mallctl = _jemalloc_mallctl()
    if mallctl is not None:
        return mallctl(JEMALLOC_PURGE_ALL, None, None, None, 0) == 0
    trim = _malloc_trim()
    return bool(trim(0)) if trim is not None else False


def in_own_mapping(array: np.ndarray) -> np.ndarray:
    """``array`` copied into an anonymous memory mapping of its own (C order), which goes back
    to the operating system (munmap) as soon as the last reference to it does; an array under
    :data:`OWN_MAPPING_MIN_BYTES` is returned as it is.

    For large buffers that arrive at a steady rate and live for seconds: the node's frames,
    which wait in the window queue while a window allocates and frees hundreds of MB around
    them. In glibc's heap each queued 1.4 MB image pins the pages around it, the window's freed
    memory cannot be returned and the arenas grow (fragmentation); in a 2.5-min soak of the
    node the arenas grew 673 -> 1010 MB from frame 100 to the peak with the images in the heap
    and 602 -> 759 MB with each in its own mapping, peak RSS over frame 100's +22.8 % -> +12.9 %
    (BENCHMARKS.md "Memory"). Cost: ~0.7 ms per 1242x375 frame (copy, page faults, munmap)."""
    if array.nbytes < OWN_MAPPING_MIN_BYTES:
        return array
    private = getattr(mmap, "MAP_PRIVATE", None)  # not shared memory (Windows: no flags)
    buf = (mmap.mmap(-1, array.nbytes) if private is None
           else mmap.mmap(-1, array.nbytes, flags=private))
    out = np.frombuffer(buf, dtype=array.dtype, count=array.size).reshape(array.shape)
    out[...] = array
    return out
