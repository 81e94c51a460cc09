"""The per-pixel fit ``dL = c P + b E`` over frame windows, from per-pixel weighted sums.

Per window and pixel ``P = ON - OFF``, ``E = ON + OFF`` and ``dL`` the change of the frames'
log intensity (see :mod:`evcal.gap.stats`). :func:`window_sums` adds up, per pixel and in
one pass over the windows, the weighted products the least squares needs;
:func:`fit_from_sums` solves them with the estimators' solve (:mod:`evcal.solver`) and
:func:`residual_from_sums` gives the sum of squared residuals without a second pass. The
statistics (:func:`evcal.gap.stats._fit`), the APS-frame fitters (:mod:`evcal.gap.frames`)
and the bandwidth fitter (:mod:`evcal.gap.fitters`, through
:func:`lowpass_log_changes`) all fit through here.
"""

# @numba.njit is untyped (the kernels themselves are annotated), as for the modules listed
# in pyproject.toml's mypy overrides
# mypy: disallow-untyped-decorators=False

from __future__ import annotations

from typing import Any

import numba
import numpy as np

from ..solver import NormalEquations, SolveLimits, solve_pixels

MIN_FIT_EVENTS = 10


@numba.njit(cache=True, nogil=True, inline="always")
def _add(out: Any, h: int, i: int, wi: float, p: float, e: float, y: float
         ) -> None:  # pragma: no cover - compiled
    out[h, 0, i] += wi * p * p
    out[h, 1, i] += wi * p * e
    out[h, 2, i] += wi * e * e
    out[h, 3, i] += wi * p * y
    out[h, 4, i] += wi * e * y
    out[h, 5, i] += wi * e
    out[h, 6, i] += wi * y * y


@numba.njit(cache=True, nogil=True)
def _window_sums(P: np.ndarray, E: np.ndarray, dL: np.ndarray, w: np.ndarray, split: int
                 ) -> Any:  # pragma: no cover - compiled
    """Per pixel, over the windows before ``split`` ([0]) and from it on ([1]): the weighted
    sums of P P, P E, E E, P dL, E dL, E and dL dL (one pass over the windows)."""
    n_w, npix = P.shape
    out = np.zeros((2, 7, npix))
    for k in range(n_w):
        h = 0 if k < split else 1
        for i in range(npix):
            wi = np.float64(w[k, i])
            if wi == 0.0:
                continue
            _add(out, h, i, wi, np.float64(P[k, i]), np.float64(E[k, i]), np.float64(dL[k, i]))
    return out


@numba.njit(cache=True, nogil=True)
def _window_sums_by_pixel(P: np.ndarray, E: np.ndarray, dL: np.ndarray, w: np.ndarray,
                          split: int) -> Any:  # pragma: no cover - compiled
    """:func:`_window_sums` of arrays laid out ``[npix, n_w]`` (a pixel's windows adjacent),
    summed in the same order (each pixel's windows in turn): the same figures."""
    npix, n_w = P.shape
    out = np.zeros((2, 7, npix))
    for i in range(npix):
        for k in range(n_w):
            h = 0 if k < split else 1
            wi = np.float64(w[i, k])
            if wi == 0.0:
                continue
            _add(out, h, i, wi, np.float64(P[i, k]), np.float64(E[i, k]), np.float64(dL[i, k]))
    return out


@numba.njit(cache=True, nogil=True)
def _offset_window_sums(F: np.ndarray, w: np.ndarray, P: np.ndarray, E: np.ndarray,
                        offsets_dn: np.ndarray, log_offset: float
                        ) -> Any:  # pragma: no cover - compiled
    """:func:`_window_sums_by_pixel` of every observation (``P``, ``E`` ``[n_obs, npix,
    n_w]``) against ``dL`` the window changes of ``log(max(F - o, 0) + log_offset)`` (``F``
    ``[npix, n_w + 1]``) for each ``o`` of ``offsets_dn``: ``[n_obs, n_o, 7, npix]``, each
    pixel's windows summed in the same order."""
    n_obs, npix, n_w = P.shape
    n_o = offsets_dn.size
    out = np.zeros((n_obs, n_o, 7, npix))
    L = np.empty(n_w + 1)
    for i in range(npix):
        for g in range(n_o):
            o = offsets_dn[g]
            for k in range(n_w + 1):
                L[k] = np.log(max(F[i, k] - o, 0.0) + log_offset)
            for j in range(n_obs):
                # in registers, added in the order _add adds them
                spp = spe = see = spy = sey = se = syy = 0.0
                for k in range(n_w):
                    wi = np.float64(w[i, k])
                    if wi == 0.0:
                        continue
                    p = np.float64(P[j, i, k])
                    e = np.float64(E[j, i, k])
                    y = L[k + 1] - L[k]
                    spp += wi * p * p
                    spe += wi * p * e
                    see += wi * e * e
                    spy += wi * p * y
                    sey += wi * e * y
                    se += wi * e
                    syy += wi * y * y
                out[j, g, 0, i] = spp
                out[j, g, 1, i] = spe
                out[j, g, 2, i] = see
                out[j, g, 3, i] = spy
                out[j, g, 4, i] = sey
                out[j, g, 5, i] = se
                out[j, g, 6, i] = syy
    return out


def offset_window_sums(F: np.ndarray, w: np.ndarray, P: list[np.ndarray],
                       E: list[np.ndarray], offsets_dn: np.ndarray, log_offset: float
                       ) -> np.ndarray:
    """Per observation ``j`` and dark offset ``o``: :func:`window_sums` of ``P[j]``,
    ``E[j]``, ``w`` (``[windows, pixels]``) and ``dL`` the changes of ``log(max(F - o, 0) +
    log_offset)`` over the frames ``F`` (``[windows + 1, pixels]``), ``[n_obs, n_o, 7,
    npix]``: one pass that takes each pixel's logarithms once for every observation and
    allocates no ``[windows, pixels]`` array per offset."""
    f = np.ascontiguousarray(np.asarray(F, np.float64).T)
    pe = [np.stack([np.asarray(a).T for a in arrs]) for arrs in (P, E)]
    out: np.ndarray = _offset_window_sums(f, np.ascontiguousarray(np.asarray(w).T), pe[0],
                                          pe[1], np.asarray(offsets_dn, np.float64),
                                          float(log_offset))
    return out


def window_sums(P: np.ndarray, E: np.ndarray, dL: np.ndarray, wgt: np.ndarray,
                split: int | None = None) -> np.ndarray:
    """Per-pixel weighted sums ``[7, npix]`` of P P, P E, E E, P dL, E dL, E, dL dL over the
    windows (``[2, 7, npix]``: before and from window ``split``, when given).

    ``[windows, pixels]`` arrays in column order (the observations' columns of pixels taken
    with an index keep it) are summed through their transposes, which are in row order: a
    copy of each into row order would cost more than the sums."""
    arrs = [np.asarray(a) for a in (P, E, dL, wgt)]
    n_w = arrs[0].shape[0]
    at = n_w if split is None else int(split)
    by_column = sum(a.flags.f_contiguous and not a.flags.c_contiguous for a in arrs)
    if by_column >= 2:
        out: np.ndarray = _window_sums_by_pixel(
            *[np.ascontiguousarray(a.T) for a in arrs], at)
    else:
        out = _window_sums(*[np.ascontiguousarray(a) for a in arrs], at)
    return out[0] if split is None else out


@numba.njit(cache=True, nogil=True)
def lowpass_log_changes(intensity: Any, window_s: Any, offset: float, cutoff_hz: float,
                         ref_dn: float) -> Any:  # pragma: no cover - compiled
    """Per window and pixel, the change of the frames' log intensity (``[K, N]`` DN, log of
    ``I + offset``) through the bandwidth low-pass of cutoff ``cutoff_hz (I + offset) /
    ref_dn`` (at least 0.5 Hz), sampled at frame rate: ``[K - 1, N]``."""
    k_n, n = intensity.shape
    out = np.empty((max(k_n - 1, 0), n))
    for i in range(n):
        lf = np.log(np.float64(intensity[0, i]) + offset)
        for k in range(1, k_n):
            x = np.float64(intensity[k, i]) + offset
            fc = max(0.5, cutoff_hz * x / ref_dn)
            alpha = 1.0 - np.exp(-2.0 * np.pi * fc * window_s[k - 1])
            new = lf + alpha * (np.log(x) - lf)
            out[k - 1, i] = new - lf
            lf = new
    return out


def fit_pixels(P: np.ndarray, E: np.ndarray, dL: np.ndarray, wgt: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed-form per-pixel least squares of ``dL = c P + b E``; returns ``c, b, ok``."""
    return fit_from_sums(*window_sums(P, E, dL, wgt)[:6])


def residual_from_sums(sums: np.ndarray, c: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per pixel, the weighted sum of squared residuals ``dL - c P - b E`` from the sums of
    :func:`window_sums` (expanded: no second pass over the windows)."""
    spp, spe, see, spy, sey, _, syy = sums
    ss = syy - 2 * c * spy - 2 * b * sey + c * c * spp + 2 * c * b * spe + b * b * see
    out: np.ndarray = np.maximum(ss, 0.0)
    return out


def fit_from_sums(spp: np.ndarray, spe: np.ndarray, see: np.ndarray, spy: np.ndarray,
                  sey: np.ndarray, n_ev: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`fit_pixels` from the per-pixel weighted sums of ``P P``, ``P E``, ``E E``,
    ``P dL``, ``E dL`` and ``E``: the estimators' solve (:func:`evcal.solver.solve_pixels`,
    no residual correction, at least :data:`MIN_FIT_EVENTS` events), NaN where not trusted."""
    n = int(np.size(spp))
    ne = NormalEquations(n)
    for name, v in (("pp", spp), ("pe", spe), ("ee", see), ("py", spy), ("ey", sey)):
        getattr(ne, name)[:] = np.ravel(v)
    sol = solve_pixels(ne, np.floor(np.ravel(n_ev)).astype(np.int64),
                       limits=SolveLimits(min_events=MIN_FIT_EVENTS, min_equations=0.0))
    ok = sol.valid.reshape(np.shape(spp))
    c = np.where(ok, sol.c.reshape(ok.shape), np.nan)
    b = np.where(ok, sol.b.reshape(ok.shape), np.nan)
    return c, b, ok
