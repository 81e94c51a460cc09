"""The service's allocator policy (evcal.service.mallocpolicy), applied in a child process:
freed memory is kept and every thread allocates from one arena."""

from __future__ import annotations

import ctypes.util
import subprocess
import sys

import pytest

from evcal.testing import python_env

CHILD = """
import threading, numpy as np
from evcal.service.mallocpolicy import keep_freed_memory
print(keep_freed_memory())

def faults():
    with open("/proc/thread-self/stat") as f:
        return int(f.read().rsplit(")", 1)[1].split()[7])

out = []
def worker():  # 40 MiB arrays in a thread, freed and made again
    np.ones(40 << 20, np.uint8)
    before = faults()
    for _ in range(10):
        np.ones(40 << 20, np.uint8)
    out.append(faults() - before)
t = threading.Thread(target=worker); t.start(); t.join()
print(out[0])
"""


def _run(env_extra: dict[str, str]) -> list[str]:
    env = dict(python_env(), **env_extra)
    res = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True,
                         env=env, timeout=60, check=True)
    return res.stdout.split("\n")


@pytest.mark.skipif(not sys.platform.startswith("linux") or not ctypes.util.find_library("c"),
                     reason="glibc's mallopt and /proc/thread-self")
def test_a_thread_reuses_freed_memory_instead_of_faulting_fresh_pages():
    kept = _run({})
    assert kept[0].startswith("kept:")
    assert "one arena" in kept[0]
    # 10 arrays of 10,240 pages: with the thresholds but the thread's own arena, its heaps
    # were unmapped when free and 5,320 pages faulted again (measured); with one arena none
    assert int(kept[1]) < 1000
    off = _run({"EVCAL_MALLOC_KEEP": "0"})
    assert off[0] == "off (EVCAL_MALLOC_KEEP=0)"
