"""ros/allocator.py: the node re-executes itself on mimalloc (default) or a named library,
once; glibc when asked for or when the library is not there."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from sfm_ttr_ros.ros import allocator


def fake_execve(calls):
    return lambda path, argv, env: calls.append((path, argv, env))


@pytest.fixture
def fake_mimalloc(tmp_path, monkeypatch):
    """mimalloc's library as an empty file under tmp_path; nothing mapped yet."""
    lib = tmp_path / "libmimalloc.so"
    lib.write_bytes(b"")
    monkeypatch.setattr(allocator, "find_mimalloc", lambda: str(lib))
    monkeypatch.setattr(allocator, "mapped", lambda preloaded=None: None)
    return lib


def test_mimalloc_is_the_default_and_re_executes_once_with_its_options(fake_mimalloc):
    lib = fake_mimalloc
    calls = []
    note = allocator.preload({"LD_PRELOAD": "/x/other.so"}, ["py", "refiner", "--ros-args"],
                             fake_execve(calls))
    [(path, argv, env)] = calls
    assert path == sys.executable and argv == ["py", "refiner", "--ros-args"]
    assert env["LD_PRELOAD"] == f"{lib} /x/other.so" and env[allocator.PRELOADED_ENV] == str(lib)
    assert env["MIMALLOC_ALLOW_THP"] == "0"  # live p95 0.17 s with huge pages (BENCHMARKS §6)
    assert note == f"malloc: mimalloc ({lib}, re-executed)"
    # the second start: the guard says it was tried, and it does not loop
    calls.clear()
    note = allocator.preload(env, ["py"], fake_execve(calls))
    assert calls == [] and "could not be preloaded" in note and str(lib) in note


def test_the_users_mimalloc_options_stand(fake_mimalloc):
    calls = []
    allocator.preload({"MIMALLOC_ALLOW_THP": "1"}, ["py"], fake_execve(calls))
    assert calls[0][2]["MIMALLOC_ALLOW_THP"] == "1"


def test_glibc_a_missing_library_or_a_bad_path_keep_glibc(tmp_path, fake_mimalloc, monkeypatch):
    calls = []
    assert allocator.preload({allocator.ENV: "glibc"}, ["py"], fake_execve(calls)) == (
        "malloc: glibc (SFM_TTR_MALLOC=glibc)")
    monkeypatch.setattr(allocator, "find_mimalloc", lambda: None)
    note = allocator.preload({}, ["py"], fake_execve(calls))
    assert note.startswith("malloc: glibc") and "pip install cmeel-mimalloc" in note
    note = allocator.preload({allocator.ENV: str(tmp_path / "x.so")}, ["py"], fake_execve(calls))
    assert "no such file" in note and calls == []


def test_an_explicit_path_is_preloaded_and_a_mapped_allocator_is_left(tmp_path, fake_mimalloc,
                                                                    monkeypatch):
    lib = tmp_path / "libcustom-malloc.so"
    lib.write_bytes(b"")
    calls = []
    allocator.preload({allocator.ENV: str(lib)}, ["py"], fake_execve(calls))
    assert calls and calls[0][2]["LD_PRELOAD"] == str(lib)
    assert "MIMALLOC_ALLOW_THP" not in calls[0][2]
    monkeypatch.setattr(allocator, "mapped", lambda preloaded=None: lib.name)
    calls.clear()
    note = allocator.preload({allocator.ENV: str(lib), allocator.PRELOADED_ENV: str(lib)},
                             ["py"], fake_execve(calls))
    assert note == f"malloc: {lib.name} ({lib})" and not calls


def test_the_installed_wheel_provides_mimalloc():
    """setup.py installs cmeel-mimalloc on Linux: the default must find its library."""
    if not sys.platform.startswith("linux"):
        pytest.skip("the wheel is for Linux")
    path = allocator.find_mimalloc()
    assert path is not None and Path(path).is_file()


def _run(code: str, **env_vars: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, **env_vars)
    env.pop(allocator.PRELOADED_ENV, None)
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                          timeout=60)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="LD_PRELOAD and /proc")
def test_a_real_re_execution_runs_on_mimalloc():
    """The real os.execve: the second interpreter has mimalloc mapped and says so."""
    code = "from sfm_ttr_ros.ros import allocator; print('NOTE', allocator.preload())"
    out = _run(code, **{allocator.ENV: "mimalloc"})
    assert out.returncode == 0, out.stderr
    assert f"NOTE malloc: mimalloc ({allocator.find_mimalloc()})" in out.stdout


def test_a_library_that_cannot_be_preloaded_runs_on_glibc_in_a_real_re_execution(tmp_path):
    """A file that is no shared library makes ld.so warn and start without it; the re-executed
    process sees the guard and stays on glibc."""
    lib = tmp_path / "not_a_library.so"
    lib.write_bytes(b"not an ELF file")
    out = _run("from sfm_ttr_ros.ros import allocator; print('NOTE', allocator.preload())",
               **{allocator.ENV: str(lib)})
    assert out.returncode == 0, out.stderr
    assert f"NOTE malloc: glibc ({lib} could not be preloaded)" in out.stdout
