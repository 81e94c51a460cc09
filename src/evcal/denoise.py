"""Event denoising: the background-activity (nearest-neighbour support) filter, and events in
frame intervals where the frames show no change.

Shot noise and leak events are isolated: no neighbour of their pixel fired shortly before.
Events of a moving edge come in space-time chains. The filter keeps an event when one of the
pixels around it (its 3x3 neighbourhood without itself, or ``(2 radius + 1)^2 - 1`` pixels)
had an event within ``window_us`` µs before it -- the background-activity filter of jAER and
of most event pipelines (Delbruck 2008). One sequential pass over the events (numba), a
timestamp map of the sensor's size. Two refinements, both off by default:

- ``same_polarity``: only a neighbour's event of the same polarity supports. An edge makes
  events of one polarity along its path; noise takes either sign, so in a busy neighbourhood
  (a textured scene in motion, where nearly every event has some neighbour within the
  window) half of the random support goes.
- ``two_sided``: support may also come from a neighbour's event within ``window_us`` *after*
  (offline, the whole stream is known): the first event of an edge entering a quiet region
  has no predecessor but has successors.

:func:`still_interval_mask` drops the events of frame intervals in which the frames show no
change at the pixel (a change of log intensity below ``max_dl``): there a pixel fires only
from noise, or from the last fraction of a threshold it had already come, which is rare for a
small ``max_dl``.

Both remove some real events too, so they bias a fit of the thresholds: use them where that
bias is accounted for (:mod:`evcal.gap.correct` applies the same filters to its simulations,
whose difference removes it).
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np

from .errors import ConfigError
from .events import SensorSize
from .recording import Frames
from .stream import event_windows

__all__ = ["background_activity_filter", "still_interval_mask"]


@numba.njit(cache=True, nogil=True)
def _ba_keep(t: np.ndarray, x: np.ndarray, y: np.ndarray, p: np.ndarray, height: int,
             width: int, window_us: int, radius: int, same_polarity: bool,
             forward: bool) -> Any:  # pragma: no cover - compiled
    """Whether a neighbour fired within ``window_us`` before (``forward``) or after each
    event; with ``same_polarity``, an event of the same polarity."""
    n_pol = 2 if same_polarity else 1
    far = np.iinfo(np.int64).max // 4
    last = np.full((n_pol, height + 2 * radius, width + 2 * radius), -far if forward else far,
                   np.int64)
    keep = np.zeros(t.size, np.bool_)
    for j in range(t.size):
        i = j if forward else t.size - 1 - j
        yy = y[i] + radius
        xx = x[i] + radius
        ti = t[i]
        k = (1 if p[i] > 0 else 0) if same_polarity else 0
        ok = False
        for dy in range(-radius, radius + 1):
            for dx in range(-radius, radius + 1):
                if dy == 0 and dx == 0:
                    continue
                gap = ti - last[k, yy + dy, xx + dx] if forward else last[k, yy + dy, xx + dx] - ti
                if gap <= window_us:
                    ok = True
        keep[i] = ok
        last[k, yy, xx] = ti
    return keep


def background_activity_filter(events: np.ndarray, sensor: SensorSize, window_us: int, *,
                               radius: int = 1, same_polarity: bool = False,
                               two_sided: bool = False) -> np.ndarray:
    """The boolean mask of the events a neighbour supports (see the module docstring).

    ``events`` are evcal's (sorted by time, inside ``sensor``); ``window_us`` > 0.
    """
    if int(window_us) <= 0:
        raise ConfigError(f"window_us={window_us} must be > 0")
    if int(radius) < 1:
        raise ConfigError(f"radius={radius} must be >= 1")
    if events.size == 0:
        return np.zeros(0, bool)
    args = (np.ascontiguousarray(events["t_us"], np.int64),
            np.ascontiguousarray(events["x"], np.int64),
            np.ascontiguousarray(events["y"], np.int64),
            np.ascontiguousarray(events["p"], np.int64),
            int(sensor.height), int(sensor.width), int(window_us), int(radius),
            bool(same_polarity))
    keep: np.ndarray = _ba_keep(*args, True)
    if two_sided:
        keep |= _ba_keep(*args, False)
    return keep


def still_interval_mask(events: np.ndarray, frames: Frames, sensor: SensorSize,
                        max_dl: float, log_offset: float) -> np.ndarray:
    """The boolean mask of the events *not* in a frame interval where the pixel's log
    intensity ``log(I + log_offset)`` changes by less than ``max_dl`` between the frames
    that bracket it (events before the first or after the last frame are kept)."""
    if not max_dl > 0:
        raise ConfigError(f"max_dl={max_dl} must be > 0")
    n_f = len(frames)
    if events.size == 0 or n_f < 2:
        return np.ones(events.size, bool)
    log_i = np.log(frames.images.reshape(n_f, -1).astype(np.float64) + float(log_offset))
    still = np.abs(np.diff(log_i, axis=0)) < max_dl
    win = event_windows(events["t_us"], frames.t_us)
    pix = events["y"].astype(np.int64) * sensor.width + events["x"]
    inside = (win >= 0) & (win < n_f - 1)
    keep = np.ones(events.size, bool)
    keep[inside] = ~still[win[inside], pix[inside]]
    return keep
