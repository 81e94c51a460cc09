"""OnEI's smoothed per-pixel estimate (:class:`LowPassEstimate`) and its compiled passes: the
low-pass fold of a solution and the calibration maps."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from ..calibration import CALIBRATION_MAPS, DEFAULT_BIAS, DEFAULT_CONTRAST, Reason, Special
from ..errors import StateError
from ..solver import PixelSolution
from ..special import K_POPULATION, Z_MEASUREMENT, label_one, population_limits
from .kernels import jit

VALID = int(Reason.VALID)
_UNOBSERVED, _NORMAL = int(Special.UNOBSERVED), int(Special.NORMAL)


@jit()
def low_pass(c_new: np.ndarray, b_new: np.ndarray, se_c_new: np.ndarray, se_b_new: np.ndarray,
              ok: np.ndarray, reason_new: np.ndarray, smoothing: float, c: np.ndarray,
              b: np.ndarray, se_c: np.ndarray, se_b: np.ndarray, seen: np.ndarray,
              n_solved: np.ndarray, reason: np.ndarray) -> Any:  # pragma: no cover - compiled
    """Fold one solve into the smoothed estimate, in place (OnEI's low-pass with start-up
    correction). New values pass through float32, as they did through a Calibration."""
    for i in range(c.size):
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
            seen[i] = True
        reason[i] = VALID if seen[i] else reason_new[i]


@jit()
def _estimate_maps(lo: int, hi: int, c: np.ndarray, b: np.ndarray, se_c: np.ndarray,
                   se_b: np.ndarray, seen: np.ndarray, reason: np.ndarray, z: float,
                   limits: np.ndarray, significant: bool, c32: np.ndarray, b32: np.ndarray,
                   se_c32: np.ndarray, se_b32: np.ndarray, reason_out: np.ndarray,
                   valid_out: np.ndarray,
                   special_out: np.ndarray) -> None:  # pragma: no cover - compiled
    """Pixels ``lo .. hi`` of the calibration maps of the estimate, in one pass (threads
    take disjoint ranges): the float32 contrast, bias and standard errors (inf where not
    valid), the reasons, the valid mask and the special classes (:func:`~evcal.special.
    classify`'s rule with the population's ``limits``)."""
    b_low, b_high, c_low, c_high = limits[0], limits[1], limits[2], limits[3]
    # slices first: a loop from 0 vectorises (indices from lo could be negative, numba's
    # wraparound then costs 3-7x)
    c, b, se_c, se_b = c[lo:hi], b[lo:hi], se_c[lo:hi], se_b[lo:hi]
    seen, reason, c32, b32 = seen[lo:hi], reason[lo:hi], c32[lo:hi], b32[lo:hi]
    se_c32, se_b32, reason_out = se_c32[lo:hi], se_b32[lo:hi], reason_out[lo:hi]
    valid_out, special_out = valid_out[lo:hi], special_out[lo:hi]
    for i in range(hi - lo):
        v = seen[i]
        c32[i] = c[i]
        b32[i] = b[i]
        se_c32[i] = se_c[i] if v else np.inf
        se_b32[i] = se_b[i] if v else np.inf
        reason_out[i] = reason[i]
        valid_out[i] = v
        k = label_one(c[i], b[i], se_c[i], se_b[i], z, b_low, b_high, c_low, c_high)
        k = k if significant else _NORMAL
        special_out[i] = k if v else _UNOBSERVED


class LowPassEstimate:
    """OnEI's smoothed per-pixel estimate (flat maps) and its low-pass update.

    ``est <- (1 - a) est + a new`` on pixels whose new solution is valid, with
    ``a = max(smoothing, 1 / n)`` for a pixel's ``n``-th valid solution (the start-up
    correction: the first ``1 / smoothing`` solutions are averaged with equal weights).
    """

    ARRAYS = ("c", "b", "se_c", "se_b", "seen", "n_solved", "reason")
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

    def fold(self, new: PixelSolution, smoothing: float) -> None:
        low_pass(new.c, new.b, new.se_c, new.se_b, new.valid,
                  new.reason, float(smoothing), self.c, self.b, self.se_c, self.se_b,
                  self.seen, self.n_solved, self.reason)

    def maps(self, shape: tuple[int, int],
             on_threads: Callable[[int, Callable[[int, int, int], None]], None] | None = None
             ) -> dict[str, np.ndarray]:
        """The calibration maps of the estimate (new arrays of the schema's dtypes; defaults
        where never solved), special classes as :func:`~evcal.special.classify`'s, in one
        compiled pass; ``on_threads(n, work)`` may split it into ranges ``work(thread, lo,
        hi)`` (the calibrator's threads)."""
        n = self.c.size
        limits = population_limits(self.c, self.b, self.seen, K_POPULATION,
                                   self.POPULATION_SAMPLE)
        # every map of the schema but the counts of events used (the calibrator's)
        out = {spec.name: np.empty(n, spec.dtype) for spec in CALIBRATION_MAPS
               if spec.name != "n_events"}

        def work(_i: int, lo: int, hi: int) -> None:
            _estimate_maps(lo, hi, self.c, self.b, self.se_c, self.se_b, self.seen,
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
        """Copy a :meth:`state` in (shapes checked; :class:`StateError` otherwise)."""
        for name in self.ARRAYS:
            load_into(getattr(self, name), state[name], name)


def load_into(dst: np.ndarray, src: np.ndarray, name: str) -> None:
    if np.shape(src) != dst.shape:
        raise StateError(f"state {name} has shape {np.shape(src)}, expected {dst.shape}")
    dst[:] = src
