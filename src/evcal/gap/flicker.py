"""The scene's flicker (:class:`evcal.sim.effects.Flicker`) in the gap workflow: its
frequency read off the spectrum of the events' net polarity and refined against simulations,
its depth and phase matched by simulation.

A lamp on the mains flickers at twice its frequency (100 or 120 Hz). The frames cannot show
it: each averages the light over its exposure at another phase of the flicker (they alias
it), and the workflow's simulations, driven by the frames, have none. The events follow it:
every pixel whose log intensity is near one of its thresholds fires in step with the light,
ON on its rise and OFF on its fall, so the sensor's count of ON minus OFF events carries a
line at the flicker's frequency that no motion seen at 20-30 frames a second makes.

The line's complex amplitude does not say the depth by itself (how many pixels sit near a
threshold depends on the scene, the motion and the thresholds), so the fitter simulates the
current model with a flicker and moves its depth and phase until the simulated line has the
measured amplitude and phase: the phase by the angle between them, the depth by their ratio
(to a power measured by the secant, since pixels join the flicker's rhythm faster than in
proportion once it spans their thresholds). The frequency of the spectrum's peak is off by a
few hundredths of a hertz where the line swells and fades with the motion (its phase drifts
by a radian over a 3 s recording): each simulation also gives the drift of the measured
line's phase against the simulated one's, segment by segment, where the shared swelling
cancels (:func:`frequency_error`).
"""

from __future__ import annotations

import numpy as np

from ..sim.effects import Flicker
from .effects import FitContext, FitResult, Fitted, NoEvidence
from .stats import Observation

# the frequencies searched (Hz): above any motion the frames follow, below what the
# simulations' internal rate (1 kHz) samples with four steps a cycle
FLICKER_BAND_HZ = (40.0, 250.0)
# the bins of the net polarity's count (us): 2 kHz, above twice the band's top
BIN_US = 500
# a line: its power at least this many times the band's median power
MIN_LINE = 30.0
# and this many times the power the model's own simulations have there (the frames' rate
# and its harmonics, which the simulations share, fall in the band too)
MIN_OVER_MODEL = 10.0
# the simulations that match depth and phase, and where they start
ITERATIONS = 3
START_DEPTH = 0.05
DEPTH_RANGE = (0.002, 0.5)


def net_series(obs: Observation) -> tuple[int, np.ndarray]:
    """The first bin's start (us) and the count of ON minus OFF events of ``obs`` in bins of
    :data:`BIN_US` from its first frame to its last."""
    t0 = int(obs.frame_t_us[0])
    t1 = int(obs.frame_t_us[-1])
    n = max((t1 - t0) // BIN_US, 1)
    k = (obs.t_us.astype(np.int64) - t0) // BIN_US
    keep = (k >= 0) & (k < n)
    sign = np.where(obs.p[keep] > 0, 1.0, -1.0)
    return t0, np.bincount(k[keep], weights=sign, minlength=n)


def _bin_times(t0_us: int, n: int) -> np.ndarray:
    """The centres (seconds of the recording's time) of ``n`` bins from ``t0_us``."""
    out: np.ndarray = (t0_us + (np.arange(n) + 0.5) * BIN_US) * 1e-6
    return out


def line_at(t0_us: int, x: np.ndarray, freq_hz: float) -> complex:
    """The complex amplitude of ``x`` (bins from ``t0_us``) at ``freq_hz``, against the
    recording's absolute time (so that phases of different observations compare)."""
    t = _bin_times(t0_us, x.size)
    return complex(np.sum((x - x.mean()) * np.exp(-2j * np.pi * freq_hz * t)))


# the segments whose phases at the line's frequency refine it (their drift over time)
PHASE_SEGMENTS = 6


def find_line(t0_us: int, x: np.ndarray) -> tuple[float, float]:
    """The strongest frequency of ``x`` in :data:`FLICKER_BAND_HZ` and its power over the
    band's median power.

    The spectrum's peak bin, then the peak of the Hann-windowed amplitude within three bins
    of it (the response of the events to a flicker swells and fades with the motion, which
    splits the line into bumps a bin apart), then the drift of the line's phase over
    :data:`PHASE_SEGMENTS` segments of the recording (which the swelling does not move): a
    frequency off by 0.05 Hz turns the phase by 0.8 rad over 2.5 s, and a simulated
    flicker at it no longer keeps time with the measured one."""
    freqs = np.fft.rfftfreq(x.size, BIN_US * 1e-6)
    power = np.abs(np.fft.rfft(x - x.mean())) ** 2
    band = (freqs >= FLICKER_BAND_HZ[0]) & (freqs <= FLICKER_BAND_HZ[1])
    if band.sum() < 8:
        return float("nan"), 0.0
    idx = np.flatnonzero(band)
    i = int(idx[np.argmax(power[idx])])
    ratio = float(power[i] / max(float(np.median(power[idx])), 1e-12))
    df = freqs[1] - freqs[0]
    t = _bin_times(t0_us, x.size)
    xx = x - x.mean()
    grid = freqs[i] + np.linspace(-3 * df, 3 * df, 121)
    amp = np.abs(np.exp(-2j * np.pi * grid[:, None] * t[None, :]) @ (xx * np.hanning(x.size)))
    f = float(grid[int(np.argmax(amp))])
    for _ in range(3):
        step = _drift_hz(*_segment_lines(t, xx, f), min_segments=1)
        if not np.isfinite(step) or abs(step) > df:
            break
        f += step
    return f, ratio


def _segment_lines(t_s: np.ndarray, xx: np.ndarray, freq_hz: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The centres (s) of :data:`PHASE_SEGMENTS` segments of the bins (times ``t_s``, values
    ``xx`` less their mean) and each segment's complex amplitude at ``freq_hz``."""
    segments = np.array_split(np.arange(xx.size), PHASE_SEGMENTS)
    centres = np.array([t_s[s].mean() for s in segments])
    z = np.array([np.sum(xx[s] * np.exp(-2j * np.pi * freq_hz * t_s[s])) for s in segments])
    return centres, z


def _drift_hz(centres: np.ndarray, z: np.ndarray, *, min_segments: int) -> float:
    """The slope (Hz) of the unwrapped phase of the segments' amplitudes ``z`` over their
    ``centres``, each weighted by the square root of its magnitude; NaN with fewer than
    ``min_segments`` segments that carry a line."""
    w = np.sqrt(np.abs(z))
    if not np.all(np.isfinite(w)) or np.count_nonzero(w) < min_segments:
        return float("nan")
    design = np.stack([np.ones_like(centres), centres], 1) * w[:, None]
    coef = np.linalg.lstsq(design, np.unwrap(np.angle(z)) * w, rcond=None)[0]
    return float(coef[1]) / (2 * np.pi)


def frequency_error(t0_us: int, x: np.ndarray, t0_sim_us: int, x_sim: np.ndarray,
                    freq_hz: float) -> float:
    """How far (Hz) the flicker in ``x`` (the measured net polarity, bins from ``t0_us``)
    is above ``freq_hz``, the frequency of the flicker simulated in ``x_sim``: the slope of
    the phase of the measured line over the simulated one across :data:`PHASE_SEGMENTS`
    segments of the recording, weighted by their amplitudes. NaN where a segment pair has no
    line to compare."""
    n = min(x.size, x_sim.size)
    if n < 8 * PHASE_SEGMENTS:
        return float("nan")
    centres, zm = _segment_lines(_bin_times(t0_us, n), x[:n] - x[:n].mean(), freq_hz)
    _, zs = _segment_lines(_bin_times(t0_sim_us, n), x_sim[:n] - x_sim[:n].mean(), freq_hz)
    return _drift_hz(centres, zm * np.conj(zs), min_segments=3)


def _wrap(phase: float) -> float:
    return float((phase + np.pi) % (2 * np.pi) - np.pi)


def fit_flicker(ctx: FitContext) -> FitResult:
    """A flicker of the light: a line in the events' net polarity between 40 and 250 Hz,
    :data:`MIN_LINE` times the band's median and :data:`MIN_OVER_MODEL` times what the
    model's simulations show there; depth, phase and the frequency's last hundredths by up
    to :data:`ITERATIONS` simulations of the model with it (``ctx.simulate``)."""
    if ctx.simulate is None:
        return NoEvidence("fitting a flicker needs simulations of the model, which this "
                          "context cannot run")
    t0, x = net_series(ctx.meas)
    if x.size < 200 or not np.any(x):
        return NoEvidence("too short or too few events for a spectrum of the net polarity")
    f, line = find_line(t0, x)
    if not np.isfinite(f) or line < MIN_LINE:
        return NoEvidence(f"the events' net polarity has no line between "
                          f"{FLICKER_BAND_HZ[0]:.0f} and {FLICKER_BAND_HZ[1]:.0f} Hz (the "
                          f"strongest, at {f:.1f} Hz, is {line:.0f}x the band's median power; "
                          f"{MIN_LINE:.0f}x needed)")
    z_meas = line_at(t0, x, f)
    model_power = float(np.mean([abs(line_at(*net_series(s), f)) ** 2 for s in ctx.sims])) \
        if ctx.sims else 0.0
    over = abs(z_meas) ** 2 / max(model_power, 1e-12)
    if over < MIN_OVER_MODEL:
        return NoEvidence(f"the line at {f:.1f} Hz in the events' net polarity is in the "
                          f"model's simulations too ({over:.1f}x their power; "
                          f"{MIN_OVER_MODEL:.0f}x needed): the frames make it")
    # the net polarity follows the light's rise (its derivative, a cosine where the light
    # is a sine): a quarter cycle on, the first guess of the phase
    depth, phase = START_DEPTH, _wrap(float(np.angle(z_meas)) + np.pi / 2)
    gamma = 1.0
    prev: tuple[float, float] | None = None  # (log depth, log |simulated line|)
    history = []
    t_mid_s = 0.5 * (float(ctx.meas.frame_t_us[0]) + float(ctx.meas.frame_t_us[-1])) * 1e-6
    df_max = 1.0 / max(x.size * BIN_US * 1e-6, 1e-3)  # the spectrum's bin
    for _ in range(ITERATIONS):
        obs = ctx.simulate(Flicker(freq_hz=f, depth=depth, phase_rad=phase))
        t0_sim, x_sim = net_series(obs)
        z = line_at(t0_sim, x_sim, f)
        if abs(z) <= 0:
            break
        z_meas = line_at(t0, x, f)
        history.append({"freq_hz": f, "depth": depth, "phase_rad": phase,
                        "amplitude_ratio": abs(z) / abs(z_meas)})
        now = (float(np.log(depth)), float(np.log(abs(z))))
        if prev is not None and abs(now[0] - prev[0]) > 1e-3:
            gamma = float(np.clip((now[1] - prev[1]) / (now[0] - prev[0]), 0.5, 3.0))
        prev = now
        phase = _wrap(phase + float(np.angle(z_meas / z)))
        depth = float(np.clip(depth * (abs(z_meas) / abs(z)) ** (1.0 / gamma), *DEPTH_RANGE))
        # the frequency, from the drift of the measured line's phase against the simulated
        # one's, segment by segment: the simulation shares the scene's motion, so the
        # swelling and fading of the line cancel in their ratio, which leaves the drift a
        # frequency error makes (0.05 Hz turns it by 0.8 rad over 2.5 s); the phase (the
        # light's at t = 0) turned with it so that it stays at the recording's middle,
        # where the whole recording's line set it
        step = frequency_error(t0, x, t0_sim, x_sim, f)
        if np.isfinite(step) and abs(step) < df_max:
            f += step
            phase = _wrap(phase - 2 * np.pi * step * t_mid_s)
    return Fitted(Flicker(freq_hz=round(f, 3), depth=depth, phase_rad=phase),
                  {"line_over_band_median": line, "line_over_model": over,
                   "iterations": history})
