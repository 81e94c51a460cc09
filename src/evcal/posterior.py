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

Where the estimator states how each pixel's errors of ``c`` and ``b`` correlate (OffEI:
``diagnostics.error_correlation``, in memory), the two are pulled together: with the pixel's
error covariance ``S`` and ``T = diag(tau_c^2, tau_b^2)`` from each map's own bin, the
posterior mean is ``mu + T (T + S)^-1 (x - mu)`` and its covariance ``T - T (T + S)^-1 T``.
A pixel's events measure one combination of ``c`` and ``b`` well (the threshold of the
polarity it fires most) and the other poorly; pulling each map alone moves both, the joint
pull mostly the poor one. Without a stated correlation (OnEI, a calibration read from a
file) each map is pulled alone, which is the joint pull with no correlation.

Special pixels (hot, cold, warm, cool: :mod:`evcal.special`) are judged on their own
evidence and keep their raw estimates; they and the invalid pixels are not in the
population. Nor is a valid pixel without a stated error (infinite or NaN: OnEI's pixels
whose solves had no residual freedom): there is nothing to weigh its estimate by, so it
keeps it. Only estimators whose errors are calibrated get posterior maps: OffEI's and
OnEI's (:mod:`evcal.onei.stderr`; offline also checked on the recording's two halves,
:mod:`evcal.splithalf`); OffE states none, and shrinking by errors that
are not calibrated would pull too hard or not at all. The raw estimate is always there: it
is what the estimator returns, and :func:`posterior_maps` returns a new calibration saying it
holds the posterior (``diagnostics.extra["estimate"]``).

There is no pull toward a pixel's neighbours: the estimates' errors are themselves
correlated between neighbouring pixels (they share the scene's edges), so a neighbourhood
says less about a pixel than it seems to, even where the true maps have spatial structure.
What the posterior gains and costs is measured in docs/MEASUREMENTS.md.

The priors and their use are apart (:func:`posterior_priors`, :func:`apply_priors`): the
priors move slowly with the maps, so a live service refreshes them now and then and applies
them to every update (a few elementwise passes over the maps); :func:`posterior_maps` does
both at once.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from functools import partial
from typing import Any

import numba
import numpy as np

from .calibration import Calibration, Special
from .errors import ConfigError

__all__ = ["BINS", "POSTERIOR_METHODS", "LivePosterior", "MapPrior", "PosteriorPriors",
           "apply_priors", "estimate_of", "posterior_maps", "posterior_priors"]

BINS = 8  # equal-count bins of the stated error, each with its own prior
MIN_BIN_PIXELS = 50  # fewer pixels than this per bin: fewer bins
TAU2_FLOOR_SHARE = 0.02  # tau^2 is at least this share of the estimates' robust variance
MAD_TO_SD = 1.4826
# the priors come from an evenly strided sample of at most about this many pool pixels: a
# median of a few thousand pixels per bin is as good as one of all of them, at a fraction of
# the cost (a live service applies a posterior to every update)
PRIOR_PIXELS = 16384
POSTERIOR_METHODS = ("offei", "onei")  # estimators whose stated errors are calibrated

# ``split(n, work)`` runs ``work(lo, hi)`` over ranges of n pixels (OnEIExecutor.split)
Split = Callable[[int, Callable[[int, int], None]], None]
# ``submit(fn, *args)`` runs ``fn(*args)`` on a worker thread (OnEIExecutor.submit)
Submit = Callable[..., "Future[Any]"]


@dataclass(frozen=True)
class MapPrior:
    """The prior of one map: bins of the stated error (``edges``: the upper bounds of all
    bins but the last), each bin's centre ``mu`` and spread ``tau2``."""

    edges: np.ndarray
    mu: np.ndarray
    tau2: np.ndarray
    pixels: np.ndarray  # pool pixels per bin (estimated from the sample)

    def doc(self) -> list[dict[str, float]]:
        return [{"bin": k, "pixels": int(self.pixels[k]), "mu": float(self.mu[k]),
                 "tau": float(np.sqrt(self.tau2[k])),
                 "stderr_below": float(self.edges[k]) if k < self.edges.size else float("inf")}
                for k in range(self.mu.size) if self.pixels[k] > 0]


@dataclass(frozen=True)
class PosteriorPriors:
    """The priors of ``contrast`` and ``bias`` (:func:`posterior_priors`); ``None`` where
    the pool has fewer than two pixels (that map is left as it is)."""

    contrast: MapPrior | None
    bias: MapPrior | None
    pool_pixels: int
    bins: int


def estimate_of(cal: Calibration) -> str:
    """``"posterior"`` when ``cal`` holds :func:`posterior_maps`' maps, else ``"raw"``."""
    return str(cal.diagnostics.extra.get("estimate", "raw"))


def _check(cal: Calibration) -> None:
    if cal.method not in POSTERIOR_METHODS:
        raise ConfigError(f"posterior maps need calibrated standard errors: "
                          f"{', '.join(POSTERIOR_METHODS)} has them, {cal.method} does not")
    if estimate_of(cal) == "posterior":
        raise ConfigError("this calibration holds posterior maps already")


def _pool(cal: Calibration) -> np.ndarray:
    pool: np.ndarray = cal.valid & (cal.special == Special.NORMAL)
    return pool


def posterior_priors(cal: Calibration, *, bins: int = BINS) -> PosteriorPriors:
    """The population priors of ``cal``'s raw maps (see the module docstring). Raises
    :class:`ConfigError` as :func:`posterior_maps` does."""
    _check(cal)
    pool = _pool(cal)
    return PosteriorPriors(_prior(cal.contrast, cal.stderr_contrast, pool, bins),
                           _prior(cal.bias, cal.stderr_bias, pool, bins),
                           int(pool.sum()), int(bins))


def apply_priors(cal: Calibration, priors: PosteriorPriors, *, split: Split | None = None,
                 note: dict[str, Any] | None = None) -> Calibration:
    """``cal`` with its valid, normal pixels' ``contrast``, ``bias`` and their standard
    errors replaced by their posterior under ``priors`` (from this calibration or an
    earlier one of the same sensor); everything else, the special pixels' values included,
    as it was. ``split(n, work)``: runs ``work(lo, hi)`` over ranges of the ``n`` pixels
    (on threads: :meth:`evcal.onei.OnEIExecutor.split`); None: one pass here. ``note``:
    more figures for the diagnostics' ``posterior`` entry."""
    _check(cal)
    pool = _pool(cal)
    rho = _correlation(cal)
    joint = rho.size > 0 and priors.contrast is not None and priors.bias is not None
    c, se_c, b, se_b = _apply(cal, rho, pool, priors.contrast, priors.bias, split)
    info: dict[str, Any] = {
        "estimate": "posterior",
        "posterior": {"pixels": priors.pool_pixels, "bins": priors.bins,
                      "joint": joint,
                      "contrast_prior": priors.contrast.doc() if priors.contrast else [],
                      "bias_prior": priors.bias.doc() if priors.bias else [],
                      **(note or {})},
    }
    diag = cal.diagnostics
    diag = diag.updated(extra={**diag.extra, **info})
    return cal.replace(contrast=c, bias=b, stderr_contrast=se_c, stderr_bias=se_b,
                       diagnostics=diag)


def posterior_maps(cal: Calibration, *, bins: int = BINS) -> Calibration:
    """``cal`` with its valid, normal pixels' ``contrast``, ``bias`` and their standard
    errors replaced by the posterior's (see the module docstring); everything else, the
    special pixels' values included, as it was. Raises :class:`ConfigError` for a method
    whose errors are not calibrated or a calibration that holds the posterior already."""
    return apply_priors(cal, posterior_priors(cal, bins=bins))


def _prior(est: np.ndarray, se: np.ndarray, pool: np.ndarray, bins: int) -> MapPrior | None:
    """The prior of one map from (a strided sample of) its ``pool`` pixels."""
    x = est[pool]
    s = se[pool]
    step = max(1, x.size // PRIOR_PIXELS)
    x = x[::step].astype(np.float64)
    s = s[::step].astype(np.float64)
    # the pixels the pull applies to: a stated error (the others keep their own estimates)
    finite = np.isfinite(x) & np.isfinite(s)
    x, s = x[finite], s[finite]
    if x.size < 2:
        return None
    n_bins = int(max(1, min(bins, x.size * step // MIN_BIN_PIXELS)))
    # equal-count bins of the stated error
    edges = np.quantile(s, np.linspace(0, 1, n_bins + 1)[1:-1])
    which = np.searchsorted(edges, s, side="right")
    mu = np.zeros(n_bins)
    tau2 = np.zeros(n_bins)
    pixels = np.zeros(n_bins, np.int64)
    for k in range(n_bins):
        xk, sk = x[which == k], s[which == k]
        if not xk.size:
            continue
        mu[k] = float(np.median(xk))
        robust = (MAD_TO_SD * float(np.median(np.abs(xk - mu[k])))) ** 2
        noise = float(np.median(sk ** 2))
        tau2[k] = max(robust - noise, TAU2_FLOOR_SHARE * robust, 1e-12)
        pixels[k] = xk.size * step
    return MapPrior(edges, mu, tau2, pixels)


def _correlation(cal: Calibration) -> np.ndarray:
    """The correlation of each pixel's errors of ``c`` and ``b`` (flat float32, NaN read as
    0), where the estimator stated it (OffEI, in memory: ``diagnostics.error_correlation``);
    else an empty array (no correlation)."""
    rho = getattr(cal.diagnostics, "error_correlation", None)
    if rho is None or np.shape(rho) != cal.shape:
        return np.zeros(0, np.float32)
    out: np.ndarray = np.nan_to_num(np.asarray(rho, np.float32).ravel(), nan=0.0)
    return out


_NO_PRIOR = (np.zeros(0, np.float32), np.zeros(1, np.float32), np.ones(1, np.float32))


def _apply(cal: Calibration, rho: np.ndarray, pool: np.ndarray, pc: MapPrior | None,
           pb: MapPrior | None, split: Split | None
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Both maps' posterior and standard errors (float32, the maps' shape) in one compiled
    pass (:func:`_pull_kernel`); a map without a prior is left as it is."""
    shape = cal.shape
    xc, sc, xb, sb = (np.ascontiguousarray(a, np.float32).ravel() for a in (
        cal.contrast, cal.stderr_contrast, cal.bias, cal.stderr_bias))
    outs = [np.empty(xc.size, np.float32) for _ in range(4)]
    priors = [_NO_PRIOR if p is None else
              (p.edges.astype(np.float32), p.mu.astype(np.float32), p.tau2.astype(np.float32))
              for p in (pc, pb)]
    args = (xc, sc, xb, sb, rho, np.ascontiguousarray(pool).ravel(), *priors[0], *priors[1],
            pc is not None, pb is not None, *outs)
    if split is None:
        _pull_kernel(*args, 0, xc.size)
    else:
        split(xc.size, lambda lo, hi: _pull_kernel(*args, lo, hi))
    c, se_c, b, se_b = (o.reshape(shape) for o in outs)
    return c, se_c, b, se_b


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _bin(s: np.float32, edges: np.ndarray) -> int:  # pragma: no cover - compiled
    k = 0
    for j in range(edges.size):  # a count, not a search: no branch to mispredict
        k += s >= edges[j]
    return k


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _pull_kernel(xc: np.ndarray, sc: np.ndarray, xb: np.ndarray, sb: np.ndarray,
                 rho: np.ndarray, pool: np.ndarray, ec: np.ndarray, mc: np.ndarray,
                 tc: np.ndarray, eb: np.ndarray, mb: np.ndarray, tb: np.ndarray,
                 has_c: bool, has_b: bool, oc: np.ndarray, osc: np.ndarray, ob: np.ndarray,
                 osb: np.ndarray, lo: int, hi: int) -> None:  # pragma: no cover - compiled
    # one pass over both maps: a live service shrinks every update's maps, and numpy's
    # passes (bin search, gathers, masks) cost as much as the update itself.
    # A pixel's errors of c and b correlate: what its events measure well is a combination
    # of the two (the threshold of the polarity it fires most), and pulling each map alone
    # moves that combination as much as the poorly measured one, which the pixel's own
    # events contradict. With the pixel's error covariance S and T = diag(tau_c^2, tau_b^2)
    # of each map's own error bin: posterior mean mu + T (T + S)^-1 (x - mu), covariance
    # T - T (T + S)^-1 T, of which the diagonal is stated; no correlation (an empty rho)
    # makes it each map's own pull. A pixel without a stated error (NaN or infinite) has no
    # weight to be pulled by: it keeps its estimate.
    inf = np.float32(np.inf)
    for i in range(lo, hi):
        a = xc[i]
        bb = xb[i]
        sa = sc[i] if np.isfinite(sc[i]) else inf
        sv = sb[i] if np.isfinite(sb[i]) else inf
        kc = _bin(sa, ec)
        kb = _bin(sv, eb)
        t1, m1 = tc[kc], mc[kc]
        t2, m2 = tb[kb], mb[kb]
        use_c = has_c and pool[i] and np.isfinite(a) and sa < inf
        use_b = has_b and pool[i] and np.isfinite(bb) and sv < inf
        s11 = sa * sa
        s22 = sv * sv
        dc = a - m1
        db = bb - m2
        # a map not pulled takes no part in the other's: no correlation with it
        r = rho[i] if rho.size > 0 and use_c and use_b else np.float32(0.0)
        if r != 0.0:
            # the 2x2 in float64: a correlation near 1 leaves little of the determinant
            r = min(max(np.float64(r), -0.999), 0.999)
            s12 = r * np.float64(sa) * sv
            a11 = np.float64(t1) + np.float64(sa) * sa
            a22 = np.float64(t2) + np.float64(sv) * sv
            det = a11 * a22 - s12 * s12
            i11 = a22 / det
            i22 = a11 / det
            i12 = -s12 / det
            oc[i] = m1 + t1 * (i11 * dc + i12 * db)
            ob[i] = m2 + t2 * (i12 * dc + i22 * db)
            osc[i] = np.sqrt(max(t1 - np.float64(t1) * t1 * i11, 0.0))
            osb[i] = np.sqrt(max(t2 - np.float64(t2) * t2 * i22, 0.0))
            continue
        w1 = t1 / (t1 + s11)
        w2 = t2 / (t2 + s22)
        oc[i] = m1 + w1 * dc if use_c else a
        ob[i] = m2 + w2 * db if use_b else bb
        osc[i] = np.sqrt(w1 * s11) if use_c else sa
        osb[i] = np.sqrt(w2 * s22) if use_b else sv


class LivePosterior:
    """Posterior maps of a stream of calibrations of one sensor (a live service's camera).

    The priors are taken from the raw maps every ``refresh_us`` of sensor time and applied to
    every calibration in between: they follow the population, which moves slowly, while
    each update's own pixels are shrunk at once. They are taken afresh, before the update
    is shrunk, when none are held yet, the maps' shape or method changes, or the sensor's
    time goes backwards (a new session). With ``submit`` a periodic refresh runs on a
    worker thread, off the update's path, and the updates keep the older priors until it
    is done (``refresh_us`` 0: at every update, before it is shrunk); with ``split`` the
    pass over the pixels is split over threads.
    """

    def __init__(self, refresh_us: int = 1_000_000, *, bins: int = BINS,
                 split: Split | None = None, submit: Submit | None = None) -> None:
        if refresh_us < 0:
            raise ConfigError(f"posterior refresh_us={refresh_us} must be >= 0")
        self.refresh_us = int(refresh_us)
        self.bins = int(bins)
        self.split = split
        self.submit = submit
        self.priors: PosteriorPriors | None = None
        self.priors_t_us: int | None = None
        self._key: tuple[tuple[int, ...], str] | None = None
        self._pending: tuple[Future[PosteriorPriors], int, tuple[tuple[int, ...], str]] \
            | None = None
        self.refreshes = 0

    def reset(self) -> None:
        """Forget the priors (a new sensor, a restore)."""
        self.priors = self.priors_t_us = self._key = self._pending = None

    def _take_pending(self) -> None:
        if self._pending is None or not self._pending[0].done():
            return
        fut, t_us, key = self._pending
        self._pending = None
        if fut.exception() is None and key == self._key:
            self.priors, self.priors_t_us = fut.result(), t_us
            self.refreshes += 1

    def apply(self, cal: Calibration, t_us: int) -> Calibration:
        """``cal``'s posterior maps (:func:`apply_priors`), with priors taken no more than
        ``refresh_us`` of sensor time before ``t_us`` (or, while a refresh on the worker
        thread runs, the ones before it)."""
        key = (tuple(cal.shape), cal.method)
        self._take_pending()
        last = self.priors_t_us
        afresh = self.priors is None or last is None or key != self._key or t_us < last
        due = afresh or (t_us - (last or 0) >= self.refresh_us and self._pending is None)
        if afresh or (due and (self.submit is None or self.refresh_us == 0)):
            # here, before this update is shrunk (0: at every update)
            self._pending = None  # a refresh of other maps, or of the old session
            self.priors = posterior_priors(cal, bins=self.bins)
            self.priors_t_us = int(t_us)
            self._key = key
            self.refreshes += 1
        elif due:
            assert self.submit is not None
            self._pending = (self.submit(partial(posterior_priors, cal, bins=self.bins)),
                             int(t_us), key)
        assert self.priors is not None
        return apply_priors(cal, self.priors, split=self.split,
                            note={"priors_t_us": self.priors_t_us})
