"""glibc's malloc set for the SLAM filter's large, short-lived arrays (a process setting, made by the
process that runs the filter: ``agent.runtime.slam_worker``, ``benchmarks/slam_vs_gmapping.py``'s worker).

By default glibc serves blocks from 128 KB up with mmap, but raises that threshold to the size of every
such block freed (up to 32 MB) and its heap trim threshold to twice that. Each filter update builds a
distance field of up to ~27 MB (30 maps' windows of a 15 m scan) and frees it: after the first one,
later fields and the large temporaries come from the heap, and the heap keeps what they leave. Fixed
thresholds stop that: blocks from ``mmap_threshold`` up are always mapped and go back to the system when
freed; the heap keeps up to ``trim_threshold`` free at its top, so mid-sized arrays reuse pages instead
of faulting fresh ones in (with the trim at glibc's 128 KB default, a 1 MB threshold cost 24 % more CPU).
Intel seeds 0 / 2 (whole log, the benchmark's worker): peak RSS 113.1 / 116.1 MB against 120.3 / 120.3,
CPU 21.7 / 22.3 s against 21.6 s; the results are the same (docs/slam.md, "Speed and memory beside
GMapping", session slam-perf-9).

What the heap keeps free is still resident, and a rare burst (a loop closure's graph optimisation, ~25
MB of temporaries on Intel) left 18-37 MB free beneath later updates' fields, moving Intel's peak by
10-15 MB from one build to the next for the same poses. ``tune_malloc`` therefore also sets a slack:
after each filter update :func:`trim_heap` hands the heap's free pages back (``malloc_trim(0)``) when
more than ``heap_slack`` bytes are free (16 MB: at 8 MB it trimmed nearly every update, 1.4 M minor
faults and 2.6 s of system time on Intel; at 16 MB 152 k and 0.4 s). :func:`release_pages` hands back
pages of a buffer whose contents are dead (the tile pool's slots when a rebuild clears the maps).
Session slam-perf-11, docs/slam.md.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import mmap
import sys

import numpy as np

log = logging.getLogger(__name__)

M_TRIM_THRESHOLD = -1  # glibc's malloc.h
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 4 * 1024 * 1024
TRIM_THRESHOLD_BYTES = 64 * 1024 * 1024
HEAP_SLACK_BYTES = 16 * 1024 * 1024


class _Mallinfo2(ctypes.Structure):
    _fields_ = [
        (name, ctypes.c_size_t)
        for name in (
            *("arena", "ordblks", "smblks", "hblks", "hblkhd"),
            *("usmblks", "fsmblks", "uordblks", "fordblks", "keepcost"),
        )
    ]


# Set by tune_malloc: the heap's free bytes beyond which trim_heap hands free pages back (None: never).
_heap_slack: int | None = None
_libc: ctypes.CDLL | None = None


def trim_heap() -> bool:
    """Where :func:`tune_malloc` set a heap slack, and the heap holds more free bytes than that, hand its
    free pages back to the kernel (glibc ``malloc_trim(0)``: the free space inside the heap too, not only
    at its top). Called by the filter after each update (``RbpfSlam``): the heap keeps what a rare large
    burst (a loop closure's graph optimisation: ~25 MB of temporaries on Intel) leaves free, and that
    was resident beneath the next updates' distance fields. True if it trimmed."""
    if _heap_slack is None or _libc is None:
        return False
    info = _libc.mallinfo2()
    if info.fordblks <= _heap_slack:
        return False
    return bool(_libc.malloc_trim(0))


def tune_malloc(
    mmap_threshold: int = MMAP_THRESHOLD_BYTES,
    trim_threshold: int = TRIM_THRESHOLD_BYTES,
    heap_slack: int | None = HEAP_SLACK_BYTES,
) -> bool:
    """Set glibc's mmap and trim thresholds for this process, and the free heap :func:`trim_heap` lets
    stand (None: trim_heap does nothing); False (and nothing changed) where the C library is not glibc
    or refuses."""
    global _heap_slack, _libc
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
        gnu_get_libc_version = libc.gnu_get_libc_version  # glibc only: musl's mallopt does nothing
    except (OSError, AttributeError):
        return False
    gnu_get_libc_version.restype = ctypes.c_char_p
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    ok = bool(mallopt(M_MMAP_THRESHOLD, mmap_threshold)) and bool(mallopt(M_TRIM_THRESHOLD, trim_threshold))
    if ok and heap_slack is not None and hasattr(libc, "mallinfo2") and hasattr(libc, "malloc_trim"):
        libc.mallinfo2.restype = _Mallinfo2
        libc.malloc_trim.argtypes = (ctypes.c_size_t,)
        libc.malloc_trim.restype = ctypes.c_int
        _libc, _heap_slack = libc, heap_slack
    log.debug(
        "glibc %s: mmap threshold %d, trim threshold %d: %s",
        gnu_get_libc_version(),
        mmap_threshold,
        trim_threshold,
        ok,
    )
    return ok


_MADV_DONTNEED = 4  # Linux's asm-generic/mman-common.h


def release_pages(array: np.ndarray) -> bool:
    """Hand the whole pages inside a C-contiguous array's buffer back to the kernel (Linux
    ``madvise(MADV_DONTNEED)``): they stop counting in RSS, and the kernel supplies zero-filled pages the
    next time they are touched, so the contents are lost. For buffers whose contents are dead and will
    be written before they are read again (the tile pool's free slots after a map rebuild). False (and
    nothing done) where that is not available."""
    if not sys.platform.startswith("linux") or not array.flags.c_contiguous or array.nbytes == 0:
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        madvise = libc.madvise
    except (OSError, AttributeError):
        return False
    madvise.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int)
    madvise.restype = ctypes.c_int
    page = mmap.PAGESIZE
    start = array.ctypes.data
    first = -(-start // page) * page  # whole pages only: the buffer's neighbours keep theirs
    last = (start + array.nbytes) // page * page
    if last <= first:
        return False
    return bool(madvise(first, last - first, _MADV_DONTNEED) == 0)
