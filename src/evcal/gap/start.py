"""How the recording began: the fitter of ``start_reset``.

A sensor that ran before its recording started holds each pixel's reference anywhere
within a threshold of the light it sees: a pixel's first event comes after a change of a
random part of its threshold. A simulator that starts from its first input frame (v2e)
sets every reference to that frame's light: the first event then needs a whole threshold.
Still pixels under a slow light show it most (most of their events are first events), and
the share of ON events early in the recording. The fitter reads it off the change each
pixel's frames show before its first event, in units of the model's threshold, and matches
it by simulation: the current model with every reference reset on one seed.
"""

from __future__ import annotations

import numpy as np

from ..sim.effects import StartReset
from .effects import FitContext, FitResult, Fitted, NoEvidence
from .stats import Observation, first_event_change

# pixels with a first event needed to read the change before it
START_MIN_PIXELS = 200
# the measured change before the first events must exceed the model's by this many of its
# standard errors, and lie nearer the reset model's than the model's
START_MIN_Z = 5.0


def change_before_first_event(obs: Observation, contrast: np.ndarray) -> np.ndarray:
    """Per pixel with an event (:func:`.stats.first_event_change`), the change of its
    frames' log intensity before its first event in units of ``contrast`` (the model's
    per-pixel threshold, flat or ``[H, W]``)."""
    d, idx = first_event_change(obs)
    c = np.maximum(np.asarray(contrast, np.float64).ravel()[idx], 1e-3)
    out: np.ndarray = d / c
    return out


def _mean(obs: Observation, contrast: np.ndarray) -> tuple[float, float, int]:
    """The mean change before a first event, its standard error over pixels, the pixels."""
    d = change_before_first_event(obs, contrast)
    if d.size == 0:
        return float("nan"), float("inf"), 0
    return float(d.mean()), float(d.std() / np.sqrt(d.size)), int(d.size)


def fit_start_reset(ctx: FitContext) -> FitResult:
    """``start_reset`` when the measured pixels fire their first events after more change
    than the model's do (by :data:`START_MIN_Z` standard errors: the larger of the seeds'
    spread and the pixels'), and nearer what the model with every reference reset gives
    (one simulation of it) than what the model gives."""
    if ctx.simulate is None:
        return NoEvidence("the workflow offers no simulation to match a reset by")
    c = ctx.model.contrast
    m_meas, se_meas, n = _mean(ctx.meas, c)
    if n < START_MIN_PIXELS:
        return NoEvidence(f"{n} pixels fire in windows the frames show unclipped "
                          f"({START_MIN_PIXELS} needed)")
    sims = [_mean(o, c) for o in ctx.sims]
    m_sims = np.array([s[0] for s in sims])
    m_model = float(np.mean(m_sims))
    spread = float(np.std(m_sims, ddof=1)) if m_sims.size > 1 else 0.0
    se = max(spread, se_meas, float(np.mean([s[1] for s in sims])))
    z = (m_meas - m_model) / max(se, 1e-12)
    head = (f"the frames change by {m_meas:.3g} thresholds before a pixel's first event, "
            f"the model's by {m_model:.3g} (z = {z:+.1f})")
    if z < START_MIN_Z:
        return NoEvidence(head)
    m_reset = _mean(ctx.simulate(StartReset()), c)[0]
    if not abs(m_meas - m_reset) < abs(m_meas - m_model):
        return NoEvidence(f"{head}, nearer the model's than the {m_reset:.3g} of a reset "
                          "at the start")
    return Fitted(StartReset(), {"change_measured": m_meas, "change_model": m_model,
                                 "change_reset": m_reset, "z": z, "pixels": n})
