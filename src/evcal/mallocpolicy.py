"""Allocator policies of evcal's processes (glibc's ``mallopt``), one per kind of run.

A long-running service wants freed memory kept for reuse (:func:`keep_freed_memory`); a batch
run whose peak is its cost (``evcal gap``) wants what it let go of handed back
(:func:`trim_freed_memory`).
Both are applied by the command-line layer, never by the library. Without glibc (or with
``EVCAL_MALLOC_KEEP=0`` / ``EVCAL_MALLOC_RETURN=0``) nothing changes.

**Kept (the service).**

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
lock would slow (Python's small objects have their own allocator).

**Handed back (the gap workflow).** A run of ``evcal gap`` makes a hundred simulations, each
allocating and freeing arrays of a few MiB to a few hundred (events, per-window counts,
intervals) in several threads. With glibc's adaptive threshold every array below 32 MiB
comes from a heap once a larger one was freed, and a heap shrinks only from its top: the
freed arrays under a live one stay in the process, and the run's resident memory climbs
from round to round. ``malloc_trim`` hands the free pages inside the heaps back; the workflow
calls it when it lets go of a round's simulations. A fixed 1 MiB mmap threshold instead
(every array its own pages) kept the peak lower still but faulted every array in anew: the
3 s 240x180 case took 164 s against 119 s (docs/MEASUREMENTS.md).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os
from typing import Any

M_TRIM_THRESHOLD = -1  # glibc's mallopt parameters
M_MMAP_THRESHOLD = -3
M_ARENA_MAX = -8
MMAP_THRESHOLD_BYTES = 256 << 20  # allocations up to this come from the heap
TRIM_THRESHOLD_BYTES = 1 << 30  # free memory at the heap's top kept up to this


@functools.cache
def _glibc() -> Any:
    """glibc (with ``mallopt`` and ``malloc_trim``), or None without it."""
    try:
        lib = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        lib.mallopt  # noqa: B018 - glibc's, not another C library's
        lib.malloc_trim  # noqa: B018
    except (OSError, AttributeError):
        return None
    return lib


def keep_freed_memory() -> str:
    """Apply the service's policy to this process; returns what was done (for its info)."""
    if os.environ.get("EVCAL_MALLOC_KEEP", "1") == "0":
        return "off (EVCAL_MALLOC_KEEP=0)"
    lib = _glibc()
    if lib is None:
        return "not available (no glibc mallopt)"
    ok = True
    for param, value in ((M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES),
                         (M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES), (M_ARENA_MAX, 1)):
        ok = lib.mallopt(param, value) == 1 and ok
    if not ok:
        return "refused by mallopt"
    return (f"kept: mmap threshold {MMAP_THRESHOLD_BYTES >> 20} MiB, trim threshold "
            f"{TRIM_THRESHOLD_BYTES >> 20} MiB, one arena")


def trim_freed_memory() -> bool:
    """Hand every heap's free pages back to the kernel (glibc's ``malloc_trim``); whether
    it could. For a batch run at the points where it let go of much (the gap workflow's
    rounds): the heaps keep serving its arrays without fresh pages in between."""
    if os.environ.get("EVCAL_MALLOC_RETURN", "1") == "0":
        return False
    lib = _glibc()
    if lib is None:
        return False
    lib.malloc_trim(0)
    return True
