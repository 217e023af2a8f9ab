"""Which malloc the node runs on: mimalloc by default, glibc or another library on request.

A window allocates and frees a few hundred MB. glibc's malloc keeps the freed pieces, fragmented,
inside its arenas, so the node's memory grows over a long run; mimalloc (MIT, from PyPI:
``cmeel-mimalloc``, installed with the package) gives freed pages back by itself. It runs with
``MIMALLOC_ALLOW_THP=0`` (no transparent huge pages: their page faults delay the live output).
The measurements behind the default: BENCHMARKS.md "Memory", docs/decisions.md "Memory".

``SFM_TTR_MALLOC`` chooses: ``mimalloc`` (default; the wheel's library), ``glibc``, or the path
of a malloc library. The allocator of a process is chosen when it starts (``LD_PRELOAD``), so
:func:`preload` re-executes the running command in place (``os.execve``: same PID, arguments,
environment and open files) with the library preloaded, first thing in the node's ``main``. If it
cannot be preloaded after all, the second start says so and runs on glibc (no loop); a library
that is not installed leaves glibc with a note in the log.
"""

from __future__ import annotations

import importlib.metadata
import os
import sys
from collections.abc import Callable, Mapping
from pathlib import Path

#: The environment variable that chooses the allocator: mimalloc, glibc or a library's path.
ENV = "SFM_TTR_MALLOC"
#: What the node runs on when ``SFM_TTR_MALLOC`` is not set.
DEFAULT = "mimalloc"
#: Set in the re-executed process: the library it was started with (the loop guard).
PRELOADED_ENV = "SFM_TTR_MALLOC_PRELOADED"
#: The wheel that carries mimalloc, and the library inside it.
MIMALLOC_DISTRIBUTION = "cmeel-mimalloc"
MIMALLOC_LIBRARY = "cmeel.prefix/lib/libmimalloc.so.3"
#: mimalloc options set for the re-executed node unless its environment sets them.
MIMALLOC_OPTIONS = {"MIMALLOC_ALLOW_THP": "0"}


def find_mimalloc() -> str | None:
    """The path of the ``cmeel-mimalloc`` wheel's library, or None when it is not installed."""
    try:
        path = Path(importlib.metadata.distribution(MIMALLOC_DISTRIBUTION)
                    .locate_file(MIMALLOC_LIBRARY))
    except importlib.metadata.PackageNotFoundError:
        return None
    return str(path) if path.is_file() else None


def is_mimalloc(text: str) -> bool:
    """Whether ``text`` (a file name, /proc/self/maps) names mimalloc's library."""
    return "libmimalloc" in text


def choice(environ: Mapping[str, str]) -> str:
    """The allocator ``environ`` asks for (``SFM_TTR_MALLOC``, else :data:`DEFAULT`)."""
    return environ.get(ENV, DEFAULT).strip() or DEFAULT


def library(name: str) -> str | None:
    """The library ``SFM_TTR_MALLOC=name`` names: the wheel's for ``mimalloc`` (None when it is
    not installed), None for ``glibc``, else ``name`` itself (a path, not checked here)."""
    if name == "glibc":
        return None
    return find_mimalloc() if name == "mimalloc" else name


def mapped(preloaded: str | None = None) -> str | None:
    """The preloaded allocator mapped into this process: ``mimalloc``, or the file name of
    ``preloaded`` (a library path) when that is mapped; from Linux' /proc, None on glibc alone
    or elsewhere."""
    try:
        with open("/proc/self/maps") as maps:
            text = maps.read()
    except OSError:
        return None
    if is_mimalloc(text):
        return "mimalloc"
    if preloaded and Path(preloaded).name in text:
        return Path(preloaded).name
    return None


def preload(environ: Mapping[str, str] | None = None, argv: list[str] | None = None,
            execve: Callable[[str, list[str], dict[str, str]], object] = os.execve) -> str:
    """Re-execute this process with the chosen library preloaded when it is not glibc and is
    there (then it does not return); else a one-line note of the allocator in use, for the
    node's log. ``argv`` defaults to the command line that started this process."""
    env = dict(os.environ if environ is None else environ)
    name = choice(env)
    running = mapped(env.get(PRELOADED_ENV))
    if running is not None:
        return f"malloc: {running} ({env.get(PRELOADED_ENV) or 'preloaded'})"
    if name == "glibc":
        return f"malloc: glibc ({ENV}=glibc)"
    if env.get(PRELOADED_ENV):
        return f"malloc: glibc ({env[PRELOADED_ENV]} could not be preloaded)"
    path = library(name)
    if path is None:
        return (f"malloc: glibc ({ENV}={name} but it is not installed: "
                f"pip install {MIMALLOC_DISTRIBUTION})")
    if not Path(path).is_file():
        return f"malloc: glibc ({ENV}={name}: no such file)"
    env["LD_PRELOAD"] = " ".join(p for p in (path, env.get("LD_PRELOAD", "")) if p)
    env[PRELOADED_ENV] = path
    if is_mimalloc(Path(path).name):
        for option, value in MIMALLOC_OPTIONS.items():
            env.setdefault(option, value)
    execve(sys.executable, list(sys.orig_argv if argv is None else argv), env)
    return f"malloc: {name} ({path}, re-executed)"  # only when execve returns (tests)


__all__ = ["DEFAULT", "ENV", "MIMALLOC_DISTRIBUTION", "MIMALLOC_LIBRARY", "MIMALLOC_OPTIONS",
           "PRELOADED_ENV", "choice", "find_mimalloc", "is_mimalloc", "library", "mapped",
           "preload"]
