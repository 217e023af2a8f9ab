"""core/jemalloc.py: the node re-executes itself on jemalloc when SFM_TTR_MALLOC asks for it."""

from __future__ import annotations

import os
import subprocess
import sys

from sfm_ttr_ros.core import jemalloc


def fake_execve(calls):
    return lambda path, argv, env: calls.append((path, argv, env))


def test_jemalloc_re_executes_with_the_library_preloaded_once(tmp_path, monkeypatch):
    lib = tmp_path / jemalloc.LIBRARY
    lib.write_bytes(b"")
    monkeypatch.setattr(jemalloc, "search_paths", lambda: [tmp_path / "none.so", lib])
    monkeypatch.setattr(jemalloc, "loaded", lambda: False)
    calls = []
    note = jemalloc.preload({"LD_PRELOAD": "/x/other.so", jemalloc.ENV: "jemalloc"},
                            ["py", "refiner", "--ros-args"], fake_execve(calls))
    [(path, argv, env)] = calls
    assert path == sys.executable and argv == ["py", "refiner", "--ros-args"]
    assert env["LD_PRELOAD"] == f"{lib} /x/other.so" and env[jemalloc.PRELOADED_ENV] == str(lib)
    assert "re-executed" in note
    # the second start: the guard says it was tried, and it does not loop
    calls.clear()
    note = jemalloc.preload(env, ["py"], fake_execve(calls))
    assert calls == [] and "could not be preloaded" in note and str(lib) in note


def test_default_missing_library_or_bad_path_keep_glibc(tmp_path, monkeypatch):
    """glibc is the default (jemalloc's windows are 13-14 % slower: BENCHMARKS.md 6f)."""
    lib = tmp_path / jemalloc.LIBRARY
    lib.write_bytes(b"")
    monkeypatch.setattr(jemalloc, "search_paths", lambda: [lib])
    monkeypatch.setattr(jemalloc, "loaded", lambda: False)
    calls = []
    assert jemalloc.preload({}, ["py"], fake_execve(calls)).startswith("malloc: glibc")
    assert jemalloc.preload({jemalloc.ENV: "glibc"}, ["py"], fake_execve(calls)).startswith(
        "malloc: glibc")
    monkeypatch.setattr(jemalloc, "search_paths", lambda: [tmp_path / "none.so"])
    note = jemalloc.preload({jemalloc.ENV: "jemalloc"}, ["py"], fake_execve(calls))
    assert "no libjemalloc.so.2" in note
    note = jemalloc.preload({jemalloc.ENV: str(tmp_path / "x.so")}, ["py"], fake_execve(calls))
    assert "no such file" in note and calls == []


def test_an_explicit_path_is_preloaded_and_already_loaded_is_left(tmp_path, monkeypatch):
    lib = tmp_path / "libjemalloc-custom.so"
    lib.write_bytes(b"")
    monkeypatch.setattr(jemalloc, "loaded", lambda: False)
    calls = []
    jemalloc.preload({jemalloc.ENV: str(lib)}, ["py"], fake_execve(calls))
    assert calls and calls[0][2]["LD_PRELOAD"] == str(lib)
    monkeypatch.setattr(jemalloc, "loaded", lambda: True)
    calls.clear()
    note = jemalloc.preload({jemalloc.ENV: "jemalloc"}, ["py"], fake_execve(calls))
    assert note == "malloc: jemalloc (preloaded)"
    assert not calls


def test_a_library_that_cannot_be_preloaded_runs_on_glibc_in_a_real_re_execution(tmp_path):
    """The real os.execve: a file that is no shared library makes ld.so warn and start without
    it; the re-executed process sees the guard and stays on glibc."""
    lib = tmp_path / "not_a_library.so"
    lib.write_bytes(b"not an ELF file")
    code = ("from sfm_ttr_ros.core import jemalloc; print('NOTE', jemalloc.preload())")
    env = dict(os.environ, **{jemalloc.ENV: str(lib)})
    env.pop(jemalloc.PRELOADED_ENV, None)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    assert f"NOTE malloc: glibc ({lib} could not be preloaded)" in out.stdout
