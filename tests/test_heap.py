"""core/heap.py: the window worker gives the C heap's free pages back to the OS."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sfm_ttr_ros.core import allocator, heap


def rss_anon_mib() -> float:
    with open("/proc/self/status", encoding="ascii") as f:
        for line in f:
            if line.startswith("RssAnon:"):
                return int(line.split()[1]) / 1024
    raise AssertionError("no RssAnon in /proc/self/status")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc and /proc")
def test_free_pages_between_live_blocks_go_back_to_the_os():
    """~300 MB in 64 KB blocks (malloc's heap, not mmap), every 16th kept: glibc keeps the
    freed ones mapped (they are not at the top of the heap) until malloc_trim returns them."""
    blocks = [np.ones(8192) for _ in range(4800)]
    kept = blocks[::16]
    del blocks
    before = rss_anon_mib()
    assert heap.release_free_heap() is True
    after = rss_anon_mib()
    assert before - after > 150, (before, after)
    assert float(sum(k[0] for k in kept)) == len(kept)  # the live blocks are intact


def test_on_jemalloc_every_arena_is_purged(monkeypatch):
    """With jemalloc loaded, release_free_heap purges all arenas through mallctl (not glibc's
    malloc_trim, which would find an empty glibc heap)."""
    calls = []
    monkeypatch.setattr(heap, "_mimalloc_collect", lambda: None)
    monkeypatch.setattr(heap, "_jemalloc_mallctl", lambda: lambda *a: calls.append(a) or 0)
    assert heap.release_free_heap() is True
    assert calls == [(b"arena.4096.purge", None, None, None, 0)]


def test_on_mimalloc_its_free_pages_are_collected_at_once(monkeypatch):
    calls = []
    monkeypatch.setattr(heap, "_mimalloc_collect", lambda: calls.append)
    assert heap.release_free_heap() is True
    assert calls == [True]


PURGE_CHECK = """if True:
    import numpy as np, time
    from sfm_ttr_ros.core import allocator, heap
    def anon():
        for line in open("/proc/self/status"):
            if line.startswith("RssAnon:"):
                return int(line.split()[1]) / 1024
    assert allocator.mapped() == "{name}"
    blocks = [np.ones(8192) for _ in range(4800)]
    kept = blocks[::16]
    del blocks
    time.sleep(0.5)
    before = anon()
    assert heap.release_free_heap() is True
    print("DROP", before - anon(), float(sum(k[0] for k in kept)) == len(kept))
"""


def _freed_pages_given_back(library: str, name: str, **options: str) -> tuple[float, str]:
    """MB that release_free_heap gave back in a process on ``library`` after ~300 MB were
    freed in 64 KB blocks (every 16th kept), and whether the kept ones are intact."""
    env = dict(os.environ, LD_PRELOAD=library, **options)
    out = subprocess.run([sys.executable, "-c", PURGE_CHECK.format(name=name)], env=env,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    drop, intact = out.stdout.split()[1:]
    return float(drop), intact


@pytest.mark.skipif(not sys.platform.startswith("linux") or allocator.find_mimalloc() is None,
                    reason="the cmeel-mimalloc wheel is for Linux")
def test_on_a_real_mimalloc_the_collect_gives_freed_pages_back():
    """With mimalloc's own purge delayed by 100 s (so that what comes back is the collect's
    doing) the freed pages stay resident; release_free_heap returns those of every page without
    a kept block: ~150 of ~300 MB here (measured 151)."""
    drop, intact = _freed_pages_given_back(allocator.find_mimalloc(), "mimalloc",
                                           MIMALLOC_PURGE_DELAY="100000")
    assert drop > 100 and intact == "True", (drop, intact)


def _jemalloc_library() -> str | None:
    """The jemalloc library SFM_TTR_MALLOC names (a path), else the system's jemalloc."""
    named = os.environ.get(allocator.ENV, "").strip()
    if allocator.kind(Path(named).name) == "jemalloc" and Path(named).is_file():
        return named
    return allocator.find_jemalloc()


@pytest.mark.skipif(not sys.platform.startswith("linux") or _jemalloc_library() is None,
                    reason="no jemalloc library (apt install libjemalloc2)")
def test_on_a_real_jemalloc_the_purge_gives_freed_pages_back():
    """In a process on jemalloc with its time-based purge off (so that what comes back is the
    purge's doing) ~300 MB freed in 64 KB blocks stay resident; release_free_heap returns them
    (glibc's malloc_trim, called before, found an empty glibc heap there)."""
    drop, intact = _freed_pages_given_back(_jemalloc_library(), "jemalloc",
                                           MALLOC_CONF="dirty_decay_ms:-1,muzzy_decay_ms:-1")
    assert drop > 150 and intact == "True", (drop, intact)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_arenas_are_limited_unless_the_environment_says_otherwise(monkeypatch):
    monkeypatch.delenv("MALLOC_ARENA_MAX", raising=False)
    assert heap.limit_arenas(8) is True  # 8 = glibc's own per-core factor: harmless here
    monkeypatch.setenv("MALLOC_ARENA_MAX", "4")
    assert heap.limit_arenas(2) is False  # the user's value stands
    with pytest.raises(ValueError):
        heap.limit_arenas(0)


def test_a_large_array_gets_its_own_mapping_and_returns_it_when_dropped():
    """in_own_mapping: the same pixels, writeable, backed by an mmap of its own whose pages go
    back to the OS the moment the last reference goes (no malloc_trim needed)."""
    import mmap

    src = np.random.default_rng(0).integers(0, 255, (375, 1242, 3), dtype=np.uint8)
    img = heap.in_own_mapping(src)
    assert np.array_equal(img, src) and img.flags.writeable and img.flags.c_contiguous
    owner = img
    while isinstance(owner, np.ndarray):  # the reshaped view -> the flat view -> the buffer
        owner = owner.base
    assert isinstance(owner.obj if isinstance(owner, memoryview) else owner, mmap.mmap)
    small = np.zeros((8, 8, 3), np.uint8)
    assert heap.in_own_mapping(small) is small  # under OWN_MAPPING_MIN_BYTES: as it is
    if sys.platform.startswith("linux"):
        big = heap.in_own_mapping(np.ones(48 << 20, np.uint8))  # 48 MB, touched by the copy
        before = rss_anon_mib()
        del big
        assert before - rss_anon_mib() > 40
