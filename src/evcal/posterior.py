"""Posterior maps: each pixel's estimate pulled toward the sensor's population by how little
its own evidence says (empirical Bayes).

A pixel's OffEI or OnEI estimate ``x`` has a stated standard error ``s`` (calibrated: the
spread of ``(x - truth) / s`` is about 1 on simulated data). With the pixels' true values
spread about a centre ``mu`` by ``tau``, the posterior mean is ``mu + w (x - mu)``, ``w =
tau^2 / (tau^2 + s^2)``, and its standard error ``sqrt(w) s``: a pixel of many events keeps
its own value, one of few moves toward the population.

The prior is taken per bin of the stated error, not once for the sensor: a pixel's true
threshold and its error go together (a high threshold fires fewer events, so its error is
larger), and one centre for all would pull the high-threshold pixels down. The pixels are
split into :data:`BINS` equal-count bins of their own ``s``, separately for ``c`` and ``b``;
in each, ``mu`` is the median estimate and ``tau^2`` the robust variance of the estimates
(``(1.4826 MAD)^2``) less the median ``s^2``, kept above a small share of it.

Special pixels (hot, cold, warm, cool: :mod:`evcal.special`) are judged on their own
evidence and keep their raw estimates; they and the invalid pixels are not in the
population. Only estimators whose errors are calibrated get posterior maps: OffEI's and
OnEI's (:mod:`evcal.onei.stderr`); OffE states none for ``c``, and shrinking by errors that
are not calibrated would pull too hard or not at all. The raw estimate is always there: it
is what the estimator returns, and :func:`posterior_maps` returns a new calibration saying it
holds the posterior (``diagnostics.extra["estimate"]``).

There is no pull toward a pixel's neighbours: the estimates' errors are themselves
correlated between neighbouring pixels (they share the scene's edges), so a neighbourhood
says less about a pixel than it seems to, even where the true maps have spatial structure.
What the posterior gains and costs is measured in docs/MEASUREMENTS.md.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .calibration import Calibration, Special
from .errors import ConfigError

__all__ = ["BINS", "POSTERIOR_METHODS", "estimate_of", "posterior_maps"]

BINS = 8  # equal-count bins of the stated error, each with its own prior
MIN_BIN_PIXELS = 50  # fewer pixels than this per bin: fewer bins
TAU2_FLOOR_SHARE = 0.02  # tau^2 is at least this share of the estimates' robust variance
MAD_TO_SD = 1.4826
POSTERIOR_METHODS = ("offei", "onei")  # estimators whose stated errors are calibrated


def estimate_of(cal: Calibration) -> str:
    """``"posterior"`` when ``cal`` holds :func:`posterior_maps`' maps, else ``"raw"``."""
    return str(cal.diagnostics.extra.get("estimate", "raw"))


def posterior_maps(cal: Calibration, *, bins: int = BINS) -> Calibration:
    """``cal`` with its valid, normal pixels' ``contrast``, ``bias`` and their standard
    errors replaced by the posterior's (see the module docstring); everything else, the
    special pixels' values included, as it was. Raises :class:`ConfigError` for a method
    whose errors are not calibrated or a calibration that holds the posterior already."""
    if cal.method not in POSTERIOR_METHODS:
        raise ConfigError(f"posterior maps need calibrated standard errors: "
                          f"{', '.join(POSTERIOR_METHODS)} has them, {cal.method} does not")
    if estimate_of(cal) == "posterior":
        raise ConfigError("this calibration holds posterior maps already")
    pool = cal.valid & (cal.special == Special.NORMAL)
    c, se_c, prior_c = _shrink(cal.contrast, cal.stderr_contrast, pool, bins)
    b, se_b, prior_b = _shrink(cal.bias, cal.stderr_bias, pool, bins)
    info: dict[str, Any] = {
        "estimate": "posterior",
        "posterior": {"pixels": int(pool.sum()), "bins": bins,
                      "contrast_prior": prior_c, "bias_prior": prior_b},
    }
    diag = cal.diagnostics
    diag = diag.updated(extra={**diag.extra, **info})
    return cal.replace(contrast=c, bias=b, stderr_contrast=se_c, stderr_bias=se_b,
                       diagnostics=diag)


def _shrink(est: np.ndarray, se: np.ndarray, pool: np.ndarray, bins: int
            ) -> tuple[np.ndarray, np.ndarray, list[dict[str, float]]]:
    """The posterior of one map over the ``pool`` pixels; the priors of its bins."""
    out = est.astype(np.float32, copy=True)
    out_se = se.astype(np.float32, copy=True)
    x = est[pool].astype(np.float64)
    s = se[pool].astype(np.float64)
    finite = np.isfinite(x)
    x, s = x[finite], s[finite]
    if x.size < 2:
        return out, out_se, []
    n_bins = int(max(1, min(bins, x.size // MIN_BIN_PIXELS)))
    s_sort = np.where(np.isfinite(s), s, np.inf)
    # equal-count bins of the stated error (an infinite error falls in the last)
    edges = np.quantile(s_sort[np.isfinite(s_sort)], np.linspace(0, 1, n_bins + 1)[1:-1]) \
        if np.isfinite(s_sort).any() else np.zeros(0)
    which = np.searchsorted(edges, s_sort, side="right")
    mu = np.zeros(n_bins)
    tau2 = np.zeros(n_bins)
    priors = []
    for k in range(n_bins):
        xk, sk = x[which == k], s_sort[which == k]
        if not xk.size:
            continue
        mu[k] = float(np.median(xk))
        robust = (MAD_TO_SD * float(np.median(np.abs(xk - mu[k])))) ** 2
        fin = sk[np.isfinite(sk)]
        noise = float(np.median(fin ** 2)) if fin.size else 0.0
        tau2[k] = max(robust - noise, TAU2_FLOOR_SHARE * robust, 1e-12)
        priors.append({"bin": k, "pixels": int(xk.size), "mu": mu[k],
                       "tau": float(np.sqrt(tau2[k])),
                       "stderr_below": float(edges[k]) if k < edges.size else float("inf")})
    t2, m = tau2[which], mu[which]
    with np.errstate(invalid="ignore", divide="ignore"):
        s2 = np.square(s_sort)
        w = np.where(np.isfinite(s2), t2 / (t2 + s2), 0.0)
        post_se = np.where(np.isfinite(s2), np.sqrt(w * s2), np.sqrt(t2))
    idx = np.flatnonzero(pool.ravel())[finite]
    out.flat[idx] = (m + w * (x - m)).astype(np.float32)
    out_se.flat[idx] = post_se.astype(np.float32)
    return out, out_se, priors
