"""agent.slam.malloc: glibc's thresholds set where the C library is glibc, nothing elsewhere."""

from __future__ import annotations

import platform
import sys

import numpy as np

from agent.slam.malloc import tune_malloc


def test_the_thresholds_are_set_on_glibc_and_large_arrays_still_work() -> None:
    glibc = sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc"
    assert tune_malloc() is glibc
    # Blocks above and below the mmap threshold, allocated, written and freed again.
    for size in (1 << 10, 1 << 20, 8 << 20):
        a = np.ones(size, dtype=np.uint8)
        assert int(a.sum()) == size
        del a
