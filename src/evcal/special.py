"""Special pixels: hot, cold, warm and cool, as significant departures from the population.

A pixel is special in ``c`` when its whole confidence interval ``c ± z·se_c`` lies outside the
population's central band ``median ± k·s`` (``s`` the robust spread, 1.4826·MAD of the valid
pixels): it is both far from the others and measured well enough to say so. The same for
``b``. Contrast departures take precedence (a hot pixel with a strange bias is hot).
"""

from __future__ import annotations

import numpy as np

from .calibration import Special


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
    k_population: float = 3.0,
    z_measurement: float = 2.0,
) -> np.ndarray:
    """Special-pixel class codes (:class:`~evcal.calibration.Special`, uint8, same shape)."""
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
