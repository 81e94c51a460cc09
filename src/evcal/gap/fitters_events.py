"""Moment estimators of the event-side effects ``threshold_light`` and ``row_noise``, and of
the light dependence of ``leak`` (fitters of :data:`evcal.gap.model.FITTERS`).

Each takes the measured observation, the current model's simulations, the model and the
recording, and returns the effect with estimated parameters, or ``None`` when the data show
none of it. Estimates are measured minus simulated, so what the frames and the
interpolation do to the statistic alike in both cancels; the gap workflow then removes the
estimator's own bias by simulation (``GapConfig.debias``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..sim.effects import Leak, LogOffset, RowNoise, ThresholdLight
from .effects import FitContext, FitResult, Fitted, NoEvidence
from .stats import (
    LINE_COINCIDENCE_MIN,
    LINE_COINCIDENCE_US,
    Observation,
    _fit,
    _static,
    line_events,
    still_pixel_seconds,
)

# ------------------------------------------------------------------------ threshold_light

TL_MIN_EXPONENT = 0.02  # below this the thresholds' light dependence is not worth a parameter


def _dark_dn(model: Any) -> float:
    """The dark level under the sensor's log in ``model``: its ``log_offset`` effect, else
    the base offset."""
    lo = model.effects.get(LogOffset.name)
    return float(lo.dark_dn) if isinstance(lo, LogOffset) else float(model.log_offset)


def _resid(y: np.ndarray, P: np.ndarray, E: np.ndarray, w: np.ndarray,
           spp: np.ndarray, spe: np.ndarray, see: np.ndarray, det: np.ndarray) -> np.ndarray:
    """``y`` minus its per-pixel weighted least-squares fit on ``P``, ``E`` (columns are
    pixels; ``det`` of the 2x2 normal equations, > 0 where used)."""
    spy = (w * P * y).sum(0)
    sey = (w * E * y).sum(0)
    d = np.where(det > 0, det, 1.0)
    c = (see * spy - spe * sey) / d
    b = (spp * sey - spe * spy) / d
    return np.asarray(y - c * P - b * E)


def threshold_light_exponent(obs: Observation, dark_dn: float,
                             ref_dn: float | np.ndarray, iterations: int = 1,
                             pixels: np.ndarray | None = None) -> float:
    """Exponent ``e`` of thresholds ``th ((I + dark) / ref)**(-e)`` that the events of
    ``obs`` ask for: the least-squares ``e`` of the per-pixel OffEI equations
    ``dG_e = c P + b E`` on the response ``G_e`` (:meth:`ThresholdLight.response`), ``c``,
    ``b`` per pixel and ``e`` shared.

    Gauss-Newton from ``e = 0``: linearised at ``e_k``, ``dG_e = dG_k + (e - e_k) dD_k``
    (``D = dG / de``; at 0, ``D = ln(x / ref)^2 / 2``), so ``e - e_k`` is minus the
    regression of the residual of ``dG_k`` on that of ``dD_k`` after each pixel's own ``P``,
    ``E`` fit (Frisch-Waugh), over the usable windows of the pixels the fit trusts. By
    default one step (the first-order estimate): in the gap loop on the test pans it reads
    0.8x the exponent at 0.2-0.25, the converged least squares 0.72x (pixels disagree on the
    exponent: frames quantised in the dark weigh on it), and a candidate is compared at its
    moment estimate; the bias correction by simulation sets the named value.
    ``ref_dn`` (scalar or per pixel, units of ``I + dark``) sets where ``G`` is ``ln x`` to
    first order: each pixel's own light keeps the curvature terms least. NaN when nothing
    varies. ``pixels`` (bool per pixel): only those enter."""
    f = _fit(obs)
    # only the pixels the fit trusts enter the sums: the arrays below are [windows, those]
    cols = np.flatnonzero(f["ok"] if pixels is None else f["ok"] & pixels)
    P, E = f["P"][:, cols], f["E"][:, cols]
    w = obs.usable[:, cols].astype(np.float64)
    spp, spe, see = (w * P * P).sum(0), (w * P * E).sum(0), (w * E * E).sum(0)
    det = spp * see - spe * spe
    use = det > 1e-9 * np.maximum(spp * see, 1e-30)
    w = w * use[None, :]
    x = np.maximum(obs.intensity[:, cols].astype(np.float64), 0.0) + dark_dn
    ref = np.broadcast_to(np.asarray(ref_dn, np.float64).reshape(1, -1),
                          (1, obs.intensity.shape[1]))[:, cols]
    u = np.log(np.maximum(x, 1e-3)) - np.log(ref)
    del x
    e = 0.0
    for _ in range(max(1, iterations)):
        if abs(e) < 1e-6:
            g, d = u, 0.5 * u * u
        else:
            eu = np.exp(e * u)
            g = (eu - 1.0) / e
            d = u * eu / e - (eu - 1.0) / (e * e)
        rg = _resid(g[1:] - g[:-1], P, E, w, spp, spe, see, det)
        rd = _resid(d[1:] - d[:-1], P, E, w, spp, spe, see, det)
        den = float((w * rd * rd).sum())
        if den <= 1e-12:
            return float("nan")
        e = float(np.clip(e - (w * rg * rd).sum() / den, -0.9, 1.5))
    return e


def pixel_references(obs: Observation, dark_dn: float) -> tuple[float, np.ndarray]:
    """The light ``x = I + dark`` at which intensity-blind per-pixel fits hold each pixel's
    threshold: per pixel, the geometric mean of ``x`` over its usable windows weighted by
    their events (the windows that dominate its OffEI fit); pixels without events get the
    overall one, which is returned first (rounded, the effect's ``ref_dn``)."""
    wgt = (obs.usable * (obs.on + obs.off)).astype(np.float64)
    x_mid = 0.5 * (obs.intensity[1:] + obs.intensity[:-1]).astype(np.float64) + dark_dn
    lx = np.log(np.maximum(x_mid, 1e-3))
    tot = float(wgt.sum())
    overall = float(np.exp((wgt * lx).sum() / tot)) if tot > 0 else ThresholdLight().ref_dn
    sw = wgt.sum(0)
    per = np.where(sw > 0, np.exp((wgt * lx).sum(0) / np.maximum(sw, 1e-12)), overall)
    return round(overall, 1), per


# the measured exponent must stand this many seed-to-seed standard deviations above the
# model's simulations'
TL_MIN_Z = 3.0


def fit_threshold_light(ctx: FitContext) -> FitResult:
    """``ThresholdLight`` with the measured exponent minus that of the model's simulations
    (:func:`threshold_light_exponent` at the model's dark level), when it stands
    :data:`TL_MIN_Z` of their spread above it. The simulations carry what the
    interpolation between frames and the other effects do to it, so the difference is the
    thresholds' own light dependence. The model's threshold maps are intensity-blind fits,
    each pixel's threshold at the light it saw: the effect's per-pixel references are that
    light (:func:`pixel_references`, a function of the frames, on the whole sensor), so
    the maps keep their meaning."""
    meas, sims, model = ctx.meas, ctx.sims, ctx.model
    dark = _dark_dn(model)
    ref, per_whole = pixel_references(ctx.whole, dark)
    per = per_whole.reshape(ctx.shape)
    per_fit = (per if ctx.rows is None else per[ctx.rows]).ravel()

    def relative(pixels: np.ndarray | None) -> tuple[float, float]:
        """The measured exponent less the simulations' mean, and its spread over them."""
        em = threshold_light_exponent(meas, dark, per_fit, pixels=pixels)
        es = np.array([threshold_light_exponent(s, dark, per_fit, pixels=pixels)
                       for s in sims])
        es = es[np.isfinite(es)]
        if not np.isfinite(em) or es.size == 0:
            return float("nan"), float("nan")
        sd = float(np.sqrt((es.var(ddof=1) * (1 + 1 / es.size) if es.size > 1 else 0.0)
                           + 0.01 ** 2))
        return em - float(es.mean()), sd

    e, sd = relative(None)
    if not np.isfinite(e):
        return NoEvidence("nothing varies enough in light to measure an exponent")
    if e < TL_MIN_EXPONENT or e < TL_MIN_Z * sd:
        return NoEvidence(f"the thresholds' light dependence is the model's (exponent "
                          f"{e:+.3f} against a seed-to-seed spread of {sd:.3f})")
    detail = {"z": e / sd}
    # each pixel's thresholds where its base fit put them: at the light it saw
    return Fitted(ThresholdLight(exponent=round(float(min(e, 1.0)), 4), ref_dn=ref,
                                 pixel_ref_dn=per), detail)


# ------------------------------------------------------------------------------ row_noise

ROW_MIN_EXCESS_HZ = 0.01  # coincident still events per pixel-second worth a parameter


def _coincident_rate(obs: Observation, axis: str) -> float:
    exposure = still_pixel_seconds(obs)
    if exposure <= 0:
        return 0.0
    return float((line_events(obs, axis)["n_near"] >= LINE_COINCIDENCE_MIN).sum() / exposure)


def burst_fraction(obs: Observation, axis: str) -> float:
    """Mean share of a line's still pixels that fire in one of its bursts: per burst (runs of
    coincident still events of one line, gaps <= :data:`LINE_COINCIDENCE_US`), its events
    over the still pixels of its line in its window; bursts in lines at least half still."""
    le = line_events(obs, axis)
    co = le["n_near"] >= LINE_COINCIDENCE_MIN
    if co.sum() < 3:
        return float("nan")
    key, line, win = le["key"][co], le["line"][co], le["win"][co]
    new = np.ones(key.size, bool)
    new[1:] = (np.diff(key) > LINE_COINCIDENCE_US) | (line[1:] != line[:-1])
    burst = np.cumsum(new) - 1
    size = np.bincount(burst).astype(np.float64)
    first = np.flatnonzero(new)
    h, w = obs.shape
    st = _static(obs).reshape(obs.n_windows, h, w)
    still_in_line = st.sum(2) if axis == "row" else st.sum(1)  # [n_w, n_lines]
    length = w if axis == "row" else h
    s = still_in_line[win[first], line[first]].astype(np.float64)
    ok = s >= 0.5 * length
    if not ok.any():
        return float("nan")
    return float(np.clip(size[ok].sum() / s[ok].sum(), 0.01, 1.0))


ROW_MIN_Z = 4.0  # the coincident still events' excess over the model, in standard deviations


def fit_row_noise(ctx: FitContext) -> FitResult:
    """``RowNoise`` on the axis whose coincident still-window events the model's simulations
    miss most: the excess rate of such events per still pixel-second is ``rate * fraction``
    (every pixel of a line joins its bursts with probability ``fraction``); the fraction is
    read off the bursts' sizes against their lines' still pixels, the rate is the excess
    over it. Detection misses bursts of fewer than three still pixels: the bias correction
    of the workflow takes care of the rate. The excess must stand :data:`ROW_MIN_Z`
    standard deviations (Poisson) above the model's count."""
    meas, sims = ctx.meas, ctx.sims
    best: tuple[float, str, float, float] | None = None
    for axis in ("row", "column"):
        r_m = _coincident_rate(meas, axis)
        r_s = float(np.mean([_coincident_rate(s, axis) for s in sims]))
        if best is None or r_m - r_s > best[0]:
            best = (r_m - r_s, axis, r_m, r_s)
    assert best is not None
    excess, axis, r_m, r_s = best
    exposure = still_pixel_seconds(meas)
    z = excess * exposure / np.sqrt((r_m + r_s / max(len(sims), 1)) * exposure + 1.0)
    if excess < ROW_MIN_EXCESS_HZ or z < ROW_MIN_Z:
        return NoEvidence(f"still events coincide along a {axis} as often as in the model "
                          f"({excess:+.3g} per pixel-second more, z = {z:+.1f})")
    frac = burst_fraction(meas, axis)
    detail: dict[str, object] = {"z": float(z)}
    if not np.isfinite(frac):
        # too few bursts in half-still lines to measure their size: the effect's default
        # share, its rate from the excess (the bias correction moves the rate)
        frac = float(RowNoise().fraction)
        detail["fraction"] = "default: too few bursts to measure their size"
    return Fitted(RowNoise(rate_hz=round(excess / frac, 4), fraction=round(frac, 4),
                           axis=axis), detail)


# ----------------------------------------------------------------------------------- leak

LEAK_EXPONENTS = np.arange(0.0, 1.51, 0.25)
LEAK_MIN_CHI2_DROP = 9.0  # a light dependence must explain this much more than a flat rate


def _still_net(meas: Observation, sims: list[Observation]
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Per still window of a pixel (the busiest 1 % of pixels left out: hot pixels): the
    measured minus simulated ``ON - OFF`` count, its Poisson variance (measured events plus
    the simulated mean's variance), the mean intensity (DN) and the window's length (s)."""
    st = _static(meas)
    if st.sum() < 50:
        return None
    cm = np.bincount(meas.pix, minlength=meas.n_pixels)
    keep = st & (cm <= np.quantile(cm, 0.99))[None, :]
    net_m = (meas.on - meas.off).astype(np.float64)
    net_s = np.mean([(s.on - s.off) for s in sims], axis=0)
    # Poisson: the measured events plus the simulated mean's (over the seeds)
    var = (meas.on + meas.off) + np.mean([(s.on + s.off) for s in sims], axis=0) / len(sims)
    i_mid = 0.5 * (meas.intensity[1:] + meas.intensity[:-1]).astype(np.float64)
    ws = np.broadcast_to(meas.window_s[:, None], st.shape)
    return (net_m - net_s)[keep], var[keep], i_mid[keep], ws[keep]


LEAK_MIN_Z = 4.0  # the still windows' net ON excess, in standard deviations (Poisson)


def fit_leak(ctx: FitContext) -> FitResult:
    """``Leak`` with its rate at ``ref_dn`` and its light exponent: the excess of ON over OFF
    events in still windows is ``rate (I / ref)**e`` per pixel-second (leak adds ON only).
    The summed net excess must stand :data:`LEAK_MIN_Z` standard deviations above the
    model's (an excess of both polarities alike, noise's, has none). Per exponent of
    :data:`LEAK_EXPONENTS`, the rate by weighted least squares (Poisson variances); the
    exponent with the least chi-square, kept over 0 only when it lowers it by
    :data:`LEAK_MIN_CHI2_DROP` (a flat leak is the default: the junction leakage of the
    reset switch, Nozaki & Delbruck 2017; its parasitic photocurrent adds a part growing with
    light, up to proportional, e = 1). At e = 0 the rate is the plain ratio of the summed
    excess to the still time."""
    parts = _still_net(ctx.meas, ctx.sims)
    if parts is None:
        return NoEvidence("fewer than 50 still windows of a pixel")
    ex, var, inten, ws = parts
    z = float(ex.sum() / np.sqrt(max(float(var.sum()), 1.0)))
    var = np.maximum(var, 1.0)  # the chi-square's weights below: a window's at least 1
    if z < LEAK_MIN_Z:
        return NoEvidence(f"still pixels make as many more ON than OFF events as the model "
                          f"(net excess z = {z:+.1f})")
    ref = Leak().ref_dn
    fits = []
    for e in LEAK_EXPONENTS:
        x = ws * (np.maximum(inten, 1e-3) / ref) ** e
        # weights 1 / ws (variance proportional to time) make e = 0 the ratio of sums
        r = float((ex * x / ws).sum() / max((x * x / ws).sum(), 1e-12))
        chi2 = float((((ex - r * x) ** 2) / var).sum())
        fits.append((chi2, float(e), r))
    flat = fits[0]
    best = min(fits, key=lambda f: f[0])
    chosen = best if best[0] < flat[0] - LEAK_MIN_CHI2_DROP else flat
    _, e, rate = chosen
    if rate <= 0:
        return NoEvidence("the fitted rate is not positive")
    return Fitted(Leak(rate_hz=round(rate, 4), light_exponent=e, ref_dn=ref), {"z": z})
