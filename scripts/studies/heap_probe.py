"""The refiner node with a heap probe inside its process (docs/decisions.md, "Memory").

Runs :func:`sfm_ttr_ros.ros.node.main` with a sampler thread that writes one JSON line every
0.2 s to ``$HEAP_PROBE_OUT`` (default ``heap_probe.jsonl``): RSS (VmRSS, RssAnon, RssFile,
RssShmem, MiB), glibc's ``mallinfo2`` (``heap_used`` = uordblks, ``heap_free`` = fordblks:
freed heap still mapped, ``mmapped`` = hblkhd, ``arena``), the window worker's stage (the
innermost core function on its stack) and the stream's received / queued counters. With
``HEAP_PROBE_TRIM_S`` > 0 a second thread calls ``malloc_trim(0)`` that often while at least
32 MiB are free (the experiment section 6f rejected). Use it as the soak's node:

    .venv/bin/python scripts/soak_node.py --minutes 2.5 --set weight_policy=continue \\
        --warm-s 10 --drain-timeout 120 --exe ".venv/bin/python scripts/studies/heap_probe.py" \\
        --node-env HEAP_PROBE_OUT=probe.jsonl --out soak_probe

The sampler thread starts before the node's threads and so has a malloc arena of its own.
"""

from __future__ import annotations

import ctypes
import json
import os
import sys
import threading
import time

STAGE_FILES = ("reconstruction.py", "encoder.py", "photometric.py", "scale.py", "supervision.py",
               "measures.py", "window.py", "weights.py", "windows.py", "refiner.py",
               "pipeline.py")


class MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
        "fordblks", "keepcost")]


LIBC = ctypes.CDLL("libc.so.6")
LIBC.mallinfo2.restype = MallInfo2
LIBC.malloc_trim.argtypes = [ctypes.c_size_t]
STREAMS: list = []


def _rss() -> dict[str, int]:
    out = {}
    with open("/proc/self/status", encoding="ascii") as fh:
        for line in fh:
            if line.startswith(("VmRSS", "RssAnon", "RssFile", "RssShmem")):
                key, value = line.split(":")
                out[key] = int(value.split()[0]) // 1024
    return out


def _stage() -> str:
    for t in threading.enumerate():
        if t.name == "refiner-worker":
            f = sys._current_frames().get(t.ident)
            while f is not None:
                name = os.path.basename(f.f_code.co_filename)
                if name in STAGE_FILES:
                    return f"{name}:{f.f_code.co_name}"
                f = f.f_back
            return "?"
    return "-"


def _sample(path: str) -> None:
    t0 = time.monotonic()
    with open(path, "w", encoding="utf-8") as fh:
        while True:
            m = LIBC.mallinfo2()
            c = STREAMS[0].counters() if STREAMS else {}
            fh.write(json.dumps({
                "t": round(time.monotonic() - t0, 2), **_rss(), "heap_used": m.uordblks >> 20,
                "heap_free": m.fordblks >> 20, "mmapped": m.hblkhd >> 20,
                "arena": m.arena >> 20, "stage": _stage(), "received": c.get("received"),
                "queued": c.get("queued")}) + "\n")
            fh.flush()
            time.sleep(0.2)


def _trim(period: float) -> None:
    while True:
        time.sleep(period)
        if LIBC.mallinfo2().fordblks >= 32 << 20:
            LIBC.malloc_trim(0)


def main() -> int:
    from sfm_ttr_ros.core.stream import windows as stream

    init = stream.StreamProcessor.__init__

    def remember(self, *args, **kwargs):
        init(self, *args, **kwargs)
        STREAMS.append(self)

    stream.StreamProcessor.__init__ = remember
    threading.Thread(target=_sample, args=(os.environ.get("HEAP_PROBE_OUT",
                                                          "heap_probe.jsonl"),),
                     daemon=True).start()
    period = float(os.environ.get("HEAP_PROBE_TRIM_S", "0"))
    if period > 0:
        threading.Thread(target=_trim, args=(period,), daemon=True).start()
    from sfm_ttr_ros.ros.node import main as node_main

    sys.argv[0] = "refiner"
    return node_main()


if __name__ == "__main__":
    sys.exit(main())
