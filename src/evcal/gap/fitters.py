"""Moment estimators of the candidate effects ``refractory``, ``shot_noise``,
``hot_pixels``, ``threshold_noise``, ``bandwidth``, ``log_offset``, ``timestamp_jitter``
and ``timestamp_quantisation`` (fitters of :data:`evcal.gap.model.FITTERS`; those of the
APS frames are in :mod:`evcal.gap.frames`, of ``leak``, ``threshold_light`` and
``row_noise`` in :mod:`evcal.gap.fitters_events`).

Each takes the measured observation, the current model's simulations, the model and the
recording, and returns the effect with estimated parameters, or ``None`` when the data show
none of it (e.g. no excess of events where the effect would add them). Most compare a
statistic of the measurement with the same statistic of the simulations, so what the frames
and the interpolation do to it alike in both cancels.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from ..accumulate import order_by_key
from ..errors import CalibrationError
from ..offline import OffEIConfig, estimate_log_offset
from ..sim.effects import (
    Bandwidth,
    HotPixels,
    LogOffset,
    Refractory,
    ShotNoise,
    ThresholdNoise,
    TimestampJitter,
    TimestampQuantisation,
)
from ..stream import event_windows
from . import frames as _frames
from .compare import discrepancy
from .effects import FitContext, FitResult, Fitted, NoEvidence
from .fitters_events import _dark_dn
from .pixelfit import (
    MIN_FIT_EVENTS,
    fit_from_sums,
    lowpass_log_changes,
    residual_from_sums,
    window_sums,
)
from .stats import (
    NOMINAL_LOG_OFFSET_DN,
    Observation,
    StatValue,
    _changing_windows,
    _fit,
    _iei,
    _static,
    every_nth_row,
    timestamp_quantum,
)

if TYPE_CHECKING:
    from .model import Model


def _hot_excess(meas: Observation, sims: list[Observation]) -> Any:
    n = meas.n_pixels
    dur = (meas.frame_t_us[-1] - meas.frame_t_us[0]) * 1e-6
    cm = np.bincount(meas.pix, minlength=n).astype(np.float64)
    cs = np.mean([np.bincount(s.pix, minlength=n) for s in sims], axis=0)
    ex = cm - cs
    z = ex / np.sqrt(cs + 1.0 + (0.3 * cs) ** 2)
    return cm, cs, ex, z, dur


def late_slot_intervals(obs: Observation, q: TimestampQuantisation) -> np.ndarray:
    """Under the ``spread`` timestamp scheme ``q``: for each pixel's first event of a step
    that lies at a later slot than the step's first, other than its last, the time (us)
    since the pixel's previous event.

    A frame-driven simulator stamps a pixel's events at the first slots of its step
    (:func:`evcal.sim.effects.quantise_events`), so such an event was held back at the
    earlier slots: by a dead time that ended between them. These intervals therefore all
    lie just above the dead time, however sparse the pairs of events are at short
    intervals otherwise. The last slot is left out: a simulator also stamps its noise
    events there (v2e's shot noise), which no dead time holds back. A step's slot spacing
    is the offset of its earliest event from the step's start. Kept in ``obs.extra`` (the
    measurement's is asked for every round)."""
    t = np.asarray(obs.t_us, np.int64)
    if t.size < 2 or q.scheme != "spread":
        return np.zeros(0)
    key = f"late_slot_intervals/{float(q.step_us)!r}/{float(q.phase_us)!r}"
    cached = obs.extra.get(key)
    if isinstance(cached, np.ndarray):
        return cached
    step = float(q.step_us)
    t0 = int(obs.frame_t_us[0])
    origin = t0 + float(q.phase_us) % step - step  # as quantise_events
    k = np.maximum(np.ceil((t - origin) / step).astype(np.int64) - 1, 0)
    off = t - (origin + k * step)  # in (0, step]
    ks, first = np.unique(k, return_inverse=True)
    min_off = np.full(ks.size, np.inf)
    np.minimum.at(min_off, first, off)
    n_slots = np.maximum(1, np.rint(step / np.maximum(min_off, 1.0))).astype(np.int64)[first]
    slot = np.rint(off * n_slots / step).astype(np.int64) - 1
    order = order_by_key(obs.pix, obs.n_pixels)  # stable: each pixel's events in time order
    tp, pp, kp = t[order], np.asarray(obs.pix)[order], k[order]
    sp, np_ = slot[order], n_slots[order]
    same = np.r_[False, pp[1:] == pp[:-1]]
    first_in_step = same & np.r_[False, kp[1:] != kp[:-1]]
    late = first_in_step & (sp > 0) & (sp < np_ - 1)
    out: np.ndarray = (tp - np.r_[tp[:1], tp[:-1]])[late].astype(np.float64)
    obs.extra[key] = out
    return out


# a dead time is read off the slots when the measurement holds at least this many held-back
# events, and this many times the simulations' (which have none without a dead time)
SLOT_MIN_EVENTS = 50
SLOT_EXCESS = 3.0


def _slot_dead_time(meas: Observation, sims: list[Observation], model: Model
                    ) -> float | None:
    """The dead time read off the slots of a ``spread`` timestamp scheme in the current
    model (:func:`late_slot_intervals`: the 2nd percentile of the held-back events'
    intervals), or ``None`` when there is no such scheme or too few held-back events."""
    q = model.effects.get(TimestampQuantisation.name)
    if not isinstance(q, TimestampQuantisation) or q.scheme != "spread":
        return None
    u_m = late_slot_intervals(meas, q)
    n_s = float(np.mean([late_slot_intervals(s, q).size for s in sims])) if sims else 0.0
    if u_m.size < SLOT_MIN_EVENTS or u_m.size < SLOT_EXCESS * n_s + SLOT_MIN_EVENTS:
        return None
    return float(np.percentile(u_m, 2.0))


# the longest dead time taken for a pixel's refractory period (DVS pixels: 0.1-3 ms at usual
# biases); fewer intervals up to longer ones are another effect's (a low-pass, for one)
REFRACTORY_MAX_US = 5000.0


def fit_refractory(ctx: FitContext) -> FitResult:
    """A dead time: read off the slots of a frame-driven simulator's stamps when the model
    has that scheme; else the shortest same-pixel interval of the measurement (the 1e-4
    quantile) when the simulations have pairs below it (at least 0.2 % of theirs), or the
    pairs missing at short intervals (:func:`_refractory_deficit`). ``delay`` when the
    measurement piles intervals just above the period, else ``drop``."""
    meas, sims, model = ctx.meas, ctx.sims, ctx.model
    slot_p = _slot_dead_time(meas, sims, model)
    if slot_p is not None:
        # the stamps say it directly; blocked crossings stay pending in such a simulator
        # (the gap workflow also evaluates the other mode, see evcal.gap.model.variants)
        return Fitted(Refractory(period_us=round(slot_p, 1), mode="delay"),
                      {"source": "held-back slots"})
    cm, cs, ex, z, dur = _hot_excess(meas, sims)
    keep = cm <= np.quantile(cm, 0.99)
    iei_m, _, pix_pairs = _iei(meas)
    iei_m = iei_m[keep[pix_pairs]]
    iei_s = np.concatenate([_iei(s)[0] for s in sims])
    if iei_m.size < 50 or iei_s.size < 50:
        return NoEvidence(f"{iei_m.size} same-pixel intervals measured (50 needed)")
    k = max(5, int(1e-4 * iei_m.size))
    p = float(np.partition(iei_m, k)[k])
    below = float(np.mean(iei_s < p))
    if below < 2e-3 or p < 2:
        # nothing is missing below the shortest intervals: unless noise events (which a
        # sensor's dead time does not hold back the same way, and which the model may
        # already make) fill them, while the pairs of signal events are missing
        p_def = _refractory_deficit(iei_m, [_iei(s)[0][keep[_iei(s)[2]]] for s in sims])
        if p_def is None:
            return NoEvidence(f"the model has {100 * below:.2g} % of its intervals below "
                              f"the shortest measured ({p:.3g} us) and no pairs are missing "
                              "at short intervals")
        p = p_def
    if p > REFRACTORY_MAX_US:
        return NoEvidence(f"the short intervals missing reach {p / 1000:.3g} ms, beyond any "
                          f"pixel's dead time ({REFRACTORY_MAX_US / 1000:g} ms at most): "
                          "something else thins them")
    pile_m = np.mean((iei_m >= p) & (iei_m < 1.05 * p + 2))
    pile_s = np.mean((iei_s >= p) & (iei_s < 1.05 * p + 2))
    mode = "delay" if pile_m > 3 * pile_s + 2e-3 else "drop"
    return Fitted(Refractory(period_us=round(p, 1), mode=mode),
                  {"model_share_below": below, "pile_measured": float(pile_m),
                   "pile_model": float(pile_s)})


def _refractory_deficit(iei_m: np.ndarray, iei_s: list[np.ndarray], *,
                        per_decade: int = 32) -> float | None:
    """A dead time seen as the same-pixel pairs the measurement lacks at short intervals,
    when noise events fill the very shortest intervals of both (so the shortest interval
    says nothing). The missing pairs below ``x``, ``D(x) = N_sim(< x) - N_meas(< x)`` (the
    simulations' count scaled to the measured number of pairs), grow with ``x`` up to the
    period and no further: above it the sensor makes pairs as the model does (``drop``: a
    plateau) or piles the delayed ones there (``delay``: ``D`` falls). The period is the
    shortest ``x`` where ``D`` is within its counting noise (2 sigma, plus 2 %) of its
    maximum; ``None`` unless the pairs missing there are at least 30 % of the simulated ones
    and 5 sigma of their count."""
    if iei_m.size < 50 or not iei_s or min(x.size for x in iei_s) < 50:
        return None
    grid = 10 ** np.arange(1.0, 4.6 + 1e-9, 1.0 / per_decade)  # 10 us .. 40 ms
    n_m = np.searchsorted(np.sort(iei_m), grid).astype(np.float64)
    n_s = np.mean([np.searchsorted(np.sort(x), grid) * (iei_m.size / x.size)
                   for x in iei_s], axis=0)
    d = n_s - n_m
    j_max = int(np.argmax(d))
    if d[j_max] <= 0:
        return None
    tol = 2.0 * np.sqrt(max(float(n_s[j_max]), 1.0)) + 0.02 * float(d[j_max])
    j = int(np.flatnonzero(d >= d[j_max] - tol)[0])
    if d[j] < 0.3 * n_s[j] or d[j] < 5 * np.sqrt(max(n_s[j], 1.0)):
        return None
    return float(grid[j])


def _static_excess(meas: Observation, sims: list[Observation], pol: int) -> Any:
    """Per still window of a pixel (the busiest 1 % of pixels left out: hot pixels): the
    measured minus the simulated (mean) count of polarity ``pol``, the variance of that
    difference (Poisson: measured plus simulated over the seeds, at least 1 event), the
    window's mean intensity (DN) and length (s); ``None`` with fewer than 50 still
    windows. The variance is not floored: summed, it is that of the summed excess."""
    st = _static(meas)
    if st.sum() < 50:
        return None
    cnt_m = meas.on if pol > 0 else meas.off
    cnt_s = np.mean([(s.on if pol > 0 else s.off) for s in sims], axis=0)
    cm, cs, ex, z, dur = _hot_excess(meas, sims)
    keep = (cm <= np.quantile(cm, 0.99))[None, :] & st
    i_mid = 0.5 * (meas.intensity[1:] + meas.intensity[:-1])
    ws = np.broadcast_to(meas.window_s[:, None], st.shape)
    var = cnt_m + cnt_s / max(len(sims), 1)
    return (cnt_m - cnt_s)[keep], i_mid[keep], ws[keep], var[keep]


# each polarity's excess in still windows must stand this many standard deviations above
# the model's: shot noise adds both polarities alike, so an excess of one polarity only is
# not its (a leak adds ON events only)
SHOT_MIN_Z = 4.0


def fit_shot_noise(ctx: FitContext) -> FitResult:
    """``ShotNoise`` from the still windows' excess of events of each polarity over the
    model's: ``rate(I) = r (ref / I)**e``, half of the events of each sign. Per exponent on
    a grid, ``r`` by least squares of the excess counts; the exponent whose fit leaves the
    least residual (both signs together), ``r`` the smaller sign's (a leak adds ON). Both
    polarities' summed excess must stand :data:`SHOT_MIN_Z` standard deviations above the
    model's."""
    meas, sims = ctx.meas, ctx.sims
    ref = ShotNoise().ref_dn
    parts = []
    zs = []
    for pol in (+1, -1):
        r = _static_excess(meas, sims, pol)
        if r is None:
            return NoEvidence("fewer than 50 still windows of a pixel")
        parts.append(r[:3])
        zs.append(float(r[0].sum() / np.sqrt(max(float(r[3].sum()), 1.0))))
    if min(zs) < SHOT_MIN_Z:
        which = "OFF" if zs[1] < zs[0] else "ON"
        return NoEvidence(f"still pixels make no excess of {which} events over the model "
                          f"(z = {zs[1] if which == 'OFF' else zs[0]:+.1f} for {which}, "
                          f"{max(zs):+.1f} for the other): shot noise adds both polarities")
    best: tuple[float, float, float] | None = None
    for e in np.arange(0.0, 1.51, 0.25):
        rates, ss = [], 0.0
        for ex, i, ws in parts:
            x = 0.5 * (ref / np.maximum(i, ShotNoise().min_dn)) ** e * ws
            r_e = float((x * ex).sum() / max((x * x).sum(), 1e-12))
            rates.append(r_e)
            ss += float(((ex - r_e * x) ** 2).sum())
        if best is None or ss < best[0]:
            best = (ss, float(e), min(rates))
    assert best is not None
    _, e, rate = best
    if rate <= 0:
        return NoEvidence("the fitted rate of the smaller polarity is not positive")
    return Fitted(ShotNoise(rate_hz=round(rate, 4), ref_dn=ref, light_exponent=e),
                  {"z_on": zs[0], "z_off": zs[1]})


def fit_hot_pixels(ctx: FitContext) -> FitResult:
    """Hot pixels fire when the scene is still: pixels whose still-window count stands 5
    standard deviations (and 10 Hz) above the model's, of those still for at least 5 % of
    the longest still time; their median excess rate, and the share of ON among it."""
    meas, sims = ctx.meas, ctx.sims
    st = _static(meas)
    t_still = (st * meas.window_s[:, None]).sum(0)
    if t_still.max() <= 0:
        return NoEvidence("no pixel is ever still")
    em = ((meas.on + meas.off) * st).sum(0).astype(np.float64)
    es = np.mean([((s.on + s.off) * st).sum(0) for s in sims], axis=0)
    ex = em - es
    z = ex / np.sqrt(es + 1.0 + (0.3 * es) ** 2)
    hot = (z > 5) & (ex > 10.0 * t_still) & (t_still > 0.05 * t_still.max())
    if not hot.any():
        return NoEvidence("no still pixel fires 10 Hz and 5 sigma above the model")
    rate = float(np.median(ex[hot] / t_still[hot]))
    pm = ((meas.on - meas.off) * st).sum(0)[hot].sum()
    ps = np.mean([((s.on - s.off) * st).sum(0)[hot].sum() for s in sims])
    on_frac = float(np.clip(0.5 + 0.5 * (pm - ps) / max(ex[hot].sum(), 1), 0, 1))
    # pixels never still cannot be tested: the fraction is that of the testable ones
    frac = float(hot.sum() / max((t_still > 0.05 * t_still.max()).sum(), 1))
    return Fitted(HotPixels(fraction=round(frac, 6), rate_hz=round(rate, 3),
                            on_fraction=round(on_frac, 3)), {"pixels": int(hot.sum())})


def _threshold_slope(obs: Observation) -> float:
    f = _fit(obs)
    m = np.isfinite(f["res"]) & (f["E"] > 0)
    c = np.where(f["ok"], f["c"], np.nan)
    y = (f["res"] / c[None, :]) ** 2
    y, x = y[m], f["E"][m]
    good = np.isfinite(y)
    y, x = y[good], x[good]
    if x.size < 20:
        return float("nan")
    xm, ym = x.mean(), y.mean()
    return float(((x - xm) * (y - ym)).sum() / max(((x - xm) ** 2).sum(), 1e-12))


# the measured growth of the fit's squared residual with the events of a window must stand
# this many seed-to-seed standard deviations above the model's
THRESHOLD_NOISE_MIN_Z = 3.0


def fit_threshold_noise(ctx: FitContext) -> FitResult:
    """Thresholds drawn anew at every event leave a residual of the per-pixel fit whose
    square, in units of ``c``, grows with the window's events by ``sigma^2`` per event:
    ``sigma^2`` is the measured slope (:func:`_threshold_slope`) less the model's, which
    must stand :data:`THRESHOLD_NOISE_MIN_Z` of its spread over the seeds above it."""
    sm = _threshold_slope(ctx.meas)
    ss = np.array([_threshold_slope(s) for s in ctx.sims])
    ss = ss[np.isfinite(ss)]
    if not np.isfinite(sm) or ss.size == 0:
        return NoEvidence("too few fitted windows to measure the residual's growth")
    d = sm - float(ss.mean())
    var = float(ss.var(ddof=1)) * (1 + 1 / ss.size) if ss.size > 1 else 0.0
    sd = np.sqrt(var + (0.03 * abs(float(ss.mean()))) ** 2 + 1e-8)
    z = d / sd
    if d <= 0 or z < THRESHOLD_NOISE_MIN_Z:
        return NoEvidence(f"the fit's residual grows with a window's events as the model's "
                          f"does (z = {z:+.1f})")
    if d > 1.0:
        # no threshold noise (sigma <= 1) makes this much residual: something else does
        return NoEvidence(f"the residual grows by {d:.2g} c^2 per event, more than any "
                          "threshold noise makes")
    return Fitted(ThresholdNoise(sigma=round(float(np.sqrt(d)), 4)), {"z": float(z)})


def _filter_fit_error(obs: Observation, cutoff_hz: float, offset: float) -> float:
    """Unexplained fraction of ``dLf = c P + b E`` where ``Lf`` is the frames' log intensity
    through the bandwidth low-pass with this cutoff (per pixel, at frame rate). Kept in
    ``obs.extra`` (the measurement's is asked for again every round)."""
    key = f"bandwidth_fit_error/{float(cutoff_hz)!r}/{float(offset)!r}"
    if key in obs.extra:
        cached: float = obs.extra[key]
        return cached
    f = _fit(obs)
    dlf = lowpass_log_changes(np.ascontiguousarray(obs.intensity),
                              np.ascontiguousarray(obs.window_s, np.float64), float(offset),
                              float(cutoff_hz), float(Bandwidth().ref_dn))
    sums = window_sums(f["P"], f["E"], dlf, obs.usable.astype(np.float64))
    c, b, ok = fit_from_sums(*sums[:6])
    ssr = residual_from_sums(sums, np.nan_to_num(c), np.nan_to_num(b))
    err = float(ssr[ok].sum() / max(float(sums[6][ok].sum()), 1e-12))
    obs.extra[key] = err
    return err


# the lag grid widened by these factors, in turn, while the events' lag lies beyond it
BANDWIDTH_LAG_REACH = (2.0, 4.0)


def fit_bandwidth(ctx: FitContext) -> FitResult:
    """The cutoff at ``ref_dn``: seen by the frames, measured by the events' lag.

    Seen: the cutoff whose first-order low-pass of the frames' log intensity, applied at
    frame rate, the events explain best must lie below the frame rate (a filter applied at
    frame rate tells nothing of faster ones): no evidence when no filter beats none. That
    filter reads the cutoff several times low (on v2e's 30 Hz low-pass, 16.2 Hz at 128 DN
    in this law, 3.7-5.7 Hz), so the value is the lag's: a low-pass of cutoff
    ``f(I) = f_c (I + offset) / ref_dn`` follows a ramp ``1 / (2 pi f(I))`` late, and the
    lag of the events behind the frames' changes (measured less simulated,
    :func:`evcal.gap.frames.event_lag`), over pixels weighted by their events, gives
    ``f_c = ref_dn E[1 / (I + offset)] / (2 pi lag)`` (``I`` a pixel's mean frame value).

    Physics tells a slow photoreceptor from a late frame stamp: the low-pass delays the
    events of dark moments more than those of bright ones (the cutoff follows the
    photocurrent), a frame's timing delays every event alike. When the lag is measured in
    the darkest and the brightest third of the cells (window, pixel) by their light
    (:func:`evcal.gap.frames._lag_by_light`) and is shorter in the dark by twice its noise,
    there is no evidence of a low-pass; nor without a lag of the events behind the frames'
    changes, or with a lag within its noise (:func:`evcal.gap.frames.lag_noise_us`: the
    test the frame lag passes too, so that neither of the two is named for evidence the
    other was refused; the lag-by-light difference's own, larger noise judges only the
    order of the thirds). Thirds alike do not refuse it (a window's
    light mixes the dark and bright moments of a moving scene, which dilutes the difference):
    the simulations of the low-pass and of the frame lag, compared on every statistic,
    decide.
    A lag beyond the grid's reach is sought on a grid twice and four times as wide; beyond
    that too (a slow photoreceptor in the dark), it takes the frame-rate filter's cutoff
    (the bias correction makes up part of its error).

    Whatever the frames see, the lag alone is not trusted: with nothing hidden, the
    simulations driven by interpolated frames leave the events a few grid steps of lag
    (0.2 ms at 200 Hz frames), which would read as a kHz photoreceptor."""
    meas, sims, model, rec = ctx.meas, ctx.sims, ctx.model, ctx.rec
    grid = np.geomspace(2.0, 2000.0, 19)
    err = np.array([_filter_fit_error(meas, g, model.log_offset) for g in grid])
    i = int(np.argmin(err))
    if i == grid.size - 1:
        return NoEvidence("a low-pass of the frames explains the events no better than none")
    f = float(grid[i])
    if 0 < i:
        x = np.log(grid[i - 1 : i + 2])
        y = err[i - 1 : i + 2]
        den = y[0] - 2 * y[1] + y[2]
        if den > 0:
            f = float(np.exp(x[1] + 0.5 * (x[1] - x[0]) * (y[0] - y[2]) / den))
    frame_rate_hz = 1e6 / float(np.median(np.diff(meas.frame_t_us)))
    if f >= frame_rate_hz:
        # a low-pass the frames see is slower than they are sampled; a faster one's lag is
        # what a frame's timing, or the light between the frames, leaves as well
        return NoEvidence(f"the low-pass of the frames that explains the events best "
                          f"({f:.3g} Hz) is faster than the frames ({frame_rate_hz:.3g} Hz) "
                          "can tell")
    found = _frames.event_lag(meas, sims, rec)
    for reach in BANDWIDTH_LAG_REACH:
        # beyond the frame timing's grid: a low-pass in the dark delays its events longer
        if found is None or np.isfinite(found[0]):
            break
        found = _frames.event_lag(meas, sims, rec, reach)
    detail: dict[str, Any] = {"frame_filter_hz": f}
    if found is None or found[0] <= 0:
        return NoEvidence("the events do not lag the frames' changes more than the model's "
                          "do: a low-pass would delay them")
    lag, lags = found
    detail["lag_us"] = lag
    by_light = _frames._lag_by_light(meas, sims, lags)
    noise_us = _frames.lag_noise_us(sims, lags)
    if lag <= _frames.LAG_MIN_NOISE * noise_us:
        return NoEvidence(f"the events lag the frames' changes by {lag:.0f} us beyond the "
                          f"model's, within {_frames.LAG_MIN_NOISE:g} times its noise "
                          f"({noise_us:.0f} us)")
    if by_light is not None:
        detail["lag_by_light_us"] = by_light.lags_us
        detail["noise_us"] = by_light.noise_us
        if by_light.earlier_in_the_dark():
            dark, bright = by_light.lags_us[0], by_light.lags_us[-1]
            return NoEvidence(f"the events are later in the brightest third of the moments "
                              f"({bright:.0f} us) than in the darkest ({dark:.0f} us, noise "
                              f"{by_light.noise_us:.0f} us): a low-pass delays the dark ones "
                              "more")
    if np.isfinite(lag):
        ref = float(Bandwidth().ref_dn)
        light = meas.intensity.mean(0).astype(np.float64) + float(model.log_offset)
        w = (meas.on.sum(0) + meas.off.sum(0)).astype(np.float64)
        ok = (light > 0) & (w > 0)
        if ok.any():
            inv = float(np.sum(w[ok] / light[ok]) / np.sum(w[ok]))
            return Fitted(Bandwidth(cutoff_hz=round(ref * inv / (2.0 * np.pi * lag * 1e-6),
                                                    3)), detail)
    # later than the lag grid reaches: the frame-rate filter's cutoff (several times low; the
    # bias correction makes up part of it)
    return Fitted(Bandwidth(cutoff_hz=round(f, 3)), detail)


# light bins of the sensitivity a dark level shapes: its law is a curve in the light
LOG_OFFSET_BINS = 8
LOG_OFFSET_GRID_DN = np.geomspace(0.5, 400.0, 160)
# windows a light bin needs (of the measurement's windows that change by more than 0.1)
LOG_OFFSET_MIN_WINDOWS = 50
# the least noise of a bin's log sensitivity: the model's own error, beyond the seeds'
LOG_OFFSET_FLOOR = 0.02
# the two readings of the dark level are settled by simulation when they differ by more
LOG_OFFSET_DISAGREE = 1.3


def sensitivity_by_light(obs: Observation, edges: np.ndarray | None = None
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Events per unit of the frames' log change (nominal offset) in the windows that change
    by more than 0.1, per bin of the window's light (``edges``, DN; default the
    :data:`LOG_OFFSET_BINS` quantiles of ``obs``'s own windows): the sensitivity, the bin's
    light (its windows' mean weighted by their change), the windows per bin and the edges."""
    adl, m, i_mid = _changing_windows(obs)
    light = i_mid[m].astype(np.float64)
    if edges is None:
        q = np.quantile(light, np.linspace(0.0, 1.0, LOG_OFFSET_BINS + 1)) if light.size \
            else np.zeros(LOG_OFFSET_BINS + 1)
        edges = np.asarray(q, np.float64).copy()
        edges[-1] += 1e-6
    nb = edges.size - 1
    idx = np.clip(np.searchsorted(edges, light, side="right") - 1, 0, nb - 1)
    a = adl[m]
    dl = np.bincount(idx, weights=a, minlength=nb)
    ev = np.bincount(idx, weights=_fit(obs)["E"][m], minlength=nb)
    n = np.bincount(idx, minlength=nb)
    with np.errstate(invalid="ignore", divide="ignore"):
        sens = np.where(dl > 0, ev / dl, np.nan)
        lbar = np.where(dl > 0, np.bincount(idx, weights=light * a, minlength=nb) / dl, np.nan)
    return sens, lbar, n, edges


class _SensitivityShape:
    """The measurement's events per unit of change by light against the model's
    simulations: ``y`` the log ratio per usable bin, ``var`` its noise (the simulations'
    spread, floored), ``light`` the bins' light; :meth:`curve_fit` the dark level whose
    curve fits it, :meth:`chi2_of` how far another observation's sensitivity is from the
    measurement's (a common factor free in both)."""

    def __init__(self, meas: Observation, sims: list[Observation]) -> None:
        sens_m, lbar, n, self.edges = sensitivity_by_light(meas)
        with np.errstate(invalid="ignore", divide="ignore"):
            self.log_m = np.log(sens_m)
            log_s = np.log(np.array([sensitivity_by_light(s, self.edges)[0] for s in sims]))
        self.ok = ((n >= LOG_OFFSET_MIN_WINDOWS) & np.isfinite(self.log_m)
                   & np.isfinite(log_s).all(0) & np.isfinite(lbar))
        k = self.ok
        self.y = self.log_m[k] - log_s[:, k].mean(0)
        spread = log_s[:, k].var(0, ddof=1) if len(sims) > 1 else np.zeros(int(k.sum()))
        self.var = spread * (1.0 + 1.0 / len(sims)) + LOG_OFFSET_FLOOR ** 2
        self.light = np.maximum(lbar[k], 0.0)

    def _chi2(self, r: np.ndarray) -> np.ndarray:
        a = (r / self.var).sum(-1, keepdims=True) / (1.0 / self.var).sum()
        out: np.ndarray = ((r - a) ** 2 / self.var).sum(-1)
        return out

    def curve_fit(self, m: float) -> float:
        """The dark level whose curve ``(I + m) / (I + d)`` fits the ratio best."""
        x = (np.log(self.light[None, :] + m)
             - np.log(self.light[None, :] + LOG_OFFSET_GRID_DN[:, None]))
        return float(LOG_OFFSET_GRID_DN[int(np.argmin(self._chi2(self.y[None, :] - x)))])

    def chi2_of(self, obs: Observation) -> float:
        """How far ``obs``'s sensitivity by light is from the measurement's, in shape."""
        with np.errstate(invalid="ignore", divide="ignore"):
            log_o = np.log(sensitivity_by_light(obs, self.edges)[0])[self.ok]
        if not np.isfinite(log_o).all():
            return float("inf")
        return float(self._chi2(self.log_m[self.ok] - log_o))


def fit_log_offset(ctx: FitContext) -> FitResult:
    """The dark level ``d`` under the sensor's log. Two readings: OffEI's own estimate (the
    offset that leaves the per-pixel fits least unexplained, :func:`estimate_log_offset`) and
    the curve of the events' sensitivity to the frames' log change against light, measured
    over the model's simulations (a sensor that sees ``log(I + d)`` fires ``(I + m) / (I +
    d)`` times the events of a model with dark level ``m`` per unit of change at light ``I``:
    flat where ``I >> d``, falling in the dark). Where they differ by more than
    :data:`LOG_OFFSET_DISAGREE` times, the model with each (and without any, when a reading
    is below twice ``m``) is simulated once and the one whose sensitivity by light is
    nearest the measurement's is taken. No evidence below twice ``m``.

    Each pixel's own windows may not tell a dark level from thresholds that grow in the dark
    as a power (its ``c`` takes up the mean, the rest is in the events' quantisation), least
    with few frames. The curve sees the sensor's whole light but also what other effects
    (shot noise) and the interpolation between frames do to the sensitivity: neither
    reading is trusted alone (docs/notes/gap-oracle-2026-11-29.md)."""
    meas, sims, model = ctx.meas, ctx.sims, ctx.model
    m = _dark_dn(model)
    floor = 2.0 * max(m, NOMINAL_LOG_OFFSET_DN)
    detail: dict[str, Any] = {}
    readings: list[float] = []
    try:
        rec = ctx.recording()
        o, _ = estimate_log_offset(rec, OffEIConfig(
            window_frames=max(1, min(5, len(rec.frames) // 4))))
        detail["offei_dn"] = float(o)
        readings.append(float(o))
    except (CalibrationError, ValueError) as exc:
        detail["offei"] = str(exc)
    shape = _SensitivityShape(meas, sims) if sims else None
    if shape is not None and shape.ok.sum() >= 4:
        detail["curve_dn"] = shape.curve_fit(m)
        readings.append(detail["curve_dn"])
    if not readings:
        return NoEvidence(f"the log offset could not be estimated: {detail.get('offei')}")
    d = readings[0]
    lo, hi = min(readings), max(readings)
    # the curve alone (OffEI could not read) or two readings apart: settled by simulation
    unsettled = "offei_dn" not in detail or hi > LOG_OFFSET_DISAGREE * max(lo, 1e-9)
    if unsettled and hi >= floor and shape is not None and ctx.simulate is not None:
        trials = {r: ctx.simulate(LogOffset(dark_dn=round(r, 3))) for r in readings
                  if r >= floor}
        chi = {r: shape.chi2_of(obs) for r, obs in trials.items()}
        if lo < floor or len(readings) == 1:
            # the model as it is: its own simulations say what no dark level gives
            chi[min(lo, m)] = float(np.mean([shape.chi2_of(s) for s in sims]))
        d = min(chi, key=lambda r: chi[r])
        detail["chi2"] = {f"{r:.3g}": round(v, 2) for r, v in chi.items()}
    elif "offei_dn" not in detail:
        d = m  # the curve alone, unsettled: no evidence
    if d < floor:
        return NoEvidence(f"the offset that explains the events best is {d:.3g} DN, at the "
                          f"model's {m:.3g} DN")
    return Fitted(LogOffset(dark_dn=round(float(d), 3)), detail)


def _jitter_times(t_us: np.ndarray, sigma_us: float, quantum_us: int,
                  rng: np.random.Generator) -> np.ndarray:
    """Event times (us) with Gaussian jitter ``sigma_us``, then quantised to ``quantum_us``."""
    t = t_us + np.rint(rng.normal(0, sigma_us, t_us.size)).astype(np.int64)
    if quantum_us > 1:
        t = (t // quantum_us) * quantum_us
    return t


def _short_iei_stats(pix: np.ndarray, t_us: np.ndarray, *, nearly_sorted: bool = False
                     ) -> dict[str, StatValue]:
    """log10 of the share of same-pixel IEIs below 3, 10, 30, 100, 300 us, and the timestamp
    quantum statistic, of events in any order (``nearly_sorted``: mostly in pixel, then time
    order already, as jittered events put in their pixels' order are; the sort then merges
    runs instead of sorting from scratch, with the same result)."""
    x = np.array([3.0, 10.0, 30.0, 100.0, 300.0])
    if t_us.size < 2:
        frac = np.zeros(5)
    else:
        t_rel = t_us - t_us.min()
        if t_rel.max() < 1 << 40:
            # one sort of (pixel, time) packed in an int64 (times up to 12 days)
            key = np.sort((pix.astype(np.int64) << 40) | t_rel,
                          kind="stable" if nearly_sorted else None)
            same = (key[1:] >> 40) == (key[:-1] >> 40)
            iei = np.diff(key)[same]
        else:
            order = np.lexsort((t_rel, pix))
            same = pix[order][1:] == pix[order][:-1]
            iei = np.diff(t_rel[order])[same]
        frac = np.array([np.mean(iei < v) for v in x]) if iei.size else np.zeros(5)
    short = StatValue("short_iei", np.log10(frac + 1e-5), [f"IEI < {v:g} us" for v in x], 0.02)
    return {"short_iei": short, "timestamp_quantum": timestamp_quantum(t_us)}


SPILL_DL_EDGES = np.array([-np.inf, 0.05, 0.15, 0.3, 0.6, np.inf])


class _SpillResidual:
    """RMS of the per-window fit residual ``dL - c P - b E`` in bins of abs(dL) (the fit
    redone per pixel), after moving the events of ``obs`` to new times.

    Jittered events cross frame boundaries into the neighbouring window, one threshold of
    residual each; how many do is first order in the event rate at the boundaries. Frame times
    fall at random phases of the scene's motion, so that rate is the same for measured events
    and for simulations driven by interpolated frames, however either spreads its events
    within a frame interval (pair statistics such as short IEIs are not: linear
    interpolation spaces a pixel's events more evenly than a real edge does).

    The fit needs per-pixel sums only; they are kept per (abs(dL) bin, pixel) and updated
    in the windows that moved events leave or enter, so a new set of times costs in
    proportion to the events that change window.
    """

    # per cell: P P, P E, E E, P dL, E dL, E, dL dL (weighted by usable)
    _N_SUMS = 7

    def __init__(self, obs: Observation):
        f = _fit(obs)
        n_w, npix = obs.on.shape
        self.ft = obs.frame_t_us
        self.npix = npix
        self.n_cells = n_w * npix
        self.pix = obs.pix.astype(np.int64)
        self.pol = obs.p.astype(np.float64)
        win = event_windows(obs.t_us, self.ft)
        # events outside the frames go to a spare last cell
        self.key0 = np.where((win >= 0) & (win < n_w), win * npix + self.pix, self.n_cells)
        # only the usable cells (window, pixel) of pixels that can be fitted enter the sums:
        # moved events stay in their pixel, so one with fewer than MIN_FIT_EVENTS events
        # has no fit whatever the times (every array here is one per kept cell, and on a
        # real recording most pixels have a few events or none)
        can_fit = np.bincount(self.pix, minlength=npix) >= MIN_FIT_EVENTS
        self.cells = np.flatnonzero(obs.usable.ravel() & np.tile(can_fit, n_w))
        self.P = f["P"].ravel()[self.cells].astype(np.float64)
        self.E = f["E"].ravel()[self.cells].astype(np.float64)
        self.dL = f["dL"].ravel()[self.cells].astype(np.float64)
        self.nb = SPILL_DL_EDGES.size - 1
        b = np.clip(np.searchsorted(SPILL_DL_EDGES, np.abs(self.dL), side="right") - 1,
                    0, self.nb - 1)
        # (bin, pixel) index of every kept cell
        self.bp = b * npix + self.cells % npix
        self.sums = self._cell_sums(np.arange(self.cells.size), self.P, self.E)
        self.count = np.bincount(self.bp, minlength=self.nb * npix
                                 ).astype(np.float64).reshape(self.nb, npix)

    def _cell_sums(self, idx: np.ndarray, P: np.ndarray, E: np.ndarray) -> np.ndarray:
        """The sums of the kept cells ``idx`` (indices into :attr:`cells`) with counts
        ``P``, ``E``, per (abs(dL) bin, pixel); one term at a time (each is as long as
        ``idx``)."""
        y, bp = self.dL[idx], self.bp[idx]
        n = self.nb * self.npix
        out = np.empty((self._N_SUMS, n))
        for k, (a, b) in enumerate(((P, P), (P, E), (E, E), (P, y), (E, y), (E, None),
                                    (y, y))):
            out[k] = np.bincount(bp, weights=a if b is None else a * b, minlength=n)
        return out.reshape(self._N_SUMS, self.nb, self.npix)

    def stat(self, t_us: np.ndarray | None = None) -> StatValue:
        sums = self.sums
        if t_us is not None:
            n_w = self.ft.size - 1
            win = event_windows(t_us, self.ft)
            key = np.where((win >= 0) & (win < n_w), win * self.npix + self.pix, self.n_cells)
            moved = np.flatnonzero(key != self.key0)
            if moved.size:
                keys = np.concatenate([key[moved], self.key0[moved]])
                cells, inv = np.unique(keys, return_inverse=True)
                k = moved.size
                dp = np.bincount(inv, weights=np.concatenate([self.pol[moved],
                                                              -self.pol[moved]]))
                de = np.bincount(inv, weights=np.concatenate([np.ones(k), -np.ones(k)]))
                # cells that are not kept (not usable, or the spare one) weigh nothing
                pos = np.minimum(np.searchsorted(self.cells, cells), self.cells.size - 1)
                kept = (self.cells[pos] == cells) if self.cells.size else cells < 0
                idx, dp, de = pos[kept], dp[kept], de[kept]
                p0, e0 = self.P[idx], self.E[idx]
                sums = (sums + self._cell_sums(idx, p0 + dp, e0 + de)
                        - self._cell_sums(idx, p0, e0))
        spp, spe, see, spy, sey, sev, syy = sums
        c, b, ok = fit_from_sums(spp.sum(0), spe.sum(0), see.sum(0), spy.sum(0), sey.sum(0),
                                 sev.sum(0))
        c, b = np.where(ok, c, 0.0), np.where(ok, b, 0.0)
        # sum of squared residuals per (bin, pixel), expanded
        ss = (syy - 2 * c * spy - 2 * b * sey + c * c * spp + 2 * c * b * spe + b * b * see)
        n_bin = (self.count * ok).sum(1)
        v = np.sqrt(np.maximum((ss * ok).sum(1), 0.0) / np.maximum(n_bin, 1))
        labels = [f"|dL| {lo:.3g}..{hi:.3g}" for lo, hi in zip(SPILL_DL_EDGES[:-1],
                                                               SPILL_DL_EDGES[1:], strict=True)]
        return StatValue("spill_residual", v, labels, 0.003)


def _grid_minimum(grid: np.ndarray, gaps: np.ndarray) -> float:
    """Grid point of the smallest gap, refined by a parabola in log(grid)."""
    i = int(np.argmin(gaps))
    sigma = float(grid[i])
    if 1 < i < grid.size - 1:
        x = np.log(grid[i - 1 : i + 2])
        y = gaps[i - 1 : i + 2]
        den = y[0] - 2 * y[1] + y[2]
        if den > 0:
            sigma = float(np.exp(x[1] + 0.5 * (x[1] - x[0]) * (y[0] - y[2]) / den))
    return sigma


# a drop of the spill residual's discrepancy (mean z^2) below which it does not see the jitter
SPILL_MIN_DROP = 1.0
# how far the spill estimate may lie from the short-IEI one (which interpolated frames bias by
# up to about 1.5x) and still be taken as the size of the same jitter
SPILL_IEI_RATIO = 2.0
JITTER_EVENTS = 500_000  # measured events the jitter fitter's curves are made of, about
JITTER_GRID_US = np.concatenate([[0.0], np.geomspace(3, 3000, 16)])


def _jitter_curves(meas: Observation, sims: list[Observation], q_hat: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Gaps of the short-IEI statistics and of the spill residual against the simulated
    events jittered by each sigma of :data:`JITTER_GRID_US` (and quantised to ``q_hat``)."""
    rng = np.random.default_rng(12345)
    m_iei = _short_iei_stats(meas.pix, meas.t_us)
    m_spill = {"spill_residual": _SpillResidual(meas).stat()}
    spills = [_SpillResidual(s) for s in sims]
    # each simulation's events in pixel order (stable: each pixel's in time order), so that
    # the jittered ones are nearly sorted for the short IEIs
    orders = [order_by_key(s.pix, s.n_pixels) for s in sims]
    pix_sorted = [s.pix[o] for s, o in zip(sims, orders, strict=True)]
    g_iei, g_spill = [], []
    for sg in JITTER_GRID_US:
        ts = [_jitter_times(s.t_us, sg, q_hat, rng) for s in sims]
        g_iei.append(discrepancy(m_iei, [
            _short_iei_stats(p, t[o], nearly_sorted=True)
            for p, t, o in zip(pix_sorted, ts, orders, strict=True)]).gap)
        g_spill.append(discrepancy(m_spill, [{"spill_residual": sp.stat(t)}
                                             for sp, t in zip(spills, ts, strict=True)]).gap)
    return np.asarray(g_iei), np.asarray(g_spill)


# the short intervals' discrepancy must fall by this much at the fitted jitter (no quantum)
JITTER_MIN_DROP = 2.0


def fit_timestamp_jitter(ctx: FitContext) -> FitResult:
    """Quantum from the residues of the timestamps; sigma by jittering the simulated events on
    a grid (no re-simulation) and matching two statistics.

    The short IEIs (below 300 us) say whether there is jitter and roughly how much, but the
    frame interpolation biases them: its events are spaced more evenly than real ones, so the
    simulations have fewer close pairs for the jitter to bring together and need a larger
    sigma (about 1.4x at 500 us). The spill residual (:class:`_SpillResidual`) measures sigma
    without that bias but also grows with other effects (bandwidth, refractory), so it gives
    sigma only where it sees a change and agrees with the IEIs within a factor
    :data:`SPILL_IEI_RATIO`; otherwise the IEI estimate stands.
    """
    meas, sims = ctx.meas, ctx.sims
    t = meas.t_us
    q_hat = 1
    for q in (2, 5, 10, 20, 50, 100, 200, 500, 1000):
        res = t % q
        share = np.bincount(res, minlength=q).max() / max(t.size, 1)
        if share >= 0.99:
            q_hat = q
    # the curves are per-pixel statistics: a sample of rows holding about JITTER_EVENTS
    # events gives them (the grid jitters every event of it again for each sigma)
    n = int(np.clip(np.ceil(meas.t_us.size / JITTER_EVENTS), 1, 8))
    g_iei, g_spill = _jitter_curves(every_nth_row(meas, n), [every_nth_row(s, n) for s in sims],
                                    q_hat)
    drop = float(g_iei[0] - g_iei.min())
    if q_hat == 1 and (int(np.argmin(g_iei)) == 0 or drop < JITTER_MIN_DROP):
        return NoEvidence(f"jittering the model's events brings its short intervals no "
                          f"closer to the measured ones (their discrepancy falls by "
                          f"{drop:.2g})")
    sigma = _grid_minimum(JITTER_GRID_US, g_iei)
    s_spill = _grid_minimum(JITTER_GRID_US, g_spill)
    if (g_spill[0] - g_spill.min() > SPILL_MIN_DROP
            and sigma / SPILL_IEI_RATIO <= s_spill <= sigma * SPILL_IEI_RATIO):
        sigma = s_spill
    return Fitted(TimestampJitter(sigma_us=round(sigma, 2), quantum_us=int(q_hat)),
                  {"iei_drop": drop})


def fit_timestamp_quantisation(ctx: FitContext) -> FitResult:
    """Step and phase from the timestamps that many events share: a frame-driven simulator
    gives the events of a step a few shared times (fractions of the step; the busiest pixel's
    last event, and with ``scheme="end"`` every event, the step's end), so the most crowded
    timestamps lie on a grid. The step is the most common spacing of the crowded timestamps,
    the phase the residue of the most distinct timestamps (each step's end); the effect is
    proposed only if many more measured events than simulated ones lie on that grid, or on
    its slots (:func:`scheme_slots`: v2e stamps most events of a busy step on a slot short
    of its end)."""
    meas, sims, rec = ctx.meas, ctx.sims, ctx.rec
    t = meas.t_us
    u, cnt = np.unique(t, return_counts=True)
    if u.size < 50:
        return NoEvidence(f"{u.size} distinct timestamps")
    top = u[cnt >= max(float(np.quantile(cnt, 0.95)), 3.0)]
    d = np.diff(top)
    d = d[(d > 0) & (d <= 1_000_000)]
    if d.size < 10:
        return NoEvidence("no timestamps are shared by many events")
    step = int(np.bincount(d).argmax())
    if step < 2:
        return NoEvidence("the crowded timestamps lie on no grid")
    # every step with events has one at its end, whatever its n_max: the residue shared by
    # the most distinct timestamps
    phase = int(np.bincount(u % step, minlength=step).argmax())
    on_grid = float(np.mean(t % step == phase))
    sim_on_grid = float(np.mean([np.mean(s.t_us % step == phase) for s in sims])) \
        if sims else 1.0 / step
    # v2e's scheme puts a step's events at the slots i / N of it, N the most any pixel has
    # pending: in a busy scene most events fall on the first slot of a step, few on its end
    offsets = scheme_slots(step)
    on_slots = float(np.mean(np.isin((t - phase) % step, offsets)))
    sim_on_slots = float(np.mean([np.mean(np.isin((s.t_us - phase) % step, offsets))
                                  for s in sims])) if sims else offsets.size / step
    if on_grid < 5 * sim_on_grid + 0.02 and \
            on_slots < max(SCHEME_MIN_ON_SLOTS, sim_on_slots + SCHEME_MIN_SLOT_EXCESS):
        return NoEvidence(f"{100 * on_grid:.2g} % of the events lie on a {step} us grid "
                          f"(the model's {100 * sim_on_grid:.2g} %), {100 * on_slots:.2g} % "
                          f"on its slots of up to {SCHEME_MAX_SLOTS} per step (the model's "
                          f"{100 * sim_on_slots:.2g} %)")
    t0 = int(rec.frames.t_us[0])
    return Fitted(TimestampQuantisation(step_us=float(step), scheme="end" if on_grid > 0.9
                                        else "spread", phase_us=float((phase - t0) % step)),
                  {"on_grid": on_grid, "on_slots": on_slots})


SCHEME_MAX_SLOTS = 12  # slots per step the evidence counts (a step of N has N slots)
SCHEME_MIN_ON_SLOTS = 0.8  # events on the slots that show the scheme ...
SCHEME_MIN_SLOT_EXCESS = 0.3  # ... and by how much more than the model's


def scheme_slots(step: int, max_slots: int = SCHEME_MAX_SLOTS) -> np.ndarray:
    """The offsets from a step's start (us, in ``[0, step)``; its end is offset 0) where
    a frame-driven simulator stamps events: ``step i / N`` for ``N`` up to ``max_slots``
    slots, ``i < N``, rounded either way (whole microseconds)."""
    out = {0}
    for n in range(2, max_slots + 1):
        for i in range(1, n):
            v = step * i / n
            out.update((math.floor(v), math.ceil(v)))
    return np.array(sorted(o % step for o in out), np.int64)
