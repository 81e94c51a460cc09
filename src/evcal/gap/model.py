"""The model the gap workflow grows: per-pixel ``c``, ``b``, a log offset and named effects.

- :func:`fit_base` fits ``c``, ``b`` with OffEI at a given log offset and shrinks each pixel
  towards the population by its standard error, scaled to how much the fits really scatter
  on the recording (:func:`noise_scale`; so estimation noise does not read as fixed pattern
  in the simulation).
- :func:`simulate_model` re-simulates a measured recording under a model, driven by its frames
  (dithered by the frame noise the frames carry: quantisation and read noise, so the
  simulated events disagree with the frames as much as real ones do).
- :func:`anchor` rescales ``c`` and shifts ``b`` so that a simulation of the model, fitted the
  same way as the measurement, gives the measured population values (effects such as leak or
  refractory bias the fit; the anchor undoes that bias for the model as a whole).

The candidate effects and their fitters are in :mod:`evcal.gap.effects` (the registry).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from ..calibration import Calibration
from ..errors import CalibrationError, ConfigError
from ..events import SensorSize
from ..offline import OffEIConfig, offei
from ..online import usable_cores
from ..recording import Frames, Recording
from ..sim.effects import Effect, Exposure
from ..sim.ideal import SimConfig
from ..sim.nonideal import simulate
from ..sim.sources import FrameInterpolator
from ..splithalf import CHI2_1_MEDIAN
from .motion import SubframeShift, estimate_shift
from .pixelfit import MIN_FIT_EVENTS
from .render import RenderCache, frames_key
from .stats import NOMINAL_LOG_OFFSET_DN, Observation, _fit, block_fit, observe

if TYPE_CHECKING:
    from .flow import FlowInterpolator

_log = logging.getLogger("evcal.gap")


@dataclass(frozen=True, kw_only=True)
class NoiseScale:
    """How much more (``> 1``) or less OffEI's per-pixel ``c`` and ``b`` scatter about the
    truth on a recording than their stated standard errors say: factors on the stated
    variances, measured by :func:`noise_scale`; ``reason`` says why they are 1 by default
    (too few pixels to measure them on)."""

    contrast: float = 1.0
    bias: float = 1.0
    n_pixels: int = 0
    reason: str = ""


@dataclass(frozen=True)
class Model:
    contrast: np.ndarray
    bias: np.ndarray
    log_offset: float
    effects: dict[str, Effect] = field(default_factory=dict)
    # the maps were corrected by :func:`anchor` (an effect added to such a model, or a
    # parameter changed, keeps them: anchoring it again may take one simulation, not two)
    anchored: bool = False
    # the factors on the stated variances of the base fit (:func:`noise_scale`)
    noise_scale: NoiseScale = field(default_factory=NoiseScale)

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
    # the image's motion off the straight path between frames, read from the measured
    # events (evcal.gap.motion; flow interpolation only); None: the straight path
    shift: SubframeShift | None = None

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


# below this many pixels fitted in the simulations the stated errors are taken as they are
MIN_SCALE_PIXELS = 200
# the factors are clamped here (beyond, the simulations say more about themselves than about
# the errors)
NOISE_SCALE_RANGE = (0.25, 16.0)
# seeds of the simulations that measure the noise scale (none of the workflow's)
NOISE_SEEDS = (9001, 9002)
# the shrinkage moves each polarity's threshold ``c + b``, ``c - b`` at most this many of its
# standard errors away from the fit (limited translation): only a threshold the fit measures
# far more precisely than the population's spread, far from the population, is held
THRESHOLD_LIMIT_SE = 3.0
# a pixel's bias is kept within this share of its threshold: both polarities' thresholds
# stay above 5 % of ``c``, positive but as lopsided as the fit finds them (a pixel whose OFF
# threshold is a twentieth of its ON one fires a burst at every falling edge)
MAX_BIAS_RATIO = 0.95


def noise_scale(rec: Recording, config: OffEIConfig, cal: Calibration, model: Model, *,
                settings: SimSettings | None = None, render: RenderCache | None = None,
                seeds: tuple[int, ...] = NOISE_SEEDS) -> NoiseScale:
    """The factors by which the stated variances of OffEI's ``c``, ``b`` (``cal``, fitted on
    ``rec`` with ``config``, a numeric log offset) fall short of the fits' real scatter on
    this recording.

    ``rec`` is simulated under ``model`` (its base model: ``c``, ``b`` known) with each of
    ``seeds`` and fitted like ``cal``; over the pixels valid in ``cal`` and the fit,
    ``z = (x_fit - x - median(x_fit - x)) / se`` (the median takes out the fit's bias on the
    population, which is no pixel's noise) and ``f = median(z^2) / 0.4549``, the median of a
    chi-square with one degree of freedom (robust to the pixels the fit does not describe).
    Clamped to :data:`NOISE_SCALE_RANGE`; 1 with fewer than :data:`MIN_SCALE_PIXELS` pixels.

    The errors' scale then does not matter to the shrinkage: on road.aedat4 (27 events per
    valid pixel, 59 frames) OffEI's errors of evcal.solver.overlap_standard_errors give
    f = 3.5 / 3.3 (c / b; they understate there), the older ``d sigma^2 G^-1`` errors, about
    twice as large, 1.1 / 0.9; both shrink alike. Not the scatter between two halves of the
    recording: on road no pixel is valid in both halves, and where there are many, a pixel's
    error common to both halves cancels (on the ideal simulator ``f`` 0.58 / 0.74 with
    errors whose ``std(z)`` is 0.99 / 0.98)."""
    settings = settings or SimSettings(read_noise_dn=estimate_read_noise(rec.frames))
    def fitted(seed: int) -> Calibration | None:
        try:
            return offei(simulate_model(model, rec, seed, settings, render), config)
        except CalibrationError:
            return None

    with ThreadPoolExecutor(max_workers=max(1, min(len(seeds), usable_cores()))) as pool:
        fits = list(pool.map(fitted, seeds))
    zc: list[np.ndarray] = []
    zb: list[np.ndarray] = []
    for fit in fits:
        if fit is None:
            continue
        ok = fit.valid & cal.valid & (fit.stderr_contrast > 0) & (fit.stderr_bias > 0)
        ok &= np.isfinite(fit.stderr_contrast) & np.isfinite(fit.stderr_bias)
        for z, x, x_fit, se in ((zc, model.contrast, fit.contrast, fit.stderr_contrast),
                                (zb, model.bias, fit.bias, fit.stderr_bias)):
            dx = x_fit[ok].astype(np.float64) - x[ok]
            z.append((dx - np.median(dx)) / se[ok] if dx.size else dx)
    n = sum(z.size for z in zc)
    if n < MIN_SCALE_PIXELS:
        return NoiseScale(n_pixels=n, reason=f"{n} pixels fitted in the simulations")

    def factor(z: list[np.ndarray]) -> float:
        f = np.median(np.concatenate(z) ** 2) / CHI2_1_MEDIAN
        return float(np.clip(f, *NOISE_SCALE_RANGE))

    return NoiseScale(contrast=factor(zc), bias=factor(zb), n_pixels=n)


def _shrink(cal: Calibration, offset: float, scale: NoiseScale | None = None
            ) -> tuple[np.ndarray, np.ndarray]:
    """``c``, ``b`` of ``cal`` shrunk towards the population median, each pixel by
    ``k = 1 - f se^2 / var_obs`` (``var_obs`` the population's robust variance, ``f`` the
    recording's :class:`NoiseScale`, the stated errors rescaled to the fits' scatter), then
    each polarity's threshold (``c + b``, ``c - b``) kept within
    :data:`THRESHOLD_LIMIT_SE` of its own standard error of the fit, from the errors'
    correlation that OffEI states (``diagnostics.error_correlation``; without it, no limit).

    The limit is for a pixel whose events are nearly all of one polarity: its errors of ``c``
    and ``b`` are large and nearly equal, so each is shrunk much, while the threshold it fires
    at is measured well, and shrinking ``c`` and ``b`` each on its own moves that threshold
    far from what its events say. On the v2e mix on gravel the busiest pixel's OFF threshold
    (v2e's floor, 0.010; OffEI 0.011 with a standard error under 0.001) became 0.043, and a
    frame-driven simulator's slots and dead-time backlog follow that pixel (docs/GAP.md)."""
    if scale is None:
        scale = NoiseScale()
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
    var_c = scale.contrast * se_c**2  # the errors' variances scaled to the fits' scatter
    var_b = scale.bias * se_b**2
    kc = np.clip(1 - var_c / max(cv, 1e-12), 0, 1)
    kb = np.clip(1 - var_b / max(bv, 1e-12), 0, 1)
    c_fit, b_fit = c, b
    c = np.where(v, cm + kc * (c - cm), cm)
    b = np.where(v, bm + kb * (b - bm), bm)
    rho_map = getattr(cal.diagnostics, "error_correlation", None)
    if rho_map is not None:
        rho = np.nan_to_num(np.asarray(rho_map, np.float64).reshape(c.shape), nan=0.0)
        cov = rho * np.sqrt(var_c * var_b)
        on_off = []
        for sign in (1.0, -1.0):
            fit = c_fit + sign * b_fit
            se = np.sqrt(np.maximum(var_c + var_b + 2 * sign * cov, 0.0))
            lim = THRESHOLD_LIMIT_SE * se
            on_off.append(np.clip(c + sign * b, fit - lim, fit + lim))
        c = np.where(v, 0.5 * (on_off[0] + on_off[1]), c)
        b = np.where(v, 0.5 * (on_off[0] - on_off[1]), b)
    c = np.maximum(c, 0.3 * cm)
    b = np.clip(b, -MAX_BIAS_RATIO * c, MAX_BIAS_RATIO * c)
    return c, b


# the seed of the draw that spreads the base model's maps (:func:`_spread`): one fixed draw,
# so a recording's base model is the same on every run
SPREAD_SEED = 20261129


def _spread(c: np.ndarray, b: np.ndarray, cal: Calibration, scale: NoiseScale
            ) -> tuple[np.ndarray, np.ndarray]:
    """``c``, ``b`` (shrunk, :func:`_shrink`) plus one draw of what the shrinkage does not
    know of each pixel: a normal deviate of the posterior's variance ``tau^2 v / (tau^2 + v)``
    (``v`` the pixel's scaled error variance; ``tau^2`` the population's spread, the valid
    estimates' robust variance less their median error variance), ``tau^2`` for a pixel
    without a valid fit.

    Shrunk maps are narrower than the sensor's: every pixel without a fit holds the same
    threshold. A sensor's pixels of different thresholds fire at different times and rates
    (a still pixel's rate goes as one over its threshold, so a spread raises the mean rate),
    and the fits of its simulation scatter as the measured fits do; pixels of one threshold
    fire together wherever the light changes alike."""
    v = cal.valid
    if v.sum() < 10:
        return c, b
    rng = np.random.default_rng(SPREAD_SEED)
    out = []
    for x, est, se, f in ((c, cal.contrast, cal.stderr_contrast, scale.contrast),
                          (b, cal.bias, cal.stderr_bias, scale.bias)):
        e = est[v].astype(np.float64)
        robust = (1.4826 * np.median(np.abs(e - np.median(e)))) ** 2
        var = f * np.where(np.isfinite(se), se, np.inf).astype(np.float64) ** 2
        noise = float(np.median(var[v][np.isfinite(var[v])])) if np.isfinite(var[v]).any() \
            else 0.0
        tau2 = max(robust - noise, 0.05 * robust)
        with np.errstate(invalid="ignore", divide="ignore"):
            post = np.where(v & np.isfinite(var), tau2 * var / (tau2 + var), tau2)
        out.append(x + np.sqrt(post) * rng.standard_normal(x.shape))
    cm = float(np.median(c[v]))
    c2 = np.maximum(out[0], 0.3 * cm)
    b2 = np.clip(out[1], -MAX_BIAS_RATIO * c2, MAX_BIAS_RATIO * c2)
    return c2, b2


def fit_base(rec: Recording, log_offset: float = NOMINAL_LOG_OFFSET_DN, *,
             settings: SimSettings | None = None, render: RenderCache | None = None) -> Model:
    """``c``, ``b`` by OffEI at ``log_offset``, each pixel shrunk towards the population by its
    standard errors scaled to the recording (:func:`noise_scale`, on the model as
    ``noise_scale``; ``settings`` and ``render`` are those of its simulations)."""
    n_f = len(rec.frames)
    cfg = OffEIConfig(window_frames=max(1, min(5, n_f // 4)), log_offset=float(log_offset))
    scale = NoiseScale(reason="the fit failed")
    try:
        cal = offei(rec, cfg)
        # the scale's simulations run on the maps shrunk by the stated errors
        c, b = _shrink(cal, log_offset)
        scale = noise_scale(rec, cfg, cal, Model(c, b, float(log_offset)), settings=settings,
                            render=render)
        c, b = _spread(*_shrink(cal, log_offset, scale), cal, scale)
    except CalibrationError:
        c = np.full(rec.sensor.shape, 0.15)
        b = np.zeros(rec.sensor.shape)
    _log.info("base model at log offset %.3g DN: standard errors' variance scaled by %.3g "
              "(c), %.3g (b) from %d pixels %s", log_offset, scale.contrast, scale.bias,
              scale.n_pixels, scale.reason)
    return Model(c, b, float(log_offset), noise_scale=scale)


def light_gain(images: np.ndarray) -> np.ndarray:
    """Per frame, the factor the light common to the whole scene has changed by since the
    first frame (``[K]``, the first 1): the cumulative product of each frame's median ratio
    to the previous one over the pixels lit well inside the range in both (10..245 DN). A
    moving scene brightens as many pixels as it darkens (median ratio 1); a light that
    ramps, breathes or flickers scales them all."""
    f = images.reshape(images.shape[0], -1).astype(np.float32)
    k = f.shape[0]
    log_r = np.zeros(k)
    for i in range(1, k):
        a, b = f[i - 1], f[i]
        lit = (a > 10) & (a < 245) & (b > 10) & (b < 245)
        if lit.sum() >= 100:
            log_r[i] = float(np.median(np.log(b[lit]) - np.log(a[lit])))
    out: np.ndarray = np.exp(np.cumsum(log_r))
    return out


GAIN_SMOOTH_FRAMES = 7  # the window of the local quadratic that smooths the common light


def smooth_gain(gain: np.ndarray) -> np.ndarray:
    """``gain`` (:func:`light_gain`) smoothed by a local quadratic in its log over
    :data:`GAIN_SMOOTH_FRAMES` frames (Savitzky-Golay): a ramp or a light breathing at a
    few Hz passes, a flicker faster than the frames (mains at 100 Hz, which each frame's
    exposure samples at another phase) does not: the frames cannot say how the light went
    between them."""
    lg = np.log(np.asarray(gain, np.float64))
    k = lg.size
    half = GAIN_SMOOTH_FRAMES // 2
    if k < GAIN_SMOOTH_FRAMES:
        return np.asarray(gain, np.float64)
    out = np.empty(k)
    idx = np.arange(k)
    for i in range(k):
        lo = min(max(i - half, 0), k - GAIN_SMOOTH_FRAMES)
        x = idx[lo:lo + GAIN_SMOOTH_FRAMES] - i
        coef = np.polyfit(x, lg[lo:lo + GAIN_SMOOTH_FRAMES], 2)
        out[i] = coef[-1]
    result: np.ndarray = np.exp(out)
    return result


def latent_frames(frames: Frames, read_noise_dn: float) -> np.ndarray:
    """The frames as float32 latent intensity, their read noise taken out where a pixel is
    still: each pixel's frames, divided by the light common to the scene
    (:func:`light_gain`), are cut into runs within which every frame lies within the noise
    (``3 read_noise_dn + 1`` DN) of the run's least-squares line so far; a run is replaced by
    its line (the scene is still there; the noise is in the frames, not in the light the
    events saw), and the common light is put back, smoothed (:func:`smooth_gain`: a flicker
    the frames alias is not the light between them). A pixel that changes makes runs of one
    frame: its frames are kept as they are. The line's slope is kept only where it stands
    out of the noise and stays below half the tolerance a frame: a drift the frames cannot
    tell from their noise frame to frame (part of the scene dimming or brightening apart
    from the common light, a smooth patch that moves slowly) still makes a sensor fire.

    Without the runs a still pixel's frames (or a short moving mean of them) carry the noise
    into the simulation, whose events then follow it: on a DAVIS346 recording of a still
    scene (1 DN read noise) the simulated still pixels fired 5x the measured rate, the dark
    ones most. Without the common light taken out first, a slow change of the light (a ramp
    of a few DN a frame) made runs too, and the simulated still pixels never fired where a
    sensor fires all the time the light changes. With a run's mean in place of its line,
    a drift below the tolerance became steps: under a breathing light, a model with the
    sensor's true maps fired fewer events than the sensor in its still pixels, and those in
    bursts at the steps."""
    imgs = frames.images.astype(np.float32)
    if read_noise_dn <= 0.5 or imgs.shape[0] < 3:
        return imgs
    tol = 3.0 * read_noise_dn + 1.0
    k = imgs.shape[0]
    raw_gain = light_gain(imgs)
    gain = raw_gain.astype(np.float32)
    back = smooth_gain(raw_gain).astype(np.float32)
    f = imgs.reshape(k, -1) / gain[:, None]
    # a pass forward over the frames (vectorised over pixels) keeps each run's least-squares
    # line so far (its sums over the run, frame index j from the run's start), one backward
    # gives every frame its run's final line
    npix = f.shape[1]
    a_so_far = np.empty(f.shape, np.float32)  # the line's value at the run's start
    s_so_far = np.zeros(f.shape, np.float32)  # its slope, DN a frame
    start = np.zeros(f.shape, np.int32)
    joins = np.zeros(f.shape, bool)  # frame i continues the run of frame i - 1
    n = np.ones(npix)
    sj = np.zeros(npix)
    sf = f[0].astype(np.float64)
    sjf = np.zeros(npix)
    sjj = np.zeros(npix)
    sff = sf * sf
    st = np.zeros(npix, np.int32)
    a, slope = sf.copy(), np.zeros(npix)
    a_so_far[0] = a
    for i in range(1, k):
        j = i - st
        fi = f[i].astype(np.float64)
        inside = np.abs(fi - (a + slope * j)) < tol
        joins[i] = inside
        n = np.where(inside, n + 1, 1.0)
        sj = np.where(inside, sj + j, 0.0)
        sf = np.where(inside, sf + fi, fi)
        sjf = np.where(inside, sjf + j * fi, 0.0)
        sjj = np.where(inside, sjj + j * j, 0.0)
        sff = np.where(inside, sff + fi * fi, fi * fi)
        st = np.where(inside, st, i).astype(np.int32)
        det = n * sjj - sj * sj
        with np.errstate(divide="ignore", invalid="ignore"):
            slope = np.where(det > 0, (n * sjf - sj * sf) / np.where(det > 0, det, 1.0), 0.0)
        # a run follows a drift the frames cannot tell from their noise frame to frame (a
        # still pixel under a slow light, a smooth patch of a scene that moves slowly:
        # a sensor fires all the while); a faster change is motion, kept frame by frame
        slope = np.clip(slope, -0.5 * tol, 0.5 * tol)
        # ... and only where the drift stands out of the noise (three standard errors, the
        # noise the larger of the read noise and the run's own scatter about its line): a
        # slope read off noisy frames would break a still pixel's run or make it fire
        spread = np.maximum(sjj - sj * sj / n, 0.0)
        rss = np.maximum(sff - sf * sf / n - slope * (sjf - sj * sf / n), 0.0)
        var = np.maximum(read_noise_dn ** 2, np.where(n > 3, rss / np.maximum(n - 2, 1), 0.0))
        slope = np.where(slope * slope * spread > 9.0 * var, slope, 0.0)
        a = (sf - slope * sj) / n
        a_so_far[i], s_so_far[i], start[i] = a, slope, st
    out = np.empty(f.shape, np.float32)
    # a pixel that changed (a run of one frame) keeps its frame as it is
    single = np.ones(f.shape, bool)
    single[1:] &= ~joins[1:]
    single[:-1] &= ~joins[1:]
    la, ls, lst = a_so_far[k - 1].copy(), s_so_far[k - 1].copy(), start[k - 1].copy()
    out[k - 1] = (la + ls * (k - 1 - lst)) * back[k - 1]
    for i in range(k - 2, -1, -1):
        keep = joins[i + 1]
        la = np.where(keep, la, a_so_far[i])
        ls = np.where(keep, ls, s_so_far[i])
        lst = np.where(keep, lst, start[i])
        out[i] = (la + ls * (i - lst)) * back[i]
    out = np.where(single, imgs.reshape(k, -1), out)
    return out.reshape(imgs.shape)


def _times(frames: Frames, internal_rate_hz: float) -> np.ndarray:
    ft = frames.t_us - frames.t_us[0]
    end = int(ft[-1])
    grid = np.rint(np.arange(0, end * 1e-6 * internal_rate_hz + 1) * 1e6 / internal_rate_hz)
    grid = grid[grid <= end].astype(np.int64)
    return np.unique(np.concatenate([grid, ft]))


_RUNNING_LOCK = threading.Lock()
_running = 0  # simulations of models under way in this process


@contextmanager
def _cores_free() -> Iterator[int]:
    """While a simulation runs: the cores no other simulation had when it started (at least
    one). A simulation alone (an anchor's, the workflow's sequential steps) splits its pixels
    over the idle cores; side by side, each keeps to its own."""
    global _running
    with _RUNNING_LOCK:
        others = _running
        _running += 1
    try:
        yield max(1, usable_cores() - others)
    finally:
        with _RUNNING_LOCK:
            _running -= 1


def flow_source(drive: Frames, measured: Frames, settings: SimSettings,
                shape: tuple[int, int], shift: SubframeShift | None) -> FlowInterpolator:
    """The light between the frames ``drive`` (a model's frames of the ``measured`` ones)
    along the optical flow. The motion is the scene's: the flow of the measured frames
    serves every model (a dark-offset map subtracted from the frames would otherwise cost a
    flow of its own per candidate, for the same motion); the frames' exposure blur along it
    is taken out, as the events saw the light sharp."""
    from .flow import FlowInterpolator, deblurred  # noqa: PLC0415

    flow_images = measured.images.astype(np.float32)
    latent = deblurred(latent_frames(drive, settings.read_noise_dn), measured.t_us,
                       measured.exposure_us, flow_images)
    return FlowInterpolator(Frames(drive.t_us, latent, drive.exposure_us), shape,
                            t_origin_us=int(measured.t_us[0]), flow_images=flow_images,
                            shift=shift)


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
        if settings.interpolation == "flow":
            return flow_source(drive, fr, settings, shape, settings.shift)
        latent = Frames(drive.t_us, latent_frames(drive, settings.read_noise_dn),
                        drive.exposure_us)
        return FrameInterpolator(latent, shape, t_origin_us=t0)

    cache = render if render is not None else RenderCache(max_bytes=0)
    key = frames_key(drive, settings.interpolation, times)
    if settings.shift is not None and settings.interpolation == "flow":
        key += settings.shift.digest()
    src = cache.source(key, times, shape, make_source, add,
                       rows=None if band is None else band.rows, lag_s=lag_us * 1e-6)
    dur = max(times[-1] * 1e-6, 1e-3)
    h, w = shape if band is None else band.rec.sensor.shape
    cfg = SimConfig(height=h, width=w, duration_s=dur, frame_rate_hz=1.0,
                    internal_rate_hz=max(settings.internal_rate_hz, 1.0),
                    log_offset=model.log_offset, seed=int(seed))
    expected = rec.n_events if band is None else band.rec.n_events
    with _cores_free() as threads:
        res = simulate(cfg, model.effects, source=src, maps=(model.contrast, model.bias),
                       frames=fr if band is None else band.rec.frames, times_us=times,
                       t_origin_us=t0, expected_events=expected, threads=threads)
    return res.recording


# OffEI's valid pixels that the sensor's typical thresholds are read from (fewer: the
# population of the per-window fit)
SHIFT_MIN_VALID = 200


def subframe_shift(rec: Recording, settings: SimSettings, population: tuple[float, float]
                   ) -> tuple[SubframeShift, dict[str, float]]:
    """The image's motion between the frames off the flow interpolation's straight path,
    read from ``rec``'s events (:mod:`evcal.gap.motion`) with the sensor's typical
    thresholds: the median of OffEI's valid pixels at the nominal offset (the base model's
    fit, in the log intensity the shift is read in), or ``population`` (the statistics'
    fit) where OffEI has fewer than :data:`SHIFT_MIN_VALID`; on the latent frames every
    model's light starts from."""
    fr = rec.frames
    assert fr is not None
    contrast, bias = population
    try:
        cal = offei(rec, OffEIConfig(window_frames=max(1, min(5, len(fr) // 4)),
                                     log_offset=NOMINAL_LOG_OFFSET_DN))
        if int(cal.valid.sum()) >= SHIFT_MIN_VALID:
            contrast = float(np.median(cal.contrast[cal.valid]))
            bias = float(np.median(cal.bias[cal.valid]))
    except CalibrationError:
        pass
    if not (np.isfinite(contrast) and contrast > 0 and np.isfinite(bias)):
        # no pixel fits: nothing to read the events' steps in
        return SubframeShift(np.zeros(0, np.int64), np.zeros((0, 2), np.float32)), {}
    interp = flow_source(fr, fr, settings, rec.sensor.shape, None)
    ev = rec.events
    return estimate_shift(interp, ev["t_us"], ev["x"], ev["y"], ev["p"], contrast=contrast,
                          bias=bias, log_offset=NOMINAL_LOG_OFFSET_DN)


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


# the windows whose events the unfitted pixels' thresholds are matched on: a pixel's
# frames change there (not still, :func:`.stats._static`) by at least COUNT_MATCH_MIN_DL
# (log units; about a threshold: the events there are the change's, not noise's, which
# fires in every window alike) and at most COUNT_MATCH_MAX_DL: a change this slow is
# followed by every pixel whatever its photoreceptor's bandwidth or dead time, so the count
# says what the thresholds are and not what loses events on fast edges
COUNT_MATCH_MIN_DL = 0.15
COUNT_MATCH_MAX_DL = 0.6
# the unfitted pixels' events of each polarity in those windows that a match needs
COUNT_MATCH_MIN_EVENTS = 300


def _counted(meas: Observation) -> np.ndarray:
    """``[n_w, N]`` windows whose events the count match uses (see
    :data:`COUNT_MATCH_MAX_DL`); the frames' alone, so the same for each simulation."""
    from .stats import _dl, _shared, _static  # noqa: PLC0415

    def make() -> np.ndarray:
        dl = np.abs(_dl(meas))
        out: np.ndarray = meas.usable & ~_static(meas) & (dl >= COUNT_MATCH_MIN_DL) & \
            (dl <= COUNT_MATCH_MAX_DL)
        return out

    out: np.ndarray = _shared(meas, "count_match_windows", make)
    return out


def _quiet(meas: Observation) -> np.ndarray:
    """The pixels without a fit for want of events (flat): those the count match is for. A
    pixel that fires plenty but fits badly (one polarity only, say) is not among them: its
    count would pull the quiet pixels' thresholds."""
    out: np.ndarray = ~block_fit(meas)["ok"] & ((meas.on + meas.off).sum(0) < MIN_FIT_EVENTS)
    return out


def _unfitted_counts(obs: Observation, counted: np.ndarray, unfit: np.ndarray
                     ) -> tuple[float, float]:
    """ON and OFF events of the ``unfit`` pixels in the ``counted`` windows."""
    w = counted & unfit[None, :]
    return float(obs.on[w].sum()), float(obs.off[w].sum())


def anchor(model: Model, rec: Recording, meas: Observation, seed: int,
           settings: SimSettings, *, n_bins: int = 6, max_iter: int = 3,
           tol: float = 0.01, render: RenderCache | None = None,
           trusted: np.ndarray | None = None, band: Band | None = None
           ) -> tuple[Model, Observation | None]:
    """Correct ``c`` and ``b`` so a simulation of the model, fitted like the measurement, gives
    the measured fits, and fires as many events as the measurement where the fit cannot say.
    The fit is over windows of several frames (:func:`.stats.block_fit`): over single frame
    intervals a slow change makes the fit blind to the thresholds.

    Effects bias the per-pixel fit by an amount that depends on how busy the pixel is
    (refractory loses more events of busy pixels, leak adds relatively more to quiet ones), so
    the correction is a curve over pixel activity: pixels are binned by their measured event
    count, and in each bin ``c`` is scaled by the median ratio of the measured to the
    simulated fit (to the power ``1/g``, ``g`` the secant slope of log fitted against log
    model contrast, since under refractory the fit follows the model only in part) and ``b``
    shifted by the median difference. Curves, not per-pixel ratios, so the fit noise of single
    pixels does not enter the maps.

    Pixels without a measured fit hold the population's threshold. Where those too quiet for
    one (:func:`_quiet`) fire at least :data:`COUNT_MATCH_MIN_EVENTS` of each polarity in
    windows of a change between :data:`COUNT_MATCH_MIN_DL` and :data:`COUNT_MATCH_MAX_DL`,
    each polarity's threshold ``c +- b`` of theirs is scaled
    by the ratio of the simulated to the measured count there (events go as one over the
    threshold): on a sparse recording (a few events per pixel, none fitted) the fit's
    default threshold is no sensor's, and the events it makes the model fire too many or
    too few leave a gap no effect can close. Otherwise they take the population's correction
    (the median over every pixel fitted in both), not that of the least active bin: that
    bin's fits are the pixels that barely passed the fit's minimum of events, on a sparse
    recording a few hundred of them against the whole sensor's unfitted pixels. Up to ``max_iter``
    simulations (one more where counts are matched), until the population median agrees
    within ``tol`` after at least one correction and the counts within their own noise.

    A model whose maps were anchored before (``model.anchored``: an effect added to an
    anchored model, or a parameter changed) is accepted after its first simulation without
    a correction when that agrees within ``2 tol`` in every activity bin, not only in the
    median, and in the counts (an effect that does not move the fit costs one simulation,
    not two).

    Returns the anchored model (``anchored`` set once a simulation agreed or the maps were
    corrected) and, when the loop ended on a simulation of that very model
    (it agreed), that simulation's observation (with ``trusted``): the workflow counts it as
    the seed's simulation instead of running it again.
    """
    fm = block_fit(meas)
    fitted = fm["ok"].sum() >= 20
    unfit = _quiet(meas)
    counted = _counted(meas)
    n_meas = _unfitted_counts(meas, counted, unfit)
    match = min(n_meas) >= COUNT_MATCH_MIN_EVENTS
    if not (fitted or match):
        return model, None
    # the counts agree within twice their Poisson noise (and at least 3 %)
    count_tol = max(0.03, 2.0 / np.sqrt(min(n_meas))) if match else np.inf
    bins = _bins(meas, fm["ok"], n_bins) if fitted else np.zeros(unfit.size, np.int64)
    nb = int(bins.max()) + 1
    g = 1.0
    prev: tuple[float, float] | None = None  # (log model median c, log sim median c)
    # per polarity: (log median threshold, log count ratio) of the last simulation, exponent
    secant: list[tuple[float, float] | None] = [None, None]
    gamma = [1.0, 1.0]
    for it in range(max_iter + int(match)):
        obs = observe(simulate_model(model, rec, seed, settings, render, band),
                      trusted=trusted)
        ratio = (1.0, 1.0)
        if match:
            n_sim = _unfitted_counts(obs, counted, unfit)
            ratio = (max(n_sim[0], 1.0) / n_meas[0], max(n_sim[1], 1.0) / n_meas[1])
        counts_agree = max(abs(np.log(r)) for r in ratio) < np.log1p(count_tol)
        _log.debug("anchor, simulation %d: unfitted pixels' ON, OFF events %.3g, %.3g of the "
                   "measured", it + 1, *ratio)
        fs = block_fit(obs)
        both = fm["ok"] & fs["ok"]
        fit_agree = True
        if fitted and both.sum() >= 20:
            med_s = float(np.median(fs["c"][both]))
            med_m = float(np.median(fm["c"][both]))
            # the fitted pixels' own median: the unfitted ones move by their counts
            cur = (float(np.log(np.median(model.contrast.ravel()[fm["ok"]]))),
                   float(np.log(med_s)))
            if prev is not None and abs(cur[0] - prev[0]) > 1e-6:
                g = float(np.clip((cur[1] - prev[1]) / (cur[0] - prev[0]), 0.2, 1.5))
            prev = cur
            fit_agree = abs(med_s / med_m - 1.0) < tol and (it > 0 or nb == 1)
        elif fitted:
            if not match:
                return model, obs
            fitted = False  # the simulation fits too few pixels: counts alone from here
        if fit_agree and counts_agree and (it > 0 or nb == 1 or not fitted):
            return replace(model, anchored=True), obs
        c = model.contrast.copy()
        b = model.bias.copy()
        if fitted and not fit_agree:
            lr = np.zeros(nb)
            db = np.zeros(nb)
            lr_all = float(np.median(np.log(fm["c"][both] / fs["c"][both])))
            for j in range(nb):
                m = both & (bins == j)
                lr[j] = np.median(np.log(fm["c"][m] / fs["c"][m])) if m.sum() >= 10 \
                    else lr_all
            lr_pix = np.where(fm["ok"], lr[bins], lr_all)
            k_pix = np.exp(np.clip(lr_pix / g, -0.7, 0.7)).reshape(model.contrast.shape)
            b_pred = fs["b"] * k_pix.ravel()
            d_all = float(np.median(fm["b"][both] - b_pred[both]))
            for j in range(nb):
                m = both & (bins == j)
                db[j] = np.median(fm["b"][m] - b_pred[m]) if m.sum() >= 10 else d_all
            db_pix = np.where(fm["ok"], db[bins], d_all)
            if it == 0 and model.anchored and counts_agree and \
                    abs(med_s / med_m - 1.0) < tol and np.all(np.abs(lr) < 2 * tol) and \
                    np.all(np.abs(db) < 2 * tol * med_m):
                return model, obs
            c = np.maximum(model.contrast * k_pix, 1e-3)
            b = model.bias * k_pix + db_pix.reshape(model.bias.shape)
        if match:
            # the unfitted pixels' thresholds by the count ratio, each polarity its own
            # (the count goes as the threshold to a power -gamma, gamma measured by the
            # secant over the simulations so far: a pixel crosses a few thresholds, so a
            # count falls faster than one over its threshold)
            u = unfit.reshape(c.shape)
            th = [model.contrast[u] + model.bias[u], model.contrast[u] - model.bias[u]]
            s_pol = []
            for k in range(2):
                now = (float(np.log(np.median(th[k]))), float(np.log(ratio[k])))
                last = secant[k]
                if last is not None and abs(now[0] - last[0]) > 1e-3:
                    gamma[k] = float(np.clip((last[1] - now[1]) / (now[0] - last[0]), 0.5, 3.0))
                secant[k] = now
                s_pol.append(float(np.clip(ratio[k] ** (1.0 / gamma[k]), 1 / 3, 3.0)))
            s_on, s_off = s_pol
            th_on = (model.contrast + model.bias) * s_on
            th_off = (model.contrast - model.bias) * s_off
            c = np.where(u, np.maximum(0.5 * (th_on + th_off), 1e-3), c)
            b = np.where(u, 0.5 * (th_on - th_off), b)
        b = np.clip(b, -MAX_BIAS_RATIO * c, MAX_BIAS_RATIO * c)
        model = replace(model, contrast=c, bias=b, anchored=True)
    return model, None
