"""The service's garbage-collector policy: long-lived objects frozen, pauses measured.

CPython's cyclic collector scans every tracked container of the generation it collects. A
full (generation 2) collection of the service after start-up visits the modules, zenoh's and
numba's objects and the compiled kernels' metadata (tens of ms: docs/MEASUREMENTS.md), which,
when it lands on a frame, is that frame's latency. Those
objects live as long as the process, so they are moved out of the collector's sight
(:func:`gc.freeze`) once the service is up and again after each camera's first update (its
kernels loaded, its state allocated). Later garbage is collected as before, and the
collector's pauses are measured (``gc`` in each camera's status), so an operator sees them.
"""

from __future__ import annotations

import gc
import threading
import time
from typing import Any


class GcPolicy:
    """Freeze the objects alive now and measure every collection's pause (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._t0 = 0.0
        self.collections = [0, 0, 0]
        self.pause_ms = [0.0, 0.0, 0.0]
        self.max_pause_ms = 0.0
        self.freezes = 0
        self._installed = False

    def _callback(self, phase: str, info: dict[str, Any]) -> None:
        # runs in whichever thread triggered the collection, under the GIL: no allocation
        # of note, never raises
        if phase == "start":
            self._t0 = time.perf_counter()
            return
        ms = (time.perf_counter() - self._t0) * 1e3
        g = int(info.get("generation", 0))
        if 0 <= g <= 2:
            self.collections[g] += 1
            self.pause_ms[g] += ms
        if ms > self.max_pause_ms:
            self.max_pause_ms = ms

    def install(self) -> None:
        if not self._installed:
            gc.callbacks.append(self._callback)
            self._installed = True

    def uninstall(self) -> None:
        if self._installed:
            try:
                gc.callbacks.remove(self._callback)
            except ValueError:
                pass
            self._installed = False

    def freeze(self) -> None:
        """Collect what is garbage now, then move every surviving object to the permanent
        generation (they are not scanned again)."""
        with self._lock:
            gc.collect()
            gc.freeze()
            self.freezes += 1

    def stats(self) -> dict[str, Any]:
        return {"collections": list(self.collections),
                "pause_ms": [round(x, 3) for x in self.pause_ms],
                "max_pause_ms": round(self.max_pause_ms, 3),
                "frozen_objects": gc.get_freeze_count(), "freezes": self.freezes}
