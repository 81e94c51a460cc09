"""Event denoising: the background-activity (nearest-neighbour support) filter.

Shot noise and leak events are isolated: no neighbour of their pixel fired shortly before.
Events of a moving edge come in space-time chains. The filter keeps an event when one of the
pixels around it (its 3x3 neighbourhood without itself, or ``(2 radius + 1)^2 - 1`` pixels)
had an event within the last ``window_us`` µs -- the background-activity filter of jAER and
of most event pipelines (Delbruck 2008). One sequential pass over the events (numba), a
timestamp map of the sensor's size.

It also removes real events of isolated pixels (slow or faint edges), so it biases a fit of
the thresholds: use it where that bias is accounted for (:mod:`evcal.gap.correct` applies
the same filter to its simulations, whose difference removes it).
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np

from .events import SensorSize

__all__ = ["background_activity_filter"]


@numba.njit(cache=True, nogil=True)
def _ba_keep(t: np.ndarray, x: np.ndarray, y: np.ndarray, height: int, width: int,
             window_us: int, radius: int) -> Any:  # pragma: no cover - compiled
    last = np.full((height + 2 * radius, width + 2 * radius), np.iinfo(np.int64).min // 2,
                   np.int64)
    keep = np.zeros(t.size, np.bool_)
    for i in range(t.size):
        yy = y[i] + radius
        xx = x[i] + radius
        ti = t[i]
        ok = False
        for dy in range(-radius, radius + 1):
            for dx in range(-radius, radius + 1):
                if dy == 0 and dx == 0:
                    continue
                if ti - last[yy + dy, xx + dx] <= window_us:
                    ok = True
        keep[i] = ok
        last[yy, xx] = ti
    return keep


def background_activity_filter(events: np.ndarray, sensor: SensorSize, window_us: int, *,
                               radius: int = 1) -> np.ndarray:
    """The boolean mask of the events a neighbour supports (see the module docstring).

    ``events`` are evcal's (sorted by time, inside ``sensor``); ``window_us`` > 0.
    """
    if int(window_us) <= 0:
        raise ValueError(f"window_us={window_us} must be > 0")
    if int(radius) < 1:
        raise ValueError(f"radius={radius} must be >= 1")
    if events.size == 0:
        return np.zeros(0, bool)
    keep: np.ndarray = _ba_keep(np.ascontiguousarray(events["t_us"], np.int64),
                                np.ascontiguousarray(events["x"], np.int64),
                                np.ascontiguousarray(events["y"], np.int64),
                                int(sensor.height), int(sensor.width), int(window_us),
                                int(radius))
    return keep
