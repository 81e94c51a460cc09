"""OnEI's smoothed per-pixel estimate (:class:`LowPassEstimate`) and its compiled passes: the
low-pass fold of a solution and the calibration maps."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from ..calibration import CALIBRATION_MAPS, DEFAULT_BIAS, DEFAULT_CONTRAST, Reason, Special
from ..errors import StateError
from ..special import K_POPULATION, Z_MEASUREMENT, label_one, population_limits
from .kernels import jit

VALID = int(Reason.VALID)
_UNOBSERVED, _NORMAL = int(Special.UNOBSERVED), int(Special.NORMAL)


@jit()
def low_pass(c_new: np.ndarray, b_new: np.ndarray, se_c_new: np.ndarray, se_b_new: np.ndarray,
              ok: np.ndarray, reason_new: np.ndarray, smoothing: float, c: np.ndarray,
              b: np.ndarray, se_c: np.ndarray, se_b: np.ndarray, seen: np.ndarray,
              n_solved: np.ndarray, reason: np.ndarray, track: np.ndarray,
              corr: float) -> Any:  # pragma: no cover - compiled
    """Fold one solve into the smoothed estimate, in place (OnEI's low-pass with start-up
    correction). New values pass through float32, as they did through a Calibration.

    ``track`` (``[4, n]``) follows the variance of the smoothed estimate in units of the
    solves' own variances: ``var_c``, ``var_b`` and ``C = sum_i w_i se_i corr^age_i`` for
    each (the weights the estimate gives its solves, each solve's error, its age in updates):
    a new solve ``s`` correlates with the estimate by ``se_s C`` (solves ``k`` updates apart
    share about ``corr^k`` of their equations), so ``var <- (1-a)^2 var + a^2 se_s^2 +
    2 a (1-a) se_s C`` and ``C <- (1-a) C + a se_s``; every update ages ``C`` by ``corr``."""
    for i in range(c.size):
        # (an infinite C of a solve without residual freedom stays infinite, never 0 * inf)
        if corr > 0.0:
            track[2, i] *= corr
            track[3, i] *= corr
        else:
            track[2, i] = 0.0
            track[3, i] = 0.0
        if ok[i]:
            n_solved[i] += 1
            n = n_solved[i] if n_solved[i] >= 1 else 1
            a = 1.0 / n
            if smoothing >= a:
                a = smoothing
            c[i] += a * (np.float64(np.float32(c_new[i])) - c[i])
            b[i] += a * (np.float64(np.float32(b_new[i])) - b[i])
            se_c[i] = np.float64(np.float32(se_c_new[i]))
            se_b[i] = np.float64(np.float32(se_b_new[i]))
            for m in range(2):
                sn = se_c[i] if m == 0 else se_b[i]
                if a >= 1.0:  # the solve replaces the estimate
                    track[m, i] = sn * sn
                    track[2 + m, i] = sn
                else:
                    track[m, i] = ((1.0 - a) ** 2 * track[m, i] + a * a * sn * sn
                                   + 2.0 * a * (1.0 - a) * sn * track[2 + m, i])
                    track[2 + m, i] = (1.0 - a) * track[2 + m, i] + a * sn
            seen[i] = True
        reason[i] = VALID if seen[i] else reason_new[i]


@jit()
def _estimate_maps(lo: int, hi: int, c: np.ndarray, b: np.ndarray, track: np.ndarray,
                   f_c: float, f_b: float, seen: np.ndarray, reason: np.ndarray, z: float,
                   limits: np.ndarray, significant: bool, c32: np.ndarray, b32: np.ndarray,
                   se_c32: np.ndarray, se_b32: np.ndarray, reason_out: np.ndarray,
                   valid_out: np.ndarray,
                   special_out: np.ndarray) -> None:  # pragma: no cover - compiled
    """Pixels ``lo .. hi`` of the calibration maps of the estimate, in one pass (threads
    take disjoint ranges): the float32 contrast, bias and standard errors (the smoothed
    estimate's, ``track``'s variances, times ``f_c`` and ``f_b``; inf where not valid), the
    reasons, the valid mask and the special classes (:func:`~evcal.special.classify`'s rule
    with the population's ``limits``, judged by those errors)."""
    b_low, b_high, c_low, c_high = limits[0], limits[1], limits[2], limits[3]
    # slices first: a loop from 0 vectorises (indices from lo could be negative, numba's
    # wraparound then costs 3-7x)
    c, b, var_c, var_b = c[lo:hi], b[lo:hi], track[0, lo:hi], track[1, lo:hi]
    seen, reason, c32, b32 = seen[lo:hi], reason[lo:hi], c32[lo:hi], b32[lo:hi]
    se_c32, se_b32, reason_out = se_c32[lo:hi], se_b32[lo:hi], reason_out[lo:hi]
    valid_out, special_out = valid_out[lo:hi], special_out[lo:hi]
    for i in range(hi - lo):
        v = seen[i]
        se_c = f_c * np.sqrt(var_c[i] if var_c[i] > 0.0 else 0.0)
        se_b = f_b * np.sqrt(var_b[i] if var_b[i] > 0.0 else 0.0)
        c32[i] = c[i]
        b32[i] = b[i]
        se_c32[i] = se_c if v else np.inf
        se_b32[i] = se_b if v else np.inf
        reason_out[i] = reason[i]
        valid_out[i] = v
        k = label_one(c[i], b[i], se_c, se_b, z, b_low, b_high, c_low, c_high)
        k = k if significant else _NORMAL
        special_out[i] = k if v else _UNOBSERVED


class LowPassEstimate:
    """OnEI's smoothed per-pixel estimate (flat maps) and its low-pass update.

    ``est <- (1 - a) est + a new`` on pixels whose new solution is valid, with
    ``a = max(smoothing, 1 / n)`` for a pixel's ``n``-th valid solution (the start-up
    correction: the first ``1 / smoothing`` solutions are averaged with equal weights).
    """

    ARRAYS = ("c", "b", "se_c", "se_b", "seen", "n_solved", "reason", "track")
    # the special-pixel classes' population statistics come from at most about this many
    # pixels (special.classify): exact up to 346x260 and more, 7x fewer medians at 1280x720
    POPULATION_SAMPLE = 1 << 17

    def __init__(self, n_pixels: int) -> None:
        self.c = np.full(n_pixels, DEFAULT_CONTRAST)
        self.b = np.full(n_pixels, DEFAULT_BIAS)
        self.se_c = np.full(n_pixels, np.inf)
        self.se_b = np.full(n_pixels, np.inf)
        self.seen = np.zeros(n_pixels, bool)  # a valid solution was folded in
        self.n_solved = np.zeros(n_pixels, np.int64)  # valid solutions of each pixel so far
        self.reason = np.full(n_pixels, Reason.NO_EVENTS, np.uint8)
        # the smoothed estimate's variance, in the solves' own units (low_pass)
        self.track = np.zeros((4, n_pixels))

    def smoothed_errors(self) -> tuple[np.ndarray, np.ndarray]:
        """The standard errors of the smoothed estimate in the solves' own units (``inf``
        where never solved)."""
        with np.errstate(invalid="ignore"):
            out = np.sqrt(np.maximum(self.track[:2], 0.0))
        out[:, ~self.seen] = np.inf
        return out[0], out[1]

    def maps(self, shape: tuple[int, int],
             on_threads: Callable[[int, Callable[[int, int, int], None]], None] | None = None,
             *, scale: tuple[float, float] = (1.0, 1.0)) -> dict[str, np.ndarray]:
        """The calibration maps of the estimate (new arrays of the schema's dtypes; defaults
        where never solved), special classes as :func:`~evcal.special.classify`'s, in one
        compiled pass; ``on_threads(n, work)`` may split it into ranges ``work(thread, lo,
        hi)`` (the calibrator's threads). The standard errors stated (and special pixels
        judged by) are :meth:`smoothed_errors` times ``scale`` (``c``'s, ``b``'s)."""
        n = self.c.size
        f_c, f_b = (float(v) for v in scale)
        limits = population_limits(self.c, self.b, self.seen, K_POPULATION,
                                   self.POPULATION_SAMPLE)
        # every map of the schema but the counts of events used (the calibrator's)
        out = {spec.name: np.empty(n, spec.dtype) for spec in CALIBRATION_MAPS
               if spec.name != "n_events"}

        def work(_i: int, lo: int, hi: int) -> None:
            _estimate_maps(lo, hi, self.c, self.b, self.track, f_c, f_b, self.seen,
                           self.reason, Z_MEASUREMENT,
                           np.zeros(4) if limits is None else limits, limits is not None,
                           out["contrast"], out["bias"], out["stderr_contrast"],
                           out["stderr_bias"], out["reason"], out["valid"], out["special"])

        if on_threads is None:
            work(0, 0, n)
        else:
            on_threads(n, work)
        return {k: v.reshape(shape) for k, v in out.items()}

    def state(self) -> dict[str, np.ndarray]:
        return {name: getattr(self, name) for name in self.ARRAYS}

    def load(self, state: dict[str, np.ndarray]) -> None:
        """Copy a :meth:`state` in (shapes checked; :class:`StateError` otherwise). A state
        without ``track`` (written before it was kept) starts it as one solve's."""
        for name in self.ARRAYS:
            if name == "track" and name not in state:
                self.track[:] = 0.0
                for m, se in enumerate((self.se_c, self.se_b)):
                    fin = self.seen & np.isfinite(se)
                    self.track[m, fin] = se[fin] ** 2
                    self.track[2 + m, fin] = se[fin]
                continue
            load_into(getattr(self, name), state[name], name)


def load_into(dst: np.ndarray, src: np.ndarray, name: str) -> None:
    if np.shape(src) != dst.shape:
        raise StateError(f"state {name} has shape {np.shape(src)}, expected {dst.shape}")
    dst[:] = src
