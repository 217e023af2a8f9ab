"""Which malloc the node runs on: mimalloc by default, glibc or jemalloc on request.

glibc's malloc keeps the memory a window frees inside its arenas, and the freed pieces fragment:
in 2.5-min soaks of the node at 10 Hz (BENCHMARKS.md "Memory") the peak RSS was 10–23 % above its
value at frame 100. jemalloc 5.3 kept it within 6–9 % but its timed purge made a window 13–14 %
slower (docs/decisions.md "Memory"). mimalloc 3.4 (MIT, from PyPI: ``cmeel-mimalloc``, installed
with the package) gives freed pages back a second after they are freed (``purge_delay``): peak
5.3–6.4 % above frame 100 in four soaks, windows as fast as on glibc or faster, live latency the
same (BENCHMARKS.md "Memory"), with ``MIMALLOC_ALLOW_THP=0``: with transparent huge pages allowed
the live p95 was 0.15–0.17 s (faults of 2-MiB pages). Hence the default.

``SFM_TTR_MALLOC`` chooses: ``mimalloc`` (default; the wheel's library), ``glibc``,
``jemalloc`` (the system's ``libjemalloc.so.2``: ``apt install libjemalloc2``) or the path of a
malloc library. The allocator of a process is chosen when it starts (``LD_PRELOAD``), so
:func:`preload` re-executes the running command in place (``os.execve``: same PID, arguments,
environment and open files) with the library preloaded, first thing in the node's ``main``. If it
cannot be preloaded after all, the second start says so and runs on glibc (no loop); a library
that is not installed leaves glibc with a note in the log.
"""

from __future__ import annotations

import importlib.metadata
import os
import sys
import sysconfig
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

#: The environment variable that chooses the allocator: mimalloc, glibc, jemalloc or a path.
ENV = "SFM_TTR_MALLOC"
#: What the node runs on when ``SFM_TTR_MALLOC`` is not set.
DEFAULT = "mimalloc"
#: Set in the re-executed process: the library it was started with (the loop guard).
PRELOADED_ENV = "SFM_TTR_MALLOC_PRELOADED"
#: jemalloc's shared library (Debian / Ubuntu: ``apt install libjemalloc2``).
JEMALLOC_LIBRARY = "libjemalloc.so.2"
#: The wheel that carries mimalloc, and the library inside it.
MIMALLOC_DISTRIBUTION = "cmeel-mimalloc"
MIMALLOC_LIBRARY = "cmeel.prefix/lib/libmimalloc.so.3"
#: mimalloc options set for the re-executed node unless its environment sets them.
MIMALLOC_OPTIONS = {"MIMALLOC_ALLOW_THP": "0"}


def jemalloc_paths() -> list[Path]:
    """Where :func:`find_jemalloc` looks: the multiarch library directory, then the others."""
    multiarch = sysconfig.get_config_var("MULTIARCH") or ""
    dirs = ([f"/usr/lib/{multiarch}"] if multiarch else []) + ["/usr/lib64", "/usr/lib",
                                                              "/usr/local/lib"]
    return [Path(d) / JEMALLOC_LIBRARY for d in dirs]


def find_jemalloc() -> str | None:
    """The path of the system's jemalloc, or None."""
    return next((str(p) for p in jemalloc_paths() if p.is_file()), None)


def find_mimalloc() -> str | None:
    """The path of the ``cmeel-mimalloc`` wheel's library, or None when it is not installed."""
    try:
        path = Path(importlib.metadata.distribution(MIMALLOC_DISTRIBUTION)
                    .locate_file(MIMALLOC_LIBRARY))
    except importlib.metadata.PackageNotFoundError:
        return None
    return str(path) if path.is_file() else None


@dataclass(frozen=True)
class Named:
    """A malloc ``SFM_TTR_MALLOC`` can name: how its library is found, what installs it, and
    the environment options the node gets with it unless its environment sets them."""

    find: Callable[[], str | None]
    install: str
    options: Mapping[str, str] = field(default_factory=dict)


#: The named choices besides ``glibc``; a library file is of kind ``name`` when its file name
#: holds ``lib<name>`` (:func:`kind`).
NAMED: dict[str, Named] = {
    "jemalloc": Named(find_jemalloc, "apt install libjemalloc2"),
    "mimalloc": Named(find_mimalloc, f"pip install {MIMALLOC_DISTRIBUTION}", MIMALLOC_OPTIONS),
}


def kind(text: str) -> str | None:
    """The named malloc whose ``lib<name>`` occurs in ``text`` (a file name, /proc/self/maps)."""
    return next((name for name in NAMED if f"lib{name}" in text), None)


def choice(environ: Mapping[str, str]) -> str:
    """The allocator ``environ`` asks for (``SFM_TTR_MALLOC``, else :data:`DEFAULT`)."""
    return environ.get(ENV, DEFAULT).strip() or DEFAULT


def library(name: str) -> str | None:
    """The library ``SFM_TTR_MALLOC=name`` names: the found one for ``jemalloc`` and
    ``mimalloc`` (None when absent), None for ``glibc``, else ``name`` itself (a path, not
    checked here)."""
    if name == "glibc":
        return None
    named = NAMED.get(name)
    return named.find() if named is not None else name


def mapped(preloaded: str | None = None) -> str | None:
    """The preloadable allocator mapped into this process: ``mimalloc``, ``jemalloc``, or the
    file name of ``preloaded`` (a library path) when that is mapped; from Linux' /proc, None on
    glibc alone or elsewhere."""
    try:
        with open("/proc/self/maps") as maps:
            text = maps.read()
    except OSError:
        return None
    named = kind(text)
    if named is None and preloaded and Path(preloaded).name in text:
        return Path(preloaded).name
    return named


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
        return f"malloc: glibc ({ENV}={name} but it is not installed: {NAMED[name].install})"
    if not Path(path).is_file():
        return f"malloc: glibc ({ENV}={name}: no such file)"
    env["LD_PRELOAD"] = " ".join(p for p in (path, env.get("LD_PRELOAD", "")) if p)
    env[PRELOADED_ENV] = path
    library_kind = kind(Path(path).name)
    for option, value in (NAMED[library_kind].options if library_kind else {}).items():
        env.setdefault(option, value)
    execve(sys.executable, list(sys.orig_argv if argv is None else argv), env)
    return f"malloc: {name} ({path}, re-executed)"  # only when execve returns (tests)


__all__ = ["DEFAULT", "ENV", "JEMALLOC_LIBRARY", "MIMALLOC_DISTRIBUTION", "MIMALLOC_LIBRARY",
           "MIMALLOC_OPTIONS", "NAMED", "PRELOADED_ENV", "Named", "choice", "find_jemalloc",
           "find_mimalloc", "jemalloc_paths", "kind", "library", "mapped", "preload"]
