"""The model the gap workflow grows: per-pixel ``c``, ``b``, a log offset and named effects.

- :func:`fit_base` fits ``c``, ``b`` with OffEI at a given log offset and shrinks each pixel
  towards the population by its standard error (so estimation noise does not read as fixed
  pattern in the simulation).
- :func:`simulate_model` re-simulates a measured recording under a model, driven by its frames
  (dithered by the frame noise the frames carry: quantisation and read noise, so the
  simulated events disagree with the frames as much as real ones do).
- :func:`anchor` rescales ``c`` and shifts ``b`` so that a simulation of the model, fitted the
  same way as the measurement, gives the measured population values (effects such as leak or
  refractory bias the fit; the anchor undoes that bias for the model as a whole).
- :func:`fit_candidate` estimates one effect's parameters from the measured statistics and
  those of the current model's simulations (moment estimators, described per effect).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..calibration import Calibration
from ..errors import CalibrationError, ConfigError
from ..events import SensorSize
from ..offline import OffEIConfig, estimate_log_offset, offei
from ..recording import Frames, Recording
from ..sim.effects import (
    Bandwidth,
    Effect,
    Exposure,
    HotPixels,
    LogOffset,
    Refractory,
    ShotNoise,
    ThresholdNoise,
    TimestampJitter,
    TimestampQuantisation,
)
from ..sim.ideal import SimConfig
from ..sim.nonideal import simulate
from ..sim.sources import FrameInterpolator
from ..stream import event_windows
from . import fitters_events as _events
from . import frames as _frames
from .render import RenderCache, frames_key
from .stats import (
    NOMINAL_LOG_OFFSET_DN,
    Observation,
    StatValue,
    _fit,
    _iei,
    _static,
    discrepancy,
    every_nth_row,
    fit_from_sums,
    lowpass_log_changes,
    observe,
    residual_from_sums,
    timestamp_quantum,
    window_sums,
)


@dataclass(frozen=True)
class Model:
    contrast: np.ndarray
    bias: np.ndarray
    log_offset: float
    effects: dict[str, Effect] = field(default_factory=dict)
    # the maps were corrected by :func:`anchor` (an effect added to such a model, or a
    # parameter changed, keeps them: anchoring it again may take one simulation, not two)
    anchored: bool = False

    def with_effect(self, effect: Effect) -> Model:
        eff = dict(self.effects)
        eff[effect.name] = effect
        return replace(self, effects=eff)


@dataclass(frozen=True)
class Band:
    """A band of sensor rows that screening simulations run on: ``rows`` of the whole
    sensor, and ``rec``, the recording cut to them (its events and frames; the statistics
    of a screening are computed on it)."""

    rows: slice
    rec: Recording
    sensor_height: int  # rows of the whole sensor

    @property
    def share(self) -> float:
        """The band's share of the sensor's rows."""
        return float(self.rows.stop - self.rows.start) / self.sensor_height

    @classmethod
    def of(cls, rec: Recording, y0: int, y1: int) -> Band:
        h, w = rec.sensor.shape
        if not 0 <= y0 < y1 <= h:
            raise ConfigError(f"band rows {y0}..{y1} are not inside the sensor's 0..{h}")
        ev = rec.events[(rec.events["y"] >= y0) & (rec.events["y"] < y1)].copy()
        ev["y"] -= y0
        fr = rec.frames
        frames = Frames(fr.t_us, fr.images[:, y0:y1], fr.exposure_us)
        return cls(slice(y0, y1), Recording(SensorSize(y1 - y0, w), ev, frames,
                                            dict(rec.metadata)), h)

    def model(self, model: Model) -> Model:
        """``model`` with the maps of the band's rows, and its effects on them
        (:meth:`~evcal.sim.effects.Effect.on_rows`)."""
        return replace(model, contrast=model.contrast[self.rows], bias=model.bias[self.rows],
                       effects={k: e.on_rows(self.rows) for k, e in model.effects.items()})


@dataclass(frozen=True, kw_only=True)
class SimSettings:
    internal_rate_hz: float = 1000.0
    read_noise_dn: float = 0.0  # of the measured frames (estimated)
    dither: bool = True
    # the latent intensity between frames: "linear" blend or "flow" (motion-compensated,
    # evcal.gap.flow; needs OpenCV)
    interpolation: str = "linear"

    def __post_init__(self) -> None:
        if self.interpolation not in ("linear", "flow"):
            raise ConfigError(f"interpolation={self.interpolation!r} must be 'linear' or 'flow'")


def estimate_read_noise(frames: Frames) -> float:
    """Temporal noise of the frames (DN): robust spread of frame differences where the scene
    is still (|difference| < 8 DN), divided by sqrt(2)."""
    im = frames.images.astype(np.float64)
    d = np.diff(im, axis=0)
    d = d[np.abs(d) < 8]
    if d.size < 100:
        return 0.0
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2))


def _shrink(cal: Calibration, offset: float) -> tuple[np.ndarray, np.ndarray]:
    c = cal.contrast.astype(np.float64)
    b = cal.bias.astype(np.float64)
    v = cal.valid
    if v.sum() < 10:
        cm = float(np.median(c[v])) if v.any() else 0.15
        bm = float(np.median(b[v])) if v.any() else 0.0
        return np.full(c.shape, cm), np.full(b.shape, bm)
    cm, bm = float(np.median(c[v])), float(np.median(b[v]))
    cv = (1.4826 * np.median(np.abs(c[v] - cm))) ** 2
    bv = (1.4826 * np.median(np.abs(b[v] - bm))) ** 2
    se_c = np.where(np.isfinite(cal.stderr_contrast), cal.stderr_contrast, 1e9)
    se_b = np.where(np.isfinite(cal.stderr_bias), cal.stderr_bias, 1e9)
    kc = np.clip(1 - se_c**2 / max(cv, 1e-12), 0, 1)
    kb = np.clip(1 - se_b**2 / max(bv, 1e-12), 0, 1)
    c = np.where(v, cm + kc * (c - cm), cm)
    b = np.where(v, bm + kb * (b - bm), bm)
    c = np.maximum(c, 0.3 * cm)
    b = np.clip(b, -0.8 * c, 0.8 * c)
    return c, b


def fit_base(rec: Recording, log_offset: float = NOMINAL_LOG_OFFSET_DN) -> Model:
    """``c``, ``b`` by OffEI at ``log_offset`` (shrunk towards the population)."""
    n_f = len(rec.frames)
    cfg = OffEIConfig(window_frames=max(1, min(5, n_f // 4)), log_offset=float(log_offset))
    try:
        cal = offei(rec, cfg)
        c, b = _shrink(cal, log_offset)
    except CalibrationError:
        c = np.full(rec.sensor.shape, 0.15)
        b = np.zeros(rec.sensor.shape)
    return Model(c, b, float(log_offset))


def latent_frames(frames: Frames, read_noise_dn: float) -> np.ndarray:
    """The frames as float32 latent intensity, their read noise taken out where a pixel is
    still: each pixel's frames are cut into runs within which every frame lies within the
    noise (``3 read_noise_dn + 1`` DN) of the run's mean so far, and a run is replaced by its
    mean (the scene is still there; the noise is in the frames, not in the light the events
    saw). A pixel that changes makes runs of one frame: its frames are kept as they are.

    Without the runs a still pixel's frames (or a short moving mean of them) carry the noise
    into the simulation, whose events then follow it: on a DAVIS346 recording of a still
    scene (1 DN read noise) the simulated still pixels fired 5x the measured rate, the dark
    ones most."""
    imgs = frames.images.astype(np.float32)
    if read_noise_dn <= 0.5 or imgs.shape[0] < 3:
        return imgs
    tol = 3.0 * read_noise_dn + 1.0
    k = imgs.shape[0]
    f = imgs.reshape(k, -1)
    npix = f.shape[1]
    run = np.empty((k, npix), np.int64)  # run id of every frame of every pixel
    run[0] = np.arange(npix)
    total = f[0].astype(np.float64)
    n = np.ones(npix)
    for i in range(1, k):  # a pass over the frames, vectorised over pixels
        inside = np.abs(f[i] - total / n) < tol
        run[i] = np.where(inside, run[i - 1], i * npix + np.arange(npix))
        total = np.where(inside, total + f[i], f[i])
        n = np.where(inside, n + 1, 1.0)
    _, inv = np.unique(run, return_inverse=True)
    inv = inv.ravel()
    means = np.bincount(inv, weights=f.ravel().astype(np.float64)) / np.bincount(inv)
    out: np.ndarray = means[inv].reshape(imgs.shape).astype(np.float32)
    return out


def _times(frames: Frames, internal_rate_hz: float) -> np.ndarray:
    ft = frames.t_us - frames.t_us[0]
    end = int(ft[-1])
    grid = np.rint(np.arange(0, end * 1e-6 * internal_rate_hz + 1) * 1e6 / internal_rate_hz)
    grid = grid[grid <= end].astype(np.int64)
    return np.unique(np.concatenate([grid, ft]))


def simulate_model(model: Model, rec: Recording, seed: int, settings: SimSettings,
                   render: RenderCache | None = None, band: Band | None = None) -> Recording:
    """A re-simulation of ``rec`` (same frames, same time base) under ``model``.

    The latent intensity (the frames the model says the events saw, :func:`.frames.
    model_frames`, interpolated at the internal sample times) does not depend on the seed:
    with ``render`` it is rendered once and shared by every simulation of the run. The seed's
    quantisation dither is added to it per pixel.

    ``band``: only its rows are simulated (``model``'s maps are the band's, see
    :meth:`Band.model`), from the whole sensor's latent intensity; the result is a
    recording of the band (``band.rec``'s sensor and frames)."""
    from .frames import model_frames  # noqa: PLC0415

    fr = rec.frames
    assert fr is not None
    rng = np.random.default_rng([seed, 7919])
    # the exposure lag moves the frames' stamps only: the sequence of the frames without it,
    # read ``lag`` earlier (one render serves every lag the workflow tries)
    exp = model.effects.get(Exposure.name)
    lag_us = int(round(float(exp.lag_us))) if isinstance(exp, Exposure) else 0
    drive = model_frames(model, fr) if lag_us == 0 else model_frames(
        replace(model, effects={k: e for k, e in model.effects.items()
                                if k != Exposure.name}), fr)
    add = None
    if settings.dither and fr.images.dtype == np.uint8:
        # the quantisation error of a still pixel is the same in every frame: one offset per
        # pixel, not per frame (per-frame dither would make still scenes fire)
        add = rng.uniform(-0.5, 0.5, fr.images.shape[1:]).astype(np.float32)
        if band is not None:
            add = add[band.rows]
    times = _times(fr, settings.internal_rate_hz)
    t0 = int(fr.t_us[0])
    shape = rec.sensor.shape

    def make_source() -> FrameInterpolator:
        latent = Frames(drive.t_us, latent_frames(drive, settings.read_noise_dn),
                        drive.exposure_us)
        if settings.interpolation == "flow":
            from .flow import FlowInterpolator  # noqa: PLC0415

            return FlowInterpolator(latent, shape, t_origin_us=t0,
                                    flow_images=drive.images.astype(np.float32))
        return FrameInterpolator(latent, shape, t_origin_us=t0)

    cache = render if render is not None else RenderCache(max_bytes=0)
    key = frames_key(drive, settings.interpolation, times)
    src = cache.source(key, times, shape, make_source, add,
                       rows=None if band is None else band.rows, lag_s=lag_us * 1e-6)
    dur = max(times[-1] * 1e-6, 1e-3)
    h, w = shape if band is None else band.rec.sensor.shape
    cfg = SimConfig(height=h, width=w, duration_s=dur, frame_rate_hz=1.0,
                    internal_rate_hz=max(settings.internal_rate_hz, 1.0),
                    log_offset=model.log_offset, seed=int(seed))
    res = simulate(cfg, model.effects, source=src, maps=(model.contrast, model.bias),
                   frames=fr if band is None else band.rec.frames, times_us=times,
                   t_origin_us=t0)
    return res.recording


def population(obs: Observation) -> tuple[float, float]:
    f = _fit(obs)
    ok = f["ok"]
    if ok.sum() < 5:
        return float("nan"), float("nan")
    return float(np.median(f["c"][ok])), float(np.median(f["b"][ok]))


def _bins(meas: Observation, ok: np.ndarray, n_bins: int) -> np.ndarray:
    count = (meas.on + meas.off).sum(0).astype(np.float64)
    edges = np.unique(np.quantile(count[ok], np.linspace(0, 1, n_bins + 1)))
    edges[0], edges[-1] = -np.inf, np.inf
    result: np.ndarray = np.clip(np.searchsorted(edges, count, side="right") - 1, 0, edges.size - 2)
    return result


def anchor(model: Model, rec: Recording, meas: Observation, seed: int,
           settings: SimSettings, *, n_bins: int = 6, max_iter: int = 3,
           tol: float = 0.01, render: RenderCache | None = None,
           trusted: np.ndarray | None = None, band: Band | None = None
           ) -> tuple[Model, Observation | None]:
    """Correct ``c`` and ``b`` so a simulation of the model, fitted like the measurement, gives
    the measured fits.

    Effects bias the per-pixel fit by an amount that depends on how busy the pixel is
    (refractory loses more events of busy pixels, leak adds relatively more to quiet ones), so
    the correction is a curve over pixel activity: pixels are binned by their measured event
    count, and in each bin ``c`` is scaled by the median ratio of the measured to the
    simulated fit (to the power ``1/g``, ``g`` the secant slope of log fitted against log
    model contrast, since under refractory the fit follows the model only in part) and ``b``
    shifted by the median difference. Curves, not per-pixel ratios, so the fit noise of single
    pixels does not enter the maps. Up to ``max_iter`` simulations, until the population
    median agrees within ``tol`` after at least one correction.

    A model whose maps were anchored before (``model.anchored``: an effect added to an
    anchored model, or a parameter changed) is accepted after its first simulation without
    a correction when that agrees within ``2 tol`` in every activity bin, not only in the
    median (an effect that does not move the fit costs one simulation, not two).

    Returns the anchored model (``anchored`` set once a simulation agreed or the maps were
    corrected) and, when the loop ended on a simulation of that very model
    (it agreed), that simulation's observation (with ``trusted``): the workflow counts it as
    the seed's simulation instead of running it again.
    """
    fm = _fit(meas)
    if fm["ok"].sum() < 20:
        return model, None
    bins = _bins(meas, fm["ok"], n_bins)
    nb = int(bins.max()) + 1
    g = 1.0
    prev: tuple[float, float] | None = None  # (log model median c, log sim median c)
    for it in range(max_iter):
        obs = observe(simulate_model(model, rec, seed, settings, render, band),
                      trusted=trusted)
        fs = _fit(obs)
        both = fm["ok"] & fs["ok"]
        if both.sum() < 20:
            return model, obs
        med_s = float(np.median(fs["c"][both]))
        med_m = float(np.median(fm["c"][both]))
        cur = (float(np.log(np.median(model.contrast))), float(np.log(med_s)))
        if prev is not None and abs(cur[0] - prev[0]) > 1e-6:
            g = float(np.clip((cur[1] - prev[1]) / (cur[0] - prev[0]), 0.2, 1.5))
        prev = cur
        if abs(med_s / med_m - 1.0) < tol and (it > 0 or nb == 1):
            return replace(model, anchored=True), obs
        lr = np.zeros(nb)
        db = np.zeros(nb)
        lr_all = float(np.median(np.log(fm["c"][both] / fs["c"][both])))
        for j in range(nb):
            m = both & (bins == j)
            lr[j] = np.median(np.log(fm["c"][m] / fs["c"][m])) if m.sum() >= 10 else lr_all
        k_pix = np.exp(np.clip(lr[bins] / g, -0.7, 0.7)).reshape(model.contrast.shape)
        b_pred = fs["b"] * k_pix.ravel()
        d_all = float(np.median(fm["b"][both] - b_pred[both]))
        for j in range(nb):
            m = both & (bins == j)
            db[j] = np.median(fm["b"][m] - b_pred[m]) if m.sum() >= 10 else d_all
        if it == 0 and model.anchored and abs(med_s / med_m - 1.0) < tol and \
                np.all(np.abs(lr) < 2 * tol) and np.all(np.abs(db) < 2 * tol * med_m):
            return model, obs
        c = np.maximum(model.contrast * k_pix, 1e-3)
        b = np.clip(model.bias * k_pix + db[bins].reshape(model.bias.shape), -0.8 * c, 0.8 * c)
        model = replace(model, contrast=c, bias=b, anchored=True)
    return model, None


# ------------------------------------------------------------------------------ candidates


def _hot_excess(meas: Observation, sims: list[Observation]) -> Any:
    n = meas.n_pixels
    dur = (meas.frame_t_us[-1] - meas.frame_t_us[0]) * 1e-6
    cm = np.bincount(meas.pix, minlength=n).astype(np.float64)
    cs = np.mean([np.bincount(s.pix, minlength=n) for s in sims], axis=0)
    ex = cm - cs
    z = ex / np.sqrt(cs + 1.0 + (0.3 * cs) ** 2)
    return cm, cs, ex, z, dur


def _fit_refractory(meas: Observation, sims: list[Observation], model: Model,
                    rec: Recording) -> Effect | None:
    cm, cs, ex, z, dur = _hot_excess(meas, sims)
    keep = cm <= np.quantile(cm, 0.99)
    iei_m, _, pix_pairs = _iei(meas)
    iei_m = iei_m[keep[pix_pairs]]
    iei_s = np.concatenate([_iei(s)[0] for s in sims])
    if iei_m.size < 50 or iei_s.size < 50:
        return None
    k = max(5, int(1e-4 * iei_m.size))
    p = float(np.partition(iei_m, k)[k])
    if np.mean(iei_s < p) < 2e-3 or p < 2:
        # nothing is missing below the shortest intervals: unless noise events (which a
        # sensor's dead time does not hold back the same way, and which the model may
        # already make) fill them, while the pairs of signal events are missing
        p_def = _refractory_deficit(iei_m, [_iei(s)[0][keep[_iei(s)[2]]] for s in sims])
        if p_def is None:
            return None
        p = p_def
    pile_m = np.mean((iei_m >= p) & (iei_m < 1.05 * p + 2))
    pile_s = np.mean((iei_s >= p) & (iei_s < 1.05 * p + 2))
    mode = "delay" if pile_m > 3 * pile_s + 2e-3 else "drop"
    return Refractory(period_us=round(p, 1), mode=mode)


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
    st = _static(meas)
    if st.sum() < 50:
        return None
    cnt_m = meas.on if pol > 0 else meas.off
    cnt_s = np.mean([(s.on if pol > 0 else s.off) for s in sims], axis=0)
    cm, cs, ex, z, dur = _hot_excess(meas, sims)
    keep = (cm <= np.quantile(cm, 0.99))[None, :] & st
    i_mid = 0.5 * (meas.intensity[1:] + meas.intensity[:-1])
    ws = np.broadcast_to(meas.window_s[:, None], st.shape)
    return (cnt_m - cnt_s)[keep], i_mid[keep], ws[keep]


def _fit_shot_noise(meas: Observation, sims: list[Observation], model: Model,
                    rec: Recording) -> Effect | None:
    # rate(I) = r (ref / I)**e, half of the events of each sign: per exponent on a grid,
    # r by least squares of the still windows' excess counts; the exponent whose fit leaves
    # the least residual (both signs together), r the smaller sign's (a leak adds ON)
    ref = ShotNoise().ref_dn
    parts = []
    for pol in (+1, -1):
        r = _static_excess(meas, sims, pol)
        if r is None:
            return None
        parts.append(r)
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
        return None
    return ShotNoise(rate_hz=round(rate, 4), ref_dn=ref, light_exponent=e)


def _fit_hot_pixels(meas: Observation, sims: list[Observation], model: Model,
                    rec: Recording) -> Effect | None:
    # hot pixels fire when the scene is still: compare per-pixel counts in still windows
    st = _static(meas)
    t_still = (st * meas.window_s[:, None]).sum(0)
    if t_still.max() <= 0:
        return None
    em = ((meas.on + meas.off) * st).sum(0).astype(np.float64)
    es = np.mean([((s.on + s.off) * st).sum(0) for s in sims], axis=0)
    ex = em - es
    z = ex / np.sqrt(es + 1.0 + (0.3 * es) ** 2)
    hot = (z > 5) & (ex > 10.0 * t_still) & (t_still > 0.05 * t_still.max())
    if not hot.any():
        return None
    rate = float(np.median(ex[hot] / t_still[hot]))
    pm = ((meas.on - meas.off) * st).sum(0)[hot].sum()
    ps = np.mean([((s.on - s.off) * st).sum(0)[hot].sum() for s in sims])
    on_frac = float(np.clip(0.5 + 0.5 * (pm - ps) / max(ex[hot].sum(), 1), 0, 1))
    # pixels never still cannot be tested: the fraction is that of the testable ones
    frac = float(hot.sum() / max((t_still > 0.05 * t_still.max()).sum(), 1))
    return HotPixels(fraction=round(frac, 6), rate_hz=round(rate, 3),
                     on_fraction=round(on_frac, 3))


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


def _fit_threshold_noise(meas: Observation, sims: list[Observation], model: Model,
                         rec: Recording) -> Effect | None:
    sm = _threshold_slope(meas)
    ss = np.nanmean([_threshold_slope(s) for s in sims])
    d = sm - ss
    if not np.isfinite(d) or d <= 0:
        return None
    if d > 1.0:
        # no threshold noise (sigma <= 1) makes this much residual: something else does
        return None
    return ThresholdNoise(sigma=round(float(np.sqrt(d)), 4))


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


def _fit_bandwidth(meas: Observation, sims: list[Observation], model: Model,
                   rec: Recording) -> Effect | None:
    grid = np.geomspace(2.0, 2000.0, 19)
    err = np.array([_filter_fit_error(meas, g, model.log_offset) for g in grid])
    i = int(np.argmin(err))
    if i == grid.size - 1:
        return None  # the faster the better: no bandwidth limit visible
    f = float(grid[i])
    if 0 < i:
        x = np.log(grid[i - 1 : i + 2])
        y = err[i - 1 : i + 2]
        den = y[0] - 2 * y[1] + y[2]
        if den > 0:
            f = float(np.exp(x[1] + 0.5 * (x[1] - x[0]) * (y[0] - y[2]) / den))
    return Bandwidth(cutoff_hz=round(f, 3))


def _fit_log_offset(meas: Observation, sims: list[Observation], model: Model,
                    rec: Recording) -> Effect | None:
    cfg = OffEIConfig(window_frames=max(1, min(5, len(rec.frames) // 4)))
    try:
        o, _ = estimate_log_offset(rec, cfg)
    except (CalibrationError, ValueError):
        return None
    if o < 2 * NOMINAL_LOG_OFFSET_DN:
        return None
    return LogOffset(dark_dn=round(float(o), 3))


def _jitter_times(t_us: np.ndarray, sigma_us: float, quantum_us: int,
                  rng: np.random.Generator) -> np.ndarray:
    """Event times (us) with Gaussian jitter ``sigma_us``, then quantised to ``quantum_us``."""
    t = t_us + np.rint(rng.normal(0, sigma_us, t_us.size)).astype(np.int64)
    if quantum_us > 1:
        t = (t // quantum_us) * quantum_us
    return t


def _short_iei_stats(pix: np.ndarray, t_us: np.ndarray) -> dict[str, StatValue]:
    """log10 of the share of same-pixel IEIs below 3, 10, 30, 100, 300 us, and the timestamp
    quantum statistic, of events in any order."""
    x = np.array([3.0, 10.0, 30.0, 100.0, 300.0])
    if t_us.size < 2:
        frac = np.zeros(5)
    else:
        t_rel = t_us - t_us.min()
        if t_rel.max() < 1 << 40:
            # one sort of (pixel, time) packed in an int64 (times up to 12 days)
            key = np.sort((pix.astype(np.int64) << 40) | t_rel)
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
        self.P = f["P"].ravel()
        self.E = f["E"].ravel()
        self.dL = f["dL"].ravel()
        self.w = obs.usable.astype(np.float64).ravel()
        self.nb = SPILL_DL_EDGES.size - 1
        b = np.clip(np.searchsorted(SPILL_DL_EDGES, np.abs(self.dL), side="right") - 1,
                    0, self.nb - 1)
        # (bin, pixel) index of every cell
        self.bp = b * npix + np.tile(np.arange(npix), n_w)
        self.sums = self._cell_sums(np.arange(self.n_cells), self.P, self.E)
        self.count = np.bincount(self.bp, weights=self.w, minlength=self.nb * npix
                                 ).reshape(self.nb, npix)

    def _cell_sums(self, cells: np.ndarray, P: np.ndarray, E: np.ndarray) -> np.ndarray:
        w, y, bp = self.w[cells], self.dL[cells], self.bp[cells]
        terms = (P * P, P * E, E * E, P * y, E * y, E, y * y)
        n = self.nb * self.npix
        return np.stack([np.bincount(bp, weights=w * t, minlength=n) for t in terms]
                        ).reshape(self._N_SUMS, self.nb, self.npix)

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
                inside = cells < self.n_cells
                cells, dp, de = cells[inside], dp[inside], de[inside]
                p0, e0 = self.P[cells], self.E[cells]
                sums = (sums + self._cell_sums(cells, p0 + dp, e0 + de)
                        - self._cell_sums(cells, p0, e0))
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
    g_iei, g_spill = [], []
    for sg in JITTER_GRID_US:
        ts = [_jitter_times(s.t_us, sg, q_hat, rng) for s in sims]
        g_iei.append(discrepancy(m_iei, [_short_iei_stats(s.pix, t)
                                         for s, t in zip(sims, ts, strict=True)]).gap)
        g_spill.append(discrepancy(m_spill, [{"spill_residual": sp.stat(t)}
                                             for sp, t in zip(spills, ts, strict=True)]).gap)
    return np.asarray(g_iei), np.asarray(g_spill)


def _fit_timestamp_jitter(meas: Observation, sims: list[Observation], model: Model,
                          rec: Recording) -> Effect | None:
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
    if int(np.argmin(g_iei)) == 0 and q_hat == 1:
        return None
    sigma = _grid_minimum(JITTER_GRID_US, g_iei)
    s_spill = _grid_minimum(JITTER_GRID_US, g_spill)
    if (g_spill[0] - g_spill.min() > SPILL_MIN_DROP
            and sigma / SPILL_IEI_RATIO <= s_spill <= sigma * SPILL_IEI_RATIO):
        sigma = s_spill
    return TimestampJitter(sigma_us=round(sigma, 2), quantum_us=int(q_hat))


def _fit_timestamp_quantisation(meas: Observation, sims: list[Observation], model: Model,
                                rec: Recording) -> Effect | None:
    """Step and phase from the timestamps that many events share: a frame-driven simulator
    gives the events of a step a few shared times (fractions of the step; the busiest pixel's
    last event, and with ``scheme="end"`` every event, the step's end), so the most crowded
    timestamps lie on a grid. The step is the most common spacing of the crowded timestamps,
    the phase the residue of the most distinct timestamps (each step's end); the effect is
    proposed only if many more measured events than simulated ones lie on that grid."""
    t = meas.t_us
    u, cnt = np.unique(t, return_counts=True)
    if u.size < 50:
        return None
    top = u[cnt >= max(float(np.quantile(cnt, 0.95)), 3.0)]
    d = np.diff(top)
    d = d[(d > 0) & (d <= 1_000_000)]
    if d.size < 10:
        return None
    step = int(np.bincount(d).argmax())
    if step < 2:
        return None
    # every step with events has one at its end, whatever its n_max: the residue shared by
    # the most distinct timestamps
    phase = int(np.bincount(u % step, minlength=step).argmax())
    on_grid = float(np.mean(t % step == phase))
    sim_on_grid = float(np.mean([np.mean(s.t_us % step == phase) for s in sims])) \
        if sims else 1.0 / step
    if on_grid < 5 * sim_on_grid + 0.02:
        return None
    t0 = int(rec.frames.t_us[0])
    return TimestampQuantisation(step_us=float(step), scheme="end" if on_grid > 0.9
                                 else "spread", phase_us=float((phase - t0) % step))


FITTERS = {
    "refractory": _fit_refractory,
    "leak": _events.fit_leak,  # rate and light exponent (evcal.gap.fitters_events)
    "shot_noise": _fit_shot_noise,
    "bandwidth": _fit_bandwidth,
    "threshold_noise": _fit_threshold_noise,
    "hot_pixels": _fit_hot_pixels,
    "log_offset": _fit_log_offset,
    "timestamp_jitter": _fit_timestamp_jitter,
    "timestamp_quantisation": _fit_timestamp_quantisation,
    "aps_fpn": _frames.fit_aps_fpn,  # APS-frame effects: evcal.gap.frames
    "exposure": _frames.fit_exposure,
    "threshold_light": _events.fit_threshold_light,  # event-side effects: .fitters_events
    "row_noise": _events.fit_row_noise,
}


def variants(eff: Effect) -> list[Effect]:
    """``eff`` and the alternatives of its discrete parameters that its moment estimate
    cannot tell apart reliably (the gap workflow evaluates each): a dead time that drops
    crossings or delays them (the pile of intervals just above the period, which tells them
    apart, is blurred where timestamps are quantised)."""
    if isinstance(eff, Refractory):
        other = "drop" if eff.mode == "delay" else "delay"
        return [eff, eff.with_params(mode=other)]
    return [eff]


def fit_candidate(name: str, meas: Observation, sims: list[Observation], model: Model,
                  rec: Recording) -> Effect | None:
    """Moment estimate of effect ``name`` from measured and simulated observations; ``None``
    when the data show none of it (e.g. no excess of events where the effect would add them).
    """
    result: Effect | None = FITTERS[name](meas, sims, model, rec)
    return result
