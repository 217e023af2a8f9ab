"""Give the C heap's free memory back to the operating system after a window.

A window allocates hundreds of MB for a few seconds (SfM's features and matches, the refinement's
activations and gradients, the window's frames and depths) and frees them; glibc's malloc keeps
most of the freed pages mapped for reuse, so between windows the node's RSS stays near the
window's peak and creeps up as the arenas fragment. ``malloc_trim(0)`` returns every free page it
can (also from the middle of the arenas), at ~15-40 ms in the window worker after each window
that ran SfM (a window skipped for overload frees next to nothing);
in a 2.5-min soak of the node at 10 Hz the RSS between windows fell from ~1.6 GB to ~1.0 GB and
the final RSS from 1663 to 990 MiB (BENCHMARKS.md section 6c). Not glibc (musl, macOS): a no-op.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools


@functools.cache
def _malloc_trim():
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name or "libc.so.6")
        trim = libc.malloc_trim
    except (OSError, AttributeError):
        return None
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    return trim


def release_free_heap() -> bool:
    """``malloc_trim(0)``: True when memory was returned, False when none could be (or the C
    library has no malloc_trim)."""
    trim = _malloc_trim()
    return bool(trim(0)) if trim is not None else False
