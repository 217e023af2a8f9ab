"""core/heap.py: the window worker gives the C heap's free pages back to the OS."""

import sys

import numpy as np
import pytest

from sfm_ttr_ros.core import heap


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
