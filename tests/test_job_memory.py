"""A job returns the C heap's free memory at its end (cell.jobs.memory): what glibc would otherwise keep
of freed, fragmented allocations leaves the process's RSS."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cell.jobs.memory import _malloc_trim, release_freed_heap


def rss_mib() -> float:
    status = Path("/proc/self/status").read_text().splitlines()
    return int(next(line for line in status if line.startswith("VmRSS")).split()[1]) / 1024


@pytest.mark.skipif(_malloc_trim() is None, reason="the C library has no malloc_trim (not glibc)")
def test_freed_fragmented_heap_memory_leaves_the_rss() -> None:
    arrays = [np.ones(1000) for _ in range(20_000)]  # 8 kB each, below glibc's mmap threshold: 160 MB
    kept = arrays[::200]  # one in 200 stays: the arena is fragmented and cannot shrink from its top
    del arrays
    before = rss_mib()
    release_freed_heap()
    assert before - rss_mib() > 100.0, f"RSS {before:.0f} MiB -> {rss_mib():.0f} MiB"
    assert len(kept) == 100
