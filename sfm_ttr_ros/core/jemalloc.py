"""Run the node on jemalloc, on request (issue 15's memory).

glibc's malloc keeps the memory a window frees inside its arenas, and the freed pieces fragment:
in 2.5-min soaks of the node at 10 Hz (BENCHMARKS.md 6f) the peak RSS was 12–23 % above its
value at frame 100 in eight runs with glibc (1157–1290 MiB), with the heap in use nearly the
same at both moments; with jemalloc 5.3 (Debian's and Ubuntu's ``libjemalloc2``) it was 6–9 %
(1071–1082 MiB) in five runs, live latency the same. The price: a window takes 13–14 % longer
(jemalloc's timed purge, ``dirty_decay_ms``, gives freed pages back ~10 s after they are freed
and they are faulted in again; switched off, windows are as fast as on glibc but the RSS holds
each window's high-water mark until the purge after the window, so the peak is glibc's again:
BENCHMARKS.md 6i), so fewer windows keep up at 10 Hz. Hence not the default: ``SFM_TTR_MALLOC``
chooses ``glibc`` (default), ``jemalloc`` (the system's :data:`LIBRARY`, from its library
directories) or the path of a jemalloc library.

The allocator of a process is chosen when it starts (``LD_PRELOAD``), so :func:`preload`
re-executes the running command in place (``os.execve``: same PID, arguments, environment and
open files) with the library preloaded, first thing in the node's ``main``. If it cannot be
preloaded after all, the second start says so and runs on glibc (no loop).
"""

from __future__ import annotations

import os
import sys
import sysconfig
from collections.abc import Callable, Mapping
from pathlib import Path

#: The environment variable that chooses the allocator: glibc (default), jemalloc or a path.
ENV = "SFM_TTR_MALLOC"
#: Set in the re-executed process: the library it was started with (the loop guard).
PRELOADED_ENV = "SFM_TTR_MALLOC_PRELOADED"
#: jemalloc's shared library (Debian / Ubuntu: ``apt install libjemalloc2``).
LIBRARY = "libjemalloc.so.2"


def search_paths() -> list[Path]:
    """Where :func:`find` looks: the multiarch library directory, then the usual others."""
    multiarch = sysconfig.get_config_var("MULTIARCH") or ""
    dirs = ([f"/usr/lib/{multiarch}"] if multiarch else []) + ["/usr/lib64", "/usr/lib",
                                                              "/usr/local/lib"]
    return [Path(d) / LIBRARY for d in dirs]


def find() -> str | None:
    """The path of the system's jemalloc, or None."""
    return next((str(p) for p in search_paths() if p.is_file()), None)


def library(choice: str) -> str | None:
    """The library ``SFM_TTR_MALLOC=choice`` names: the system's for ``jemalloc``
    (:func:`find`, None when absent), else ``choice`` itself (a path, not checked here)."""
    return find() if choice == "jemalloc" else choice


def loaded() -> bool:
    """Whether this process runs with a jemalloc mapped (Linux' /proc; elsewhere False)."""
    try:
        with open("/proc/self/maps") as maps:
            return any("libjemalloc" in line for line in maps)
    except OSError:
        return False


def preload(environ: Mapping[str, str] | None = None, argv: list[str] | None = None,
            execve: Callable[[str, list[str], dict[str, str]], object] = os.execve) -> str:
    """Re-execute this process with jemalloc preloaded when ``SFM_TTR_MALLOC`` asks for it and
    the library is there (then it does not return); else a one-line note of the allocator in
    use, for the node's log. ``argv`` defaults to the command line that started this process."""
    env = dict(os.environ if environ is None else environ)
    choice = env.get(ENV, "glibc").strip() or "glibc"
    if loaded():
        return f"malloc: jemalloc ({env.get(PRELOADED_ENV) or 'preloaded'})"
    if choice == "glibc":
        return f"malloc: glibc ({ENV}=jemalloc: flatter memory, slower windows; core/jemalloc.py)"
    if env.get(PRELOADED_ENV):
        return f"malloc: glibc ({env[PRELOADED_ENV]} could not be preloaded)"
    path = library(choice)
    if path is None:
        return f"malloc: glibc ({ENV}=jemalloc but no {LIBRARY}: apt install libjemalloc2)"
    if not Path(path).is_file():
        return f"malloc: glibc ({ENV}={choice}: no such file)"
    env["LD_PRELOAD"] = " ".join(p for p in (path, env.get("LD_PRELOAD", "")) if p)
    env[PRELOADED_ENV] = path
    execve(sys.executable, list(sys.orig_argv if argv is None else argv), env)
    return f"malloc: jemalloc ({path}, re-executed)"  # only when execve returns (tests)


__all__ = ["ENV", "LIBRARY", "PRELOADED_ENV", "find", "library", "loaded", "preload",
           "search_paths"]
