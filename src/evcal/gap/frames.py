"""The frame side of the model: which frames drive a simulation, and the fitters of the
APS-frame effects (``aps_fpn``, ``exposure``).

The simulations of the gap workflow are driven by the measured APS frames. Two properties of
real DAVIS frames make those frames differ from the intensity the DVS part of the pixels saw:

- **DSNU** (``aps_fpn``): each pixel's frame value carries its own constant dark offset
  ``o[y, x]``; the events saw the light without it. :func:`model_frames` subtracts the
  per-pixel estimate ``o_hat`` (the effect's ``offset_dn`` map). Drawing a fresh random
  pattern instead would add a second pattern rather than remove the real one.
- **Exposure** (``exposure``): a frame is the intensity averaged over its exposure, and its
  timestamp may mark the start (dv-processing), middle (libcaer) or end of it; the frame
  represents the intensity ``lag_us`` after its stamp. :func:`model_frames` moves the frame
  times by ``lag_us`` (the frames attached to a simulation, and with them the statistics'
  windows, keep the stamped times).

Both fitters are moment estimates against the current model's simulations (which show
neither effect): per pixel, the dark offset that best explains the pixel's events
(:func:`fit_aps_fpn`); for the recording, the lag of the frame times that best explains the
events (:func:`fit_exposure`).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numba
import numpy as np

from ..recording import Frames, Recording
from ..sim.effects import ApsFpn, Exposure
from .effects import FitContext, FitResult, Fitted, NoEvidence
from .pixelfit import fit_from_sums, offset_window_sums, residual_from_sums, window_sums
from .stats import Observation

if TYPE_CHECKING:
    from .model import Model

# dark offsets tried per pixel (DN): DSNU of CMOS APS is a few DN (its sigma); +-16 covers 4
# sigma of 4 DN without letting the pixel's darkest frame go below the offset
FPN_GRID_DN = np.arange(-16.0, 16.01, 1.0)
# activity bins over which the estimation noise of o_hat is pooled
FPN_NOISE_BINS = 6
# lags tried, as multiples of the larger of the exposure and a quarter of the frame interval
LAG_GRID = np.linspace(-1.5, 1.5, 25)


def model_frames(model: Model, frames: Frames) -> Frames:
    """The frames that drive a simulation of ``model``: ``frames`` less the model's per-pixel
    dark offsets (``aps_fpn`` with its ``offset_dn`` map; values floored at 0, float32), at
    times moved by the ``exposure`` lag (rounded to us). ``frames`` itself when the model has
    neither (or ``aps_fpn`` without a map: a drawn pattern cannot remove the real one).
    Deterministic: no random draw."""
    fpn = model.effects.get(ApsFpn.name)
    exp = model.effects.get(Exposure.name)
    has_map = isinstance(fpn, ApsFpn) and fpn.offset_dn is not None
    lag = int(round(float(exp.lag_us))) if isinstance(exp, Exposure) else 0
    if not has_map and lag == 0:
        return frames
    images = frames.images
    if has_map:
        assert isinstance(fpn, ApsFpn)
        o = fpn.offsets_dn(frames.shape).astype(np.float32)
        images = np.maximum(images.astype(np.float32) - o[None], np.float32(0.0))
    return Frames(t_us=frames.t_us + lag, images=images, exposure_us=frames.exposure_us)


def corrected_recording(model: Model, rec: Recording) -> Recording:
    """``rec`` with the frames of :func:`model_frames` (for refitting the base maps on the
    frames the events saw, as the workflow does for ``log_offset``)."""
    fr = model_frames(model, rec.frames)
    if fr is rec.frames:
        return rec
    return Recording(rec.sensor, rec.events, fr, dict(rec.metadata))


# ------------------------------------------------------------------------------ aps_fpn


def offset_residuals(observations: list[Observation], grid_dn: np.ndarray,
                     log_offset: float) -> list[np.ndarray]:
    """Per observation, per dark offset ``o`` of ``grid_dn`` and pixel: the unexplained
    fraction of the pixel's fit ``dL = c P + b E`` with ``L = log(F - o + log_offset)`` of
    the frames ``F`` (``[n_grid, n_pixels]``; inf where ``o`` exceeds the pixel's darkest
    frame, NaN where the pixel has no fit).

    A pixel's dark offset compresses (or stretches) its frames' log changes more in the dark
    than in the light, which a constant ``c`` cannot follow: the fraction is least at the
    offset the frames actually carry. It is scale-free (``SSR / TSS``), so shrinking all
    ``dL`` by a larger offset does not win by itself. Observations of the same frames (a
    measurement and its simulations) share the frames' log changes at each offset."""
    obs0 = observations[0]
    if any(o.intensity is not obs0.intensity or o.usable is not obs0.usable
           for o in observations[1:]):
        return [r for o in observations for r in offset_residuals([o], grid_dn, log_offset)]
    # a pixel without events in a usable window has no fit in any observation (NaN): only
    # the others are computed, the arrays below are [windows, those]
    n_pix = obs0.intensity.shape[1]
    fired = np.zeros(n_pix, bool)
    for o in observations:
        fired |= ((o.on + o.off) * obs0.usable).any(0)
    cols = np.flatnonzero(fired)
    F = obs0.intensity[:, cols].astype(np.float64)
    w = obs0.usable[:, cols].astype(np.float64)
    f_min = F.min(0) if cols.size else np.zeros(0)
    out = [np.full((grid_dn.size, n_pix), np.nan) for _ in observations]
    all_sums = offset_window_sums(F, w, [(o.on - o.off)[:, cols] for o in observations],
                                  [(o.on + o.off)[:, cols] for o in observations], grid_dn,
                                  log_offset)
    # the darkest frame must stay above the offset (F >= o + 0.5 DN)
    inside = f_min[None, :] - grid_dn[:, None] >= 0.5
    for j, sums in enumerate(all_sums):  # [n_grid, 7, those]: fitted as one batch
        sums = np.moveaxis(sums, 1, 0)
        c, b, ok = fit_from_sums(*sums[:6])
        ssr = residual_from_sums(sums, np.nan_to_num(c), np.nan_to_num(b))
        tss = sums[6]
        frac = np.where(ok & (tss > 0), ssr / np.maximum(tss, 1e-30), np.nan)
        out[j][:, cols] = np.where(inside, frac, np.inf)
    return out


def offset_estimates(observations: list[Observation], log_offset: float,
                     grid_dn: np.ndarray = FPN_GRID_DN) -> list[np.ndarray]:
    """Per observation and pixel, the dark offset (DN) of the least
    :func:`offset_residuals` on the grid, refined by a parabola through its neighbours
    (NaN where the pixel has no fit). Kept in each ``obs.extra`` (the workflow refits on
    the same simulations many times); those not yet known are computed together."""
    key = f"aps_fpn_offsets/{float(log_offset)!r}/{grid_dn.tobytes().hex()}"
    todo = [o for o in observations if not isinstance(o.extra.get(key), np.ndarray)]
    if todo:
        for o, r in zip(todo, offset_residuals(todo, grid_dn, log_offset), strict=True):
            o.extra[key] = _grid_argmin(r, grid_dn)
    return [o.extra[key] for o in observations]


def _grid_argmin(r: np.ndarray, grid_dn: np.ndarray) -> np.ndarray:
    """Per pixel (column of ``r``), the grid value of the least ``r``, refined by a
    parabola through its neighbours; NaN where no value is finite."""
    valid = np.isfinite(r).any(0)
    rr = np.where(np.isfinite(r), r, np.inf)
    i = np.argmin(rr, axis=0)
    n = grid_dn.size
    cols = np.arange(r.shape[1])
    im, ip = np.clip(i - 1, 0, n - 1), np.clip(i + 1, 0, n - 1)
    y0, y1, y2 = rr[im, cols], rr[i, cols], rr[ip, cols]
    inner = (i > 0) & (i < n - 1) & np.isfinite(y0) & np.isfinite(y2)
    with np.errstate(invalid="ignore", divide="ignore"):
        den = y0 - 2 * y1 + y2
        step = np.where(inner & (den > 0), 0.5 * (y0 - y2) / den, 0.0)
    step = np.clip(np.nan_to_num(step), -0.5, 0.5)
    d = grid_dn[1] - grid_dn[0]
    est = grid_dn[i] + step * d
    out: np.ndarray = np.where(valid, est, np.nan)
    return out


# the spread of the offsets over the pixels, less the estimation noise, must stand this many
# of its own sampling errors above 0
FPN_MIN_Z = 4.0


def fit_aps_fpn(ctx: FitContext) -> FitResult:
    """DSNU of the frames: per pixel, the dark offset that best explains its events
    (:func:`offset_estimates`) on the measurement less its mean over the simulations (which
    have none: that takes out what the estimator reads into a pixel's frames by itself), the
    spread of that over pixels less the estimation noise (the variance of the estimate
    between simulations, pooled over pixels of similar activity) is ``sigma_dn^2``.

    The map removed from the frames is each pixel's difference shrunk towards 0 by its noise,
    ``s^2 / (s^2 + v)`` (as the base maps are shrunk: estimation noise must not be put into
    the model as a pattern), with its mean removed: a common dark level of the frames is the
    ``log_offset`` effect's business. No evidence when the spread is within
    :data:`FPN_MIN_Z` of its sampling error of the noise. On the rows the fit did not see
    (``ctx.rows``), the map is drawn from the fitted spread.

    Refitted on simulations made with the map, the estimate comes out about 10-15 % above
    the ``sigma_dn`` they were made with (the interpolated frames add a misfit of their
    own): the workflow's bias correction scales the map down accordingly
    (:meth:`~evcal.sim.effects.ApsFpn.with_params` scales it with ``sigma_dn``)."""
    meas, sims, model = ctx.meas, ctx.sims, ctx.model
    if len(sims) < 2:
        return NoEvidence("the estimation noise needs two simulations of the model")
    lo = float(model.log_offset)
    om, *est = offset_estimates([meas, *sims], lo)
    os_ = np.stack(est)
    ok = np.isfinite(om) & np.isfinite(os_).all(0)
    if ok.sum() < 50:
        return NoEvidence(f"{int(ok.sum())} pixels have an offset estimate (50 needed)")
    k_sims = os_.shape[0]
    d = om - os_.mean(0)
    v_pix = os_.var(0, ddof=1)
    # pooled per activity bin: K seeds give a poor variance for one pixel
    count = (meas.on + meas.off).sum(0).astype(np.float64)
    edges = np.unique(np.quantile(count[ok], np.linspace(0, 1, FPN_NOISE_BINS + 1)))
    edges[0], edges[-1] = -np.inf, np.inf
    bins = np.clip(np.searchsorted(edges, count, side="right") - 1, 0, edges.size - 2)
    v_bin = np.array([np.mean(v_pix[ok & (bins == j)]) if (ok & (bins == j)).any() else np.nan
                      for j in range(edges.size - 1)])
    v_bin = np.where(np.isfinite(v_bin), v_bin, float(np.mean(v_pix[ok])))
    noise = v_bin[bins] * (1.0 + 1.0 / k_sims)  # of d: the measured and the mean simulated
    dc = d - float(np.mean(d[ok]))
    s2 = float(np.mean(dc[ok] ** 2) - np.mean(noise[ok]))
    # a spread the noise could make: the variance's own sampling error is about
    # sqrt(2 / n) of it
    limit = FPN_MIN_Z * np.sqrt(2.0 / ok.sum()) * float(np.mean(dc[ok] ** 2))
    if s2 <= limit:
        return NoEvidence(f"the pixels' offsets spread no more than their estimation noise "
                          f"makes ({np.sqrt(max(s2, 0.0)):.2g} DN beyond it, "
                          f"{np.sqrt(limit):.2g} DN needed)")
    k = s2 / (s2 + noise)
    o_hat = np.where(ok, k * dc, 0.0)
    o_hat = o_hat - float(np.mean(o_hat[ok]))
    sigma = float(np.sqrt(s2))
    return Fitted(ApsFpn(sigma_dn=round(sigma, 3), mean_dn=0.0,
                         offset_dn=ctx.whole_map(o_hat, float(np.std(o_hat[ok])))),
                  {"pixels": int(ok.sum())})


# ------------------------------------------------------------------------------ exposure


def lag_residuals(obs: Observation, lags_us: np.ndarray,
                  pixels: np.ndarray | None = None) -> np.ndarray:
    """Per lag: the unexplained fraction of the per-pixel fit ``dL = c P + b E`` when the
    events are counted in windows between frame times + lag (``dL`` the frames' log change,
    at the nominal offset, as the statistics use), over all pixels or those of the bool mask
    ``pixels``. Only windows that every lag keeps inside the recording's frames are used, so
    each lag is scored on the same equations."""
    ssr, tss = _lag_pixel_sums(obs, lags_us)
    if pixels is not None:
        ssr, tss = ssr[:, pixels], tss[:, pixels]
    den = tss.sum(1)
    out: np.ndarray = np.where(den > 0, ssr.sum(1) / np.maximum(den, 1e-30), np.nan)
    return out


@numba.njit(cache=True, nogil=True)
def _count_windows(t_us: np.ndarray, pix: np.ndarray, p: np.ndarray, ft: np.ndarray,
                   P: np.ndarray, E: np.ndarray) -> None:  # pragma: no cover - compiled
    """``P`` (ON - OFF) and ``E`` (ON + OFF) per window between the times ``ft`` and pixel
    of the events (those outside the windows are left out), in place. A walk along the
    windows: linear in the events when they are in time order."""
    P[:] = 0
    E[:] = 0
    n_w = ft.size - 1
    k = -1
    t_prev = t_us[0] if t_us.size else 0
    for j in range(t_us.size):
        t = t_us[j]
        if t < t_prev:  # out of time order (not expected): walk again from the start
            k = -1
        t_prev = t
        while k + 1 <= n_w and ft[k + 1] <= t:
            k += 1
        if k < 0 or k >= n_w:
            continue
        E[k, pix[j]] += 1
        P[k, pix[j]] += 1 if p[j] > 0 else -1


@numba.njit(cache=True, nogil=True)
def _lag_moves(t_us: np.ndarray, ft: np.ndarray, lags: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """The windows events leave as the frame times move from ``ft + lags[0]`` through the
    increasing integer ``lags``: an event at ``t`` is in window ``j`` while
    ``t - ft[j + 1] < lag <= t - ft[j]``, so it leaves ``j`` (for ``j - 1``) at the first lag
    above ``t - ft[j]``. Returns ``(event, window left, start)``: the moves of lag ``i`` are
    ``start[i]:start[i + 1]`` (counting-sorted by lag); an event may move more than once."""
    n_l = lags.size
    n_w = ft.size - 1
    lo, hi = lags[0], lags[n_l - 1]
    count = np.zeros(n_l + 1, np.int64)
    # pass 1 counts the moves per lag, pass 2 places them
    for rep in range(2):
        if rep == 1:
            start = np.zeros(n_l + 1, np.int64)
            for i in range(n_l):
                start[i + 1] = start[i] + count[i]
            fill = start[:n_l].copy()
            ev = np.empty(start[n_l], np.int64)
            win = np.empty(start[n_l], np.int32)
        k = 0  # the first frame time above t - lo, walked along
        t_prev = t_us[0] if t_us.size else 0
        for e in range(t_us.size):
            t = t_us[e]
            if t < t_prev:  # out of time order (not expected): walk again from the start
                k = 0
            t_prev = t
            while k < n_w + 1 and ft[k] <= t - lo:
                k += 1
            j = k - 1  # -1: before the first frame; n_w: after the last
            while j >= 0 and t - ft[j] < hi:
                d = t - ft[j]  # it leaves window j at the first lag above d
                i = np.searchsorted(lags, d, side="right")
                if i < n_l and j <= n_w:
                    if rep == 0:
                        count[i] += 1
                    else:
                        ev[fill[i]] = e
                        win[fill[i]] = j
                        fill[i] += 1
                j -= 1
        if rep == 1:
            return ev, win, start
    return np.empty(0, np.int64), np.empty(0, np.int32), count  # not reached


@numba.njit(cache=True, nogil=True)
def _apply_moves(pix: np.ndarray, p: np.ndarray, ev: np.ndarray, win: np.ndarray, a: int,
                 b: int, n_w: int, P: np.ndarray, E: np.ndarray
                 ) -> None:  # pragma: no cover - compiled
    """Moves ``a:b`` of :func:`_lag_moves` applied to the counts (window ``j`` to ``j - 1``;
    windows outside ``0..n_w - 1`` hold nothing)."""
    for m in range(a, b):
        e = ev[m]
        j = win[m]
        q = pix[e]
        s = 1 if p[e] > 0 else -1
        if 0 <= j < n_w:
            E[j, q] -= 1
            P[j, q] -= s
        if 0 <= j - 1 < n_w:
            E[j - 1, q] += 1
            P[j - 1, q] += s


def _lag_windows(obs: Observation, lags_us: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The frames' log change per window and the weight of each (window, pixel): usable, and
    inside the recording for every lag (each lag is scored on the same equations)."""
    ft = obs.frame_t_us.astype(np.int64)
    span = float(np.max(np.abs(lags_us))) if lags_us.size else 0.0
    inside = (ft[:-1] - span >= ft[0]) & (ft[1:] + span <= ft[-1])
    return np.diff(obs.log_i, axis=0), (obs.usable & inside[:, None]).astype(np.float64)


def _counts_by_lag(obs: Observation, lags_us: np.ndarray
                   ) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """``(i, P, E)`` for each lag ``lags_us[i]`` (in increasing order of lag): the events'
    ``ON - OFF`` and ``ON + OFF`` per window between the frame times moved by the lag and
    pixel. The counts of the first lag, then only the events that change window at each
    next one (a sweep of the lags costs about one pass over the events, not one per lag);
    the arrays are reused from one lag to the next."""
    ft = obs.frame_t_us.astype(np.int64)
    n_w, npix = obs.on.shape
    P = np.empty((n_w, npix), np.int32)
    E = np.empty((n_w, npix), np.int32)
    lags = np.rint(np.asarray(lags_us, np.float64)).astype(np.int64)
    order = np.argsort(lags, kind="stable")
    lags_sorted = lags[order]
    _count_windows(obs.t_us, obs.pix, obs.p, ft + lags_sorted[0], P, E)
    mv_ev, mv_win, start = _lag_moves(obs.t_us, ft, lags_sorted)
    for n, i in enumerate(order):
        if n > 0:
            _apply_moves(obs.pix, obs.p, mv_ev, mv_win, int(start[n]), int(start[n + 1]), n_w,
                         P, E)
        yield int(i), P, E


def _lag_pixel_sums(obs: Observation, lags_us: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per lag and pixel: the squared residual and the squared change summed over the
    pixel's windows (0 where its fit fails). A pixel's fit does not depend on the others', so
    any subset of pixels is scored from these sums. Kept in ``obs.extra``."""
    ckey = f"exposure_lag_sums/{lags_us.tobytes().hex()}"
    cached = obs.extra.get(ckey)
    if isinstance(cached, tuple):
        return cached
    dL, w = _lag_windows(obs, lags_us)
    npix = obs.n_pixels
    ssr = np.zeros((lags_us.size, npix))
    tss = np.zeros((lags_us.size, npix))
    for i, P, E in _counts_by_lag(obs, lags_us):
        sums = window_sums(P, E, dL, w)
        c, b, ok = fit_from_sums(*sums[:6])
        ssr[i] = np.where(ok, residual_from_sums(sums, np.nan_to_num(c), np.nan_to_num(b)),
                          0.0)
        tss[i] = np.where(ok, sums[6], 0.0)
    obs.extra[ckey] = (ssr, tss)
    return ssr, tss


def _at_grid_end(r: np.ndarray) -> bool:
    """Whether the least of the residuals ``r`` over the lag grid is at either end of it."""
    i = int(np.nanargmin(r))
    return i == 0 or i == r.size - 1


def _basin_minimum(r: np.ndarray, start: int) -> int:
    """The index of the local minimum of ``r`` reached by walking downhill from ``start``:
    the minimum of the basin the whole recording's lag lies in. A third of the cells may
    have a lower residual far off on the grid (a periodic scene matches itself a period
    later), which is not the delay the whole recording shows."""
    i = int(np.clip(start, 0, r.size - 1))
    while True:
        left = r[i - 1] if i > 0 else np.inf
        right = r[i + 1] if i < r.size - 1 else np.inf
        if not (left < r[i] or right < r[i]):
            return i
        i = i - 1 if left <= right else i + 1


def _lag_minimum(lags: np.ndarray, r: np.ndarray, i: int | None = None) -> float:
    """The lag of the least residual (of the one at index ``i`` when given), refined by a
    parabola through its neighbours."""
    if i is None:
        i = int(np.nanargmin(r))
    lag = float(lags[i])
    if 0 < i < lags.size - 1:
        y0, y1, y2 = r[i - 1], r[i], r[i + 1]
        den = y0 - 2 * y1 + y2
        if den > 0:
            lag += float(np.clip(0.5 * (y0 - y2) / den, -0.5, 0.5)) * float(lags[1] - lags[0])
    return lag


def _exposure_us(rec: Recording) -> float:
    """The recording's exposure time (median of ``Frames.exposure_us``; 0 without frames)."""
    return float(np.median(rec.frames.exposure_us)) if len(rec.frames) else 0.0


def _sim_lags(sims: list[Observation], lags: np.ndarray) -> list[float]:
    """Each simulation's own lag (the minimum of its :func:`lag_residuals` on ``lags``)."""
    return [_lag_minimum(lags, r) for r in (lag_residuals(s, lags) for s in sims)
            if np.isfinite(r).any()]


def event_lag(meas: Observation, sims: list[Observation], rec: Recording, reach: float = 1.0
              ) -> tuple[float, np.ndarray] | None:
    """How much later than the frames' stamps the measured events follow the frames'
    changes, less the same on the simulations (us; :func:`lag_residuals` on a grid of
    +-1.5 times the larger of the exposure and a quarter of the frame interval), and that
    grid. ``inf`` when the measurement's least residual lies at the grid's late end (a delay
    the grid does not reach); ``None`` when it lies at the early end or the lag is within
    one grid step. ``reach`` widens the grid (a slow photoreceptor in the dark delays its
    events beyond any frame timing)."""
    if not sims:
        return None
    ft = meas.frame_t_us
    interval = float(np.median(np.diff(ft)))
    exp_us = _exposure_us(rec)
    # a lag of a quarter of the interval and more is seen: a DAVIS's events and its
    # frames' stamps may disagree by several ms, far beyond a short exposure
    scale = max(exp_us, 0.25 * interval)
    lags = LAG_GRID * scale * float(reach)
    rm = lag_residuals(meas, lags)
    if not np.isfinite(rm).any():
        return None
    if _at_grid_end(rm):
        # later than the grid reaches (a slow photoreceptor's delay in the dark): inf; earlier
        # than it reaches, nothing a frame or a photoreceptor does
        return (float(np.inf), lags) if int(np.nanargmin(rm)) == rm.size - 1 else None
    lm = _lag_minimum(lags, rm)
    ls = _sim_lags(sims, lags)
    if not ls:
        return None
    lag = lm - float(np.mean(ls))
    if abs(lag) < float(lags[1] - lags[0]):
        return None
    return lag, lags


# the events' lag behind the frames must exceed this many times its noise to be a frame's
# timing or a photoreceptor's delay (the same test for both: the two are told apart by the
# light, and by their simulations, not by how much evidence each is asked for)
LAG_MIN_NOISE = 1.0


def lag_noise_us(sims: list[Observation], lags: np.ndarray) -> float:
    """The noise of :func:`event_lag`'s difference: the larger of the grid's step and the
    spread of the simulations' own lags (the measurement's as noisy as one of them, less
    their mean of ``n``: ``sd sqrt(1 + 1/n)``)."""
    step = float(lags[1] - lags[0])
    ls = _sim_lags(sims, lags)
    if len(ls) < 2:
        return step
    return max(step, float(np.std(ls, ddof=1)) * float(np.sqrt(1 + 1 / len(ls))))


def fit_exposure(ctx: FitContext) -> FitResult:
    """Where the frames' exposure lies: the lag of the frame times at which the measured
    events best match the frames' changes (:func:`lag_residuals`, a grid of +-1.5 times the
    larger of the exposure and a quarter of the frame interval), less the same on the
    simulations (driven by the frames at their stamps, they show what the interpolation
    alone puts there). The exposure time is the recording's (median of
    ``Frames.exposure_us``). ``None`` when the lag is within its noise
    (:func:`lag_noise_us`, the test a photoreceptor's delay passes too), when the
    measurement's least residual lies at an end of the grid (a minimum the grid does not
    bracket is no estimate: a delay longer than a frame's timing is taken to explain, as a
    slow photoreceptor's in the dark), or when it differs between dark and bright pixels
    (:class:`LagByLight`)."""
    meas, sims, rec = ctx.meas, ctx.sims, ctx.rec
    found = event_lag(meas, sims, rec)
    if found is None:
        return NoEvidence("the events follow the frames' changes as the model's do (no lag "
                          "beyond one step of the grid, or none the grid brackets)")
    lag, lags = found
    if not np.isfinite(lag):
        return NoEvidence(f"the events lag the frames' changes by more than "
                          f"{lags[-1] / 1000:.3g} ms: later than any frame timing")
    noise_us = lag_noise_us(sims, lags)
    if abs(lag) <= LAG_MIN_NOISE * noise_us:
        return NoEvidence(f"the events lag the frames' changes by {lag:.0f} us beyond the "
                          f"model's, within {LAG_MIN_NOISE:g} times its noise "
                          f"({noise_us:.0f} us)")
    # a frame's timing moves every pixel's events alike; a slow photoreceptor (bandwidth)
    # delays the events of dark moments most: the lag must be the same at every light
    by_light = _lag_by_light(meas, sims, lags)
    detail: dict[str, object] = {}
    if by_light is not None:
        detail = {"lag_by_light_us": by_light.lags_us, "noise_us": by_light.noise_us}
        if not by_light.alike():
            return NoEvidence("the events' lag differs with the light ("
                              + ", ".join(f"{v:.0f}" for v in by_light.lags_us)
                              + f" us from dark to bright, noise {by_light.noise_us:.0f} us): "
                              "a frame's timing moves every pixel alike")
    return Fitted(Exposure(lag_us=round(lag, 1), exposure_us=_exposure_us(rec)), detail)


LIGHT_BINS = 3  # light bins of the lag by light: the darkest, middle and brightest third


def _lag_light_sums(obs: Observation, lags_us: np.ndarray, edges: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Per lag and light bin (``edges`` of the window's mean frame value, DN, at the
    pixel): the squared residual of the per-pixel fit (each pixel's ``c``, ``b`` fitted at
    that lag over all its windows) and the squared change, summed over the cells (window,
    pixel) of the bin. The light is the window's, the light at the time of the change: a
    moving scene brings every pixel dark and bright windows alike, so a pixel's mean light
    would not tell them apart. Kept in ``obs.extra``."""
    ckey = f"lag_light_sums/{lags_us.tobytes().hex()}/{edges.tobytes().hex()}"
    cached = obs.extra.get(ckey)
    if isinstance(cached, tuple):
        return cached
    dL, w = _lag_windows(obs, lags_us)
    i_mid = 0.5 * (obs.intensity[1:] + obs.intensity[:-1])
    nb = edges.size - 1
    cell_bin = np.clip(np.searchsorted(edges, i_mid, side="right") - 1, 0, nb - 1)
    cell_bin = np.where(w > 0, cell_bin, nb)  # unused cells to a spare bin
    tss = np.bincount(cell_bin.ravel(), weights=(w * dL * dL).ravel(), minlength=nb + 1)[:nb]
    ssr = np.zeros((lags_us.size, nb))
    for i, P, E in _counts_by_lag(obs, lags_us):
        sums = window_sums(P, E, dL, w)
        c, b, ok = fit_from_sums(*sums[:6])
        c = np.where(ok, c, 0.0)
        b = np.where(ok, b, 0.0)
        r = dL - c[None, :] * P - b[None, :] * E
        use = np.where(ok[None, :], cell_bin, nb)
        ssr[i] = np.bincount(use.ravel(), weights=(w * r * r).ravel(), minlength=nb + 1)[:nb]
    tss_all = np.broadcast_to(tss, ssr.shape).copy()
    obs.extra[ckey] = (ssr, tss_all)
    return ssr, tss_all


@dataclass(frozen=True)
class LagByLight:
    """The events' lag behind the frames (measured less simulated, us) in each third of the
    cells by their light, darkest first, each the minimum in the basin of the whole
    recording's (``inf``: the basin reaches the grid's late end, a delay the grid does not
    bracket; ``-inf``: its early end), and the noise of the difference between the darkest
    and the brightest third: the larger of the grid's step and the seed-to-seed spread of
    that difference in the simulations."""

    lags_us: list[float]
    noise_us: float

    def earlier_in_the_dark(self, k: float = 2.0) -> bool:
        """The darkest third's events earlier than the brightest third's by ``k`` noise: what
        no low-pass does (it delays the dark ones more). A third beyond an end of the grid
        is later (``inf``) or earlier (``-inf``) than any third within it; both beyond the
        same end tell no order. Alike thirds do not refuse a low-pass: the lag of a third of
        the cells, by the light of a window rather than of each moment, mixes the dark and
        the bright (a moving scene), and the simulations of the low-pass and of a frame's
        timing, compared on every statistic, tell them apart where this cannot."""
        v = np.asarray(self.lags_us)
        dark, bright = float(v[0]), float(v[-1])
        if np.isfinite(dark) and np.isfinite(bright):
            return bool(bright - dark > k * self.noise_us)
        return bool(dark < bright)

    def alike(self, k: float = 2.0) -> bool:
        """The thirds the grid reaches (at least two) within ``k`` noise of each other."""
        v = np.asarray(self.lags_us)
        fin = v[np.isfinite(v)]
        return fin.size >= 2 and bool(fin.max() - fin.min() <= k * self.noise_us)


def _lag_by_light(meas: Observation, sims: list[Observation], lags: np.ndarray
                  ) -> LagByLight | None:
    """The lag (measured less simulated) in each third of the measurement's cells (window,
    pixel) by their light (the window's mean frame value at the pixel), darkest first, and
    its noise (:class:`LagByLight`); ``None`` when a third has no minimum."""
    i_mid = 0.5 * (meas.intensity[1:] + meas.intensity[:-1])
    used = i_mid[meas.usable]
    if used.size < 100 or not sims:
        return None
    edges = np.quantile(used, np.linspace(0.0, 1.0, LIGHT_BINS + 1))
    edges[0], edges[-1] = -np.inf, np.inf
    if np.unique(edges).size < edges.size:
        return None

    def unexplained(obs: Observation) -> np.ndarray:
        ssr, tss = _lag_light_sums(obs, lags, edges)
        out: np.ndarray = np.where(tss > 0, ssr / np.maximum(tss, 1e-30), np.nan)
        return out

    rm_all = unexplained(meas)
    rs_all = [unexplained(s) for s in sims]
    if not all(np.isfinite(r).all() for r in [rm_all, *rs_all]):
        return None

    # each third's minimum is sought in the basin of the observation's own least residual
    # (none on a recording too sparse for any lag to explain part of a window's change)
    whole = [lag_residuals(o, lags) for o in [meas, *sims]]
    if not all(np.isfinite(r).any() for r in whole):
        return None

    def basins(whole_r: np.ndarray, r: np.ndarray) -> list[int]:
        start = int(np.nanargmin(whole_r))
        return [_basin_minimum(r[:, j], start) for j in range(LIGHT_BINS)]

    sim_lags = np.array([[_lag_minimum(lags, r[:, j], i) for j, i in enumerate(basins(w, r))]
                         for w, r in zip(whole[1:], rs_all, strict=True)])
    out = []
    for j, i in enumerate(basins(whole[0], rm_all)):
        if i == 0 or i == lags.size - 1:
            # beyond the grid's reach: later (inf) or earlier (-inf) than it goes
            out.append(float(np.inf) if i else -float(np.inf))
            continue
        out.append(_lag_minimum(lags, rm_all[:, j], i) - float(sim_lags[:, j].mean()))
    diff = sim_lags[:, 0] - sim_lags[:, -1]
    spread = float(diff.std(ddof=1)) * np.sqrt(1 + 1 / diff.size) if diff.size > 1 else 0.0
    return LagByLight(out, max(float(lags[1] - lags[0]), spread))
