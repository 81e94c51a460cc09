"""Special pixels: hot, cold, warm and cool, as significant departures from the population.

A pixel is special in ``c`` when its whole confidence interval ``c ± z·se_c`` lies outside the
population's central band ``median ± k·s`` (``s`` the robust spread, 1.4826·MAD of the valid
pixels): it is both far from the others and measured well enough to say so. The same for
``b``. Contrast departures take precedence (a hot pixel with a strange bias is hot).
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np

from .calibration import Special

_UNOBSERVED, _NORMAL = int(Special.UNOBSERVED), int(Special.NORMAL)
_HOT, _COLD = int(Special.HOT), int(Special.COLD)
_WARM, _COOL = int(Special.WARM), int(Special.COOL)
K_POPULATION = 3.0  # the population's central band: median -+ this many robust spreads
Z_MEASUREMENT = 2.0  # a pixel's interval: its value -+ this many standard errors


def robust_spread(v: np.ndarray) -> tuple[float, float]:
    """Median and 1.4826·MAD (a Gaussian's sigma for Gaussian data)."""
    med = float(np.median(v))
    return med, 1.4826 * float(np.median(np.abs(v - med)))


def classify(
    contrast: np.ndarray,
    bias: np.ndarray,
    stderr_contrast: np.ndarray,
    stderr_bias: np.ndarray,
    valid: np.ndarray,
    *,
    k_population: float = K_POPULATION,
    z_measurement: float = Z_MEASUREMENT,
    population_sample: int | None = None,
) -> np.ndarray:
    """Special-pixel class codes (:class:`~evcal.calibration.Special`, uint8, same shape).

    ``population_sample``: when more pixels are valid, the population's median and spread
    come from about that many of them, those on an even lattice (float64 maps only; a live
    estimate's choice: at 1280x720 the four exact medians are most of the maps' cost, and
    the lattice's sampling error, about ``1.25 / sqrt(population_sample)`` of the spread, is
    far inside the ``k_population`` spreads that decide a class).
    """
    if (_all_float64(contrast, bias, stderr_contrast, stderr_bias)
            and isinstance(valid, np.ndarray) and valid.dtype == bool
            and valid.shape == np.shape(contrast)):
        return _classify_f64(contrast, bias, stderr_contrast, stderr_bias, valid,
                             k_population, z_measurement, population_sample)
    out = np.full(np.shape(contrast), Special.UNOBSERVED, np.uint8)
    out[valid] = Special.NORMAL
    if np.count_nonzero(valid) < 10:
        return out
    c_med, c_s = robust_spread(contrast[valid])
    b_med, b_s = robust_spread(bias[valid])
    c_lo_ci = contrast - z_measurement * stderr_contrast
    c_hi_ci = contrast + z_measurement * stderr_contrast
    b_lo_ci = bias - z_measurement * stderr_bias
    b_hi_ci = bias + z_measurement * stderr_bias
    # warm/cool first so that hot/cold overwrite them
    out[valid & (b_hi_ci < b_med - k_population * b_s)] = Special.WARM
    out[valid & (b_lo_ci > b_med + k_population * b_s)] = Special.COOL
    out[valid & (c_hi_ci < c_med - k_population * c_s)] = Special.HOT
    out[valid & (c_lo_ci > c_med + k_population * c_s)] = Special.COLD
    return out


def _all_float64(*arrays: Any) -> bool:
    shape = np.shape(arrays[0])
    return all(isinstance(a, np.ndarray) and a.dtype == np.float64 and a.shape == shape
               for a in arrays)


def _classify_f64(contrast: np.ndarray, bias: np.ndarray, stderr_contrast: np.ndarray,
                  stderr_bias: np.ndarray, valid: np.ndarray, k_population: float,
                  z_measurement: float, population_sample: int | None = None) -> np.ndarray:
    """:func:`classify` for float64 maps: numpy's medians, then one compiled pass (the same
    operations as the generic path, so the same classes)."""
    shape = np.shape(contrast)
    v = np.ascontiguousarray(valid).ravel()
    c, b = np.ravel(contrast), np.ravel(bias)
    limits = population_limits(c, b, v, k_population, population_sample)
    out = _label(np.ascontiguousarray(c), np.ascontiguousarray(b),
                 np.ascontiguousarray(np.ravel(stderr_contrast)),
                 np.ascontiguousarray(np.ravel(stderr_bias)), v, float(z_measurement),
                 np.zeros(4) if limits is None else limits, limits is not None)
    result: np.ndarray = out.reshape(shape)
    return result


def population_limits(c: np.ndarray, b: np.ndarray, valid: np.ndarray, k_population: float,
                      population_sample: int | None = None) -> np.ndarray | None:
    """The central bands of flat float64 ``c`` and ``b`` over the ``valid`` pixels as
    ``[b_low, b_high, c_low, c_high]`` (median -+ k spreads), None under 10 valid pixels.

    ``population_sample``: when more pixels are valid, from the valid pixels of an even
    lattice of every ``n_valid // population_sample``-th pixel (about that many; reading only
    the lattice, not a pass over the whole sensor)."""
    n_valid = int(np.count_nonzero(valid))
    if n_valid < 10:
        return None
    if population_sample is not None and n_valid > population_sample:
        idx = np.arange(0, valid.size, n_valid // population_sample)
        idx = idx[valid[idx]]
        if idx.size < 10:  # the valid pixels avoid the lattice: all of them
            idx = np.flatnonzero(valid)
        c_pop, b_pop = c[idx], b[idx]
    else:
        c_pop, b_pop = c[valid], b[valid]
    c_med, c_s = _robust_spread_f64(c_pop)
    b_med, b_s = _robust_spread_f64(b_pop)
    return np.array([b_med - k_population * b_s, b_med + k_population * b_s,
                     c_med - k_population * c_s, c_med + k_population * c_s])


@numba.njit(cache=True, nogil=True, inline="always")
def label_one(c: float, b: float, se_c: float, se_b: float, z: float, b_low: float,
              b_high: float, c_low: float, c_high: float) -> int:  # pragma: no cover
    """The class of one valid pixel whose population is significant (contrast departures
    overwrite bias departures)."""
    k = _NORMAL  # selects, not branches: the pixel loops vectorise
    k = _WARM if b + z * se_b < b_low else k
    k = _COOL if b - z * se_b > b_high else k
    k = _HOT if c + z * se_c < c_low else k
    k = _COLD if c - z * se_c > c_high else k
    return k


@numba.njit(cache=True, nogil=True)
def _label(c: np.ndarray, b: np.ndarray, se_c: np.ndarray, se_b: np.ndarray, valid: np.ndarray,
           z: np.ndarray, limits: np.ndarray, significant: np.ndarray) -> Any:
    n = c.size
    out = np.empty(n, np.uint8)
    b_low, b_high, c_low, c_high = limits[0], limits[1], limits[2], limits[3]
    for i in range(n):
        if not valid[i]:
            out[i] = _UNOBSERVED
            continue
        out[i] = (label_one(c[i], b[i], se_c[i], se_b[i], z, b_low, b_high, c_low, c_high)
                  if significant else _NORMAL)
    return out


def _median_f64(v: np.ndarray) -> float:
    """``np.median`` of a 1-D float64 array, faster: one single-kth partition (numpy's median
    partitions at two kth, ~10x slower), the other middle value being the largest of the
    lower half. Same value: an order statistic, or ``(a + b) / 2`` of the two middle ones."""
    n = v.size
    if n == 0 or np.isnan(v).any():
        return float(np.median(v))
    h = n // 2
    part = np.partition(v, h)
    if n % 2:
        return float(part[h])
    return float((part[:h].max() + part[h]) / 2)


def _robust_spread_f64(v: np.ndarray) -> tuple[float, float]:
    """:func:`robust_spread` of a 1-D float64 array (same values, see :func:`_median_f64`)."""
    med = _median_f64(v)
    return med, 1.4826 * _median_f64(np.abs(v - med))
