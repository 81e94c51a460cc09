"""Ideal DVS pixels: exact threshold crossings of a piecewise-linear log intensity.

Model (per pixel, log intensity ``L`` linear in time between two internal samples): an ON event
fires each time ``L - ref >= c + b`` and moves ``ref`` up by ``c + b``; an OFF event fires each
time ``ref - L >= c - b`` and moves ``ref`` down by ``c - b``. The event time is where the linear
segment crosses the level. This is the model the estimators assume; the non-ideal effects
(refractory period, noise events, bandwidth, ...) live in other modules and wrap this one.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np

from ..errors import ConfigError, ErrorReason
from ..events import EVENTS_DTYPE, empty_events


@numba.njit(cache=True, nogil=True)
def _count_crossings(l0: np.ndarray, l1: np.ndarray, ref: np.ndarray, th_on: np.ndarray,
                     th_off: np.ndarray) -> Any:  # pragma: no cover - compiled
    n = 0
    for i in range(l0.size):
        d = l1[i] - ref[i]
        if d >= th_on[i]:
            n += int(d / th_on[i])
        elif -d >= th_off[i]:
            n += int(-d / th_off[i])
    return n


@numba.njit(cache=True, nogil=True)
def _crossings(l0: np.ndarray, l1: np.ndarray, ref: np.ndarray, th_on: np.ndarray,
               th_off: np.ndarray, frac: np.ndarray, idx: np.ndarray, pol: np.ndarray) -> Any:
    """Fill ``frac`` (0..1 within the step), ``idx`` (pixel), ``pol``; update ``ref``."""
    n = 0
    for i in range(l0.size):
        a = l0[i]
        b = l1[i]
        r = ref[i]
        if b - r >= th_on[i]:
            span = b - a
            level = r + th_on[i]
            while level <= b:
                f = (level - a) / span if span > 0 else 1.0
                frac[n] = min(max(f, 0.0), 1.0)
                idx[n] = i
                pol[n] = 1
                n += 1
                r = level
                level = r + th_on[i]
        elif r - b >= th_off[i]:
            span = a - b
            level = r - th_off[i]
            while level >= b:
                f = (a - level) / span if span > 0 else 1.0
                frac[n] = min(max(f, 0.0), 1.0)
                idx[n] = i
                pol[n] = -1
                n += 1
                r = level
                level = r - th_off[i]
        ref[i] = r
    return n


class IdealDvs:
    """A sensor of ideal pixels with per-pixel contrast ``c`` and bias ``b`` maps ``[H, W]``.

    Feed it log-intensity samples in time order with :meth:`step`; it returns the events of each
    segment, sorted by time.
    """

    def __init__(self, contrast: np.ndarray, bias: np.ndarray):
        contrast = np.asarray(contrast, np.float64)
        bias = np.asarray(bias, np.float64)
        if contrast.shape != bias.shape or contrast.ndim != 2:
            raise ConfigError(f"contrast {contrast.shape} and bias {bias.shape} must be equal "
                             "[H, W]")
        th_on = contrast + bias
        th_off = contrast - bias
        if (th_on <= 0).any() or (th_off <= 0).any():
            raise ConfigError("every pixel needs c + b > 0 and c - b > 0 (|b| < c)")
        self.shape = contrast.shape
        self.th_on = th_on.ravel().copy()
        self.th_off = th_off.ravel().copy()
        self.ref: np.ndarray | None = None
        self.l_prev: np.ndarray | None = None
        self.t_prev_us = 0

    def reset(self, log_i: np.ndarray, t_us: int, rng: np.random.Generator | None = None) -> None:
        """Start at ``log_i``; with ``rng`` the reference sits at a random point of its cell."""
        l0 = np.asarray(log_i, np.float64).ravel().copy()
        ref = l0.copy()
        if rng is not None:
            # residual L - ref uniform in (-th_off, th_on): no event is due at the start
            u = rng.uniform(0.0, 1.0, l0.size)
            ref = l0 - (u * (self.th_on + self.th_off) - self.th_off)
        self.ref = ref
        self.l_prev = l0
        self.t_prev_us = int(t_us)

    def step(self, log_i: np.ndarray, t_us: int) -> np.ndarray:
        """Events while the log intensity moves linearly to ``log_i`` at ``t_us``."""
        if self.ref is None or self.l_prev is None:
            raise ConfigError("call reset() with the first log image before step()",
                              ErrorReason.REJECTED)
        l1 = np.asarray(log_i, np.float64).ravel()
        dt_us = int(t_us) - self.t_prev_us
        if dt_us <= 0:
            raise ConfigError(f"step to t_us={t_us} does not move forward from {self.t_prev_us}")
        n = _count_crossings(self.l_prev, l1, self.ref, self.th_on, self.th_off)
        if n == 0:
            self.l_prev = l1.copy()
            self.t_prev_us = int(t_us)
            return empty_events()
        frac = np.empty(n, np.float64)
        idx = np.empty(n, np.int64)
        pol = np.empty(n, np.int8)
        m = _crossings(self.l_prev, l1, self.ref, self.th_on, self.th_off, frac, idx, pol)
        frac, idx, pol = frac[:m], idx[:m], pol[:m]
        order = np.argsort(frac, kind="stable")
        ev = np.empty(m, EVENTS_DTYPE)
        ev["t_us"] = self.t_prev_us + np.rint(frac[order] * dt_us).astype(np.int64)
        w = self.shape[1]
        ii = idx[order]
        ev["y"] = ii // w
        ev["x"] = ii % w
        ev["p"] = pol[order]
        self.l_prev = l1.copy()
        self.t_prev_us = int(t_us)
        return ev
