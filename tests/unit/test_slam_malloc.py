"""agent.slam.malloc: glibc's thresholds set where the C library is glibc, nothing elsewhere."""

from __future__ import annotations

import mmap
import platform
import sys

import numpy as np

from agent.slam.malloc import release_pages, tune_malloc


def test_the_thresholds_are_set_on_glibc_and_large_arrays_still_work() -> None:
    glibc = sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc"
    assert tune_malloc() is glibc
    # Blocks above and below the mmap threshold, allocated, written and freed again.
    for size in (1 << 10, 1 << 20, 8 << 20):
        a = np.ones(size, dtype=np.uint8)
        assert int(a.sum()) == size
        del a


def test_release_pages_drops_whole_pages_only() -> None:
    """The whole pages inside a buffer read back as zeros once released; the bytes before its first page
    boundary and after its last (shared with whatever lies beside it) keep their values."""
    page = mmap.PAGESIZE
    a = np.ones(6 * page, dtype=np.uint8)
    view = a[100 : 5 * page + 100]
    released = release_pages(view)
    assert released is sys.platform.startswith("linux")
    start = view.ctypes.data
    first = -(-start // page) * page - start  # offsets within the view
    last = (start + view.nbytes) // page * page - start
    if released:
        assert not view[first:last].any()
        assert view[:first].all() and view[last:].all()
    assert a[:100].all() and a[5 * page + 100 :].all()
    assert release_pages(np.ones((4, 4), dtype=np.uint8)[:, ::2]) is False  # not contiguous
