"""OffE: events-only calibration (no frames).

Over a long recording the log intensity at a pixel stays bounded while events pile up, so
``c * P(t) + b * E(t) ≈ L(t) - L(0)`` stays small: cumulative polarity ``P`` regressed on
cumulative count ``E`` (with intercept) at regular time steps has slope ``m ≈ -b / c``, and
its residual RMS ``r`` is the log-intensity excursion measured in events, ``≈ σ_L / c``. With a
population scale ``c0`` (the median contrast, by default the DI value 0.1)::

    c = median(c0 * r) / r,     b = -c * m

Pixels with too few events, no spread in ``E`` or an unrealistic result keep the defaults.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .accumulate import Accumulator
from .calibration import DEFAULT_BIAS, DEFAULT_CONTRAST, Calibration, OffEDiagnostics, Reason
from .errors import CalibrationError
from .recording import Recording
from .special import classify
from .stream import frame_cuts


@dataclass(frozen=True, kw_only=True)
class OffEConfig:
    """``step_us``: sampling period of the cumulative sums; ``c0``: population median
    contrast the relative scale is anchored to."""

    step_us: int = 10_000
    c0: float = DEFAULT_CONTRAST
    min_events: int = 20
    min_steps: int = 10
    max_ratio: float = 5.0  # c outside [median/ratio, median*ratio] is unrealistic

    def __post_init__(self) -> None:
        if self.step_us <= 0:
            raise ValueError(f"step_us={self.step_us} must be > 0")
        if not self.c0 > 0:
            raise ValueError(f"c0={self.c0} must be > 0")


def offe(rec: Recording, config: OffEConfig | None = None) -> Calibration:
    """Events-only per-pixel ``c``, ``b`` (frames, if any, are not used)."""
    cfg = config or OffEConfig()
    if rec.n_events == 0:
        raise CalibrationError("OffE needs events: the recording has none")
    t = rec.events["t_us"]
    t0, t1 = int(t[0]), int(t[-1])
    steps = np.arange(t0 + cfg.step_us, t1 + cfg.step_us, cfg.step_us, dtype=np.int64)
    n = rec.sensor.n_pixels
    acc = Accumulator(rec.sensor)
    s = {k: np.zeros(n) for k in ("e", "p", "ee", "ep", "pp")}
    pos = 0
    cuts = frame_cuts(t, steps)  # steps cut the stream as frames do
    for cut in cuts:  # loop over time steps, vectorised over pixels
        if cut > pos:
            acc.add(rec.events[pos:cut])
            pos = int(cut)
        e = (acc.on + acc.off).astype(np.float64)
        p = (acc.on - acc.off).astype(np.float64)
        s["e"] += e
        s["p"] += p
        s["ee"] += e * e
        s["ep"] += e * p
        s["pp"] += p * p
    m_steps = float(len(steps))
    n_events = (acc.on + acc.off).astype(np.int64)
    with np.errstate(divide="ignore", invalid="ignore"):
        see = s["ee"] - s["e"] ** 2 / m_steps
        sep = s["ep"] - s["e"] * s["p"] / m_steps
        spp = s["pp"] - s["p"] ** 2 / m_steps
        slope = np.where(see > 0, sep / np.where(see > 0, see, 1.0), 0.0)
        rss = np.maximum(spp - slope * sep, 0.0)
        r = np.sqrt(rss / m_steps)
    reason = np.zeros(n, np.uint8)
    reason[(n_events < cfg.min_events) | (m_steps < cfg.min_steps)] = Reason.TOO_FEW_EVENTS
    reason[(see <= 0) & (reason == 0)] = Reason.RANK_DEFICIENT
    reason[(r <= 0) & (reason == 0)] = Reason.RANK_DEFICIENT
    reason[n_events == 0] = Reason.NO_EVENTS
    cand = reason == 0
    if not cand.any():
        raise CalibrationError("OffE: no pixel has enough events for a regression")
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = float(np.median(cfg.c0 * r[cand]))
        c = np.where(cand, scale / np.where(cand, r, 1.0), DEFAULT_CONTRAST)
        b = np.where(cand, -c * slope, DEFAULT_BIAS)
    med = float(np.median(c[cand]))
    bad = cand & ((c < med / cfg.max_ratio) | (c > med * cfg.max_ratio) | (np.abs(b) >= 0.95 * c))
    reason[bad] = Reason.OUT_OF_RANGE
    valid = reason == 0
    c = np.where(valid, c, DEFAULT_CONTRAST)
    b = np.where(valid, b, DEFAULT_BIAS)
    # A standard error for b from the slope's regression; c's relative scale has none that
    # is meaningful without frames, so it is reported as unknown (inf).
    with np.errstate(divide="ignore", invalid="ignore"):
        se_slope = np.sqrt(np.where(see > 0, rss / max(m_steps - 2, 1) / see, np.inf))
    se_b = np.where(valid, c * se_slope, np.inf)
    se_c = np.full(n, np.inf)
    special = classify(c, b, np.where(valid, 0.0, np.inf), se_b, valid)
    shape = rec.sensor.shape
    return Calibration(
        contrast=c.reshape(shape), bias=b.reshape(shape), valid=valid.reshape(shape),
        reason=reason.reshape(shape), stderr_contrast=se_c.reshape(shape),
        stderr_bias=se_b.reshape(shape), special=special.reshape(shape), log_offset=math.nan,
        method="offe", n_events=n_events.reshape(shape),
        diagnostics=OffEDiagnostics(step_us=cfg.step_us, c0=cfg.c0, scale=float(scale),
                                    n_steps=int(m_steps)),
    )
