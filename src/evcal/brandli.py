"""Baselines: direct integration (DI) and Brandli et al., ISCAS 2014.

Brandli, Muller and Delbruck, "Real-time, high-speed video decompression using a frame- and
event-based DAVIS sensor", ISCAS 2014; reference implementation jAER
``ch.unizh.ini.jaer.projects.davis.frames.ApsFrameExtrapolationISCAS``. Our reading of it:

- each pixel has an ON gain ``g_on > 0`` and an OFF gain ``g_off < 0`` (log units per event,
  initialised to the DI values ``±0.1``); between frames every event adds its gain to the
  pixel's log intensity, starting from the log of the last frame;
- at each new frame the integration error ``err = L_integrated - L_frame`` is shared between
  the gains by the events that caused it: ``g_on -= eta * err * n_on / N`` and
  ``g_off -= eta * err * n_off / N`` with ``N = n_on + n_off`` (``eta = 0.25`` in jAER);
  pixels with no events are not updated; then the state resets to the new frame;
- jAER keeps time bins of the gain by inter-event interval and by default ties every pixel's
  gains to their global average; almost every event falls in one bin, so we keep one ON and one
  OFF gain per pixel and do not tie them (the per-pixel variant is what the paper compares
  against). Its log is ``ln(ADC + 10000)``, nearly linear; we use the same ``log(I + offset)``
  as every evcal estimator so the methods are compared on equal terms;
- we clip the gains to ``[min_step, max_step]`` (jAER does not) so a burst of noise cannot make
  a threshold negative.

In evcal's terms ``c = (g_on - g_off) / 2`` and ``b = (g_on + g_off) / 2``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .calibration import DEFAULT_BIAS, DEFAULT_CONTRAST, BrandliDiagnostics, Calibration, Reason
from .errors import CalibrationError, ConfigError
from .recording import Recording
from .solver import log_intensity, usable
from .special import classify
from .stream import frame_intervals


@dataclass(frozen=True, kw_only=True)
class BrandliConfig:
    eta: float = 0.25
    log_offset: float = 30.0
    initial_contrast: float = DEFAULT_CONTRAST
    min_step: float = 0.01
    max_step: float = 2.0
    min_events: int = 20
    saturation_dn: tuple[float, float] = (0.0, 255.0)

    def __post_init__(self) -> None:
        if not 0 < self.eta <= 1:
            raise ConfigError(f"eta={self.eta} must be in (0, 1]")
        if self.log_offset < 0:
            raise ConfigError(f"log_offset={self.log_offset} must be >= 0")


def brandli(rec: Recording, config: BrandliConfig | None = None) -> Calibration:
    """Per-pixel ON/OFF gains adapted at every frame from the integration error."""
    cfg = config or BrandliConfig()
    if len(rec.frames) < 2:
        raise CalibrationError(f"Brandli needs at least 2 frames, the recording has "
                               f"{len(rec.frames)}")
    n = rec.sensor.n_pixels
    g_on = np.full(n, cfg.initial_contrast)
    g_off = np.full(n, -cfg.initial_contrast)
    n_total = np.zeros(n, np.int64)
    frames = rec.frames.images
    l_prev = log_intensity(frames[0].ravel(), cfg.log_offset)
    ok_prev = usable(frames[0].ravel(), cfg.saturation_dn)
    for k, ev in frame_intervals(rec.events, rec.frames.t_us):  # vectorised over pixels
        if k == 0:
            continue  # events before the first frame have no start image
        idx = ev["y"].astype(np.int64) * rec.sensor.width + ev["x"]
        on_mask = ev["p"] > 0
        n_on = np.bincount(idx[on_mask], minlength=n)
        n_off = np.bincount(idx[~on_mask], minlength=n)
        n_ev = n_on + n_off
        n_total += n_ev
        l_now = log_intensity(frames[k].ravel(), cfg.log_offset)
        ok_now = usable(frames[k].ravel(), cfg.saturation_dn)
        err = l_prev + g_on * n_on + g_off * n_off - l_now
        upd = (n_ev > 0) & ok_prev & ok_now
        share = np.where(upd, cfg.eta * err / np.maximum(n_ev, 1), 0.0)
        g_on = np.clip(g_on - share * n_on, cfg.min_step, cfg.max_step)
        g_off = np.clip(g_off - share * n_off, -cfg.max_step, -cfg.min_step)
        l_prev, ok_prev = l_now, ok_now
    c = 0.5 * (g_on - g_off)
    b = 0.5 * (g_on + g_off)
    reason = np.zeros(n, np.uint8)
    reason[n_total < cfg.min_events] = Reason.TOO_FEW_EVENTS
    reason[n_total == 0] = Reason.NO_EVENTS
    valid = reason == 0
    c = np.where(valid, c, DEFAULT_CONTRAST)
    b = np.where(valid, b, DEFAULT_BIAS)
    inf = np.full(n, np.inf)
    special = classify(c, b, np.where(valid, 0.0, np.inf), np.where(valid, 0.0, np.inf), valid)
    shape = rec.sensor.shape
    return Calibration(
        contrast=c.reshape(shape), bias=b.reshape(shape), valid=valid.reshape(shape),
        reason=reason.reshape(shape), stderr_contrast=inf.reshape(shape),
        stderr_bias=inf.reshape(shape), special=special.reshape(shape),
        log_offset=cfg.log_offset, method="brandli", n_events=n_total.reshape(shape),
        diagnostics=BrandliDiagnostics(eta=cfg.eta, min_step=cfg.min_step,
                                       max_step=cfg.max_step),
    )
