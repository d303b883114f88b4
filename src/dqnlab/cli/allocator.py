"""glibc's allocator told to keep the memory a process frees, for the update's sake.

Every update allocates float batches of a few MB (a minibatch of 32 stacked 84x84 frames
as float32 is 3.6 MB) and frees them. glibc serves allocations above its mmap threshold
(128 KB, rising only to the largest block freed so far) with fresh mappings and trims the
heap's top above its trim threshold, so such blocks went back to the kernel at every
update and were faulted in again, page by page, at the next. With the thresholds raised
(mmap 64 MB: a replay's arrays are still their own mappings; trim 256 MB) they are reused
from the heap: the `der` preset's update took 16.0 ms instead of 19.1 (one thread) and
14.8 instead of 20.5 (two), medians of four alternating pairs on a noisy 2-core machine
(docs/benchmark.md, Atari 100k). Nothing computed changes: only where the bytes live.

Set once, at the start of a command, before anything large is allocated; skipped where
the C library is not glibc, and where the user set either threshold in the environment
(`MALLOC_MMAP_THRESHOLD_`, `MALLOC_TRIM_THRESHOLD_`: theirs win) or `DQNLAB_MALLOC=default`.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import platform

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc's malloc.h
MMAP_THRESHOLD_BYTES = 64 << 20
TRIM_THRESHOLD_BYTES = 256 << 20
USER_SETTINGS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds (see the module's docstring); whether it did."""
    if os.environ.get("DQNLAB_MALLOC") == "default" or any(
        name in os.environ for name in USER_SETTINGS
    ):
        return False
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(
        mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)
    )
