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
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import sys

log = logging.getLogger(__name__)

M_TRIM_THRESHOLD = -1  # glibc's malloc.h
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 4 * 1024 * 1024
TRIM_THRESHOLD_BYTES = 64 * 1024 * 1024


def tune_malloc(
    mmap_threshold: int = MMAP_THRESHOLD_BYTES, trim_threshold: int = TRIM_THRESHOLD_BYTES
) -> bool:
    """Set glibc's mmap and trim thresholds for this process; False (and nothing changed) where the C
    library is not glibc or refuses."""
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
    log.debug(
        "glibc %s: mmap threshold %d, trim threshold %d: %s",
        gnu_get_libc_version(),
        mmap_threshold,
        trim_threshold,
        ok,
    )
    return ok
