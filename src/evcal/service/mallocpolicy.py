"""The service's allocator policy: freed memory kept for reuse, not handed back at once.

glibc serves an allocation above its mmap threshold (128 KiB at first, raised adaptively up
to 32 MiB) with fresh pages from the kernel and returns them when it is freed; every page
is then faulted in (and zeroed) on first touch again. A live update at 1280x720 allocates
about 40 MiB of maps and messages and frees them soon after, and fresh pages make its
calibration maps several times slower than reused ones (docs/MEASUREMENTS.md). The service
therefore raises the mmap threshold and the heap's trim threshold (``mallopt``) so that
freed memory stays in the process for the next update; its RSS then sits at its working
set's high-water mark instead of swinging about it.

Those thresholds hold for the main heap. A thread that is not the main thread allocates
from an arena of its own, made of heaps of at most 64 MiB that glibc unmaps as soon as one
is wholly free, whatever the trim threshold: the camera worker's 16 MiB messages at
1280x720 then came from fresh pages again every few updates, and those updates were many
times slower than the median (thousands of page faults each; docs/MEASUREMENTS.md). So
every thread allocates from the main arena (``M_ARENA_MAX`` 1): the service's threads
allocate large arrays a few times per frame, not small objects at a rate that the arena's
lock would slow (Python's small objects have their own allocator). Without glibc (or with
``EVCAL_MALLOC_KEEP=0``) nothing changes.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

M_TRIM_THRESHOLD = -1  # glibc's mallopt parameters
M_MMAP_THRESHOLD = -3
M_ARENA_MAX = -8
MMAP_THRESHOLD_BYTES = 256 << 20  # allocations up to this come from the heap
TRIM_THRESHOLD_BYTES = 1 << 30  # free memory at the heap's top kept up to this


def keep_freed_memory() -> str:
    """Apply the policy to this process; returns what was done (for the service's info)."""
    if os.environ.get("EVCAL_MALLOC_KEEP", "1") == "0":
        return "off (EVCAL_MALLOC_KEEP=0)"
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return "not available (no glibc mallopt)"
    ok = mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1
    ok = mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES) == 1 and ok
    ok = mallopt(M_ARENA_MAX, 1) == 1 and ok
    if not ok:
        return "refused by mallopt"
    return (f"kept: mmap threshold {MMAP_THRESHOLD_BYTES >> 20} MiB, trim threshold "
            f"{TRIM_THRESHOLD_BYTES >> 20} MiB, one arena")
