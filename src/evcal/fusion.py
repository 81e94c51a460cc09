"""Frames and events' timing together: a frame-based calibration fused with OffE's.

OffEI and OnEI use what the events add up to between frames; OffE (:mod:`evcal.offe`) uses
when they fall: each pixel's cumulative polarity against its cumulative count over 10-ms
steps, compared with its neighbours'. The two see different noise (the frames' sub-threshold
residual; the pixel's own light path and count) and their errors hardly correlate, so each
pixel's two estimates are averaged by their stated errors. What OffE cannot give, the frames
do: its ``c`` has no absolute scale (it is anchored at the frame estimate's median over the
pixels valid in both) and its ``b`` no absolute level (shifted by the median difference).

The two sets of stated errors are checked against each other first: for the pixels valid in
both, ``d = x_frames - x_offe`` should spread as ``sqrt(s_frames^2 + s_offe^2)``. The frame
estimators' errors are the calibrated ones (OffEI's from its residuals, OnEI's checked on
the recording's halves), so what the differences show beyond them is put on OffE's: its
errors are widened by one factor so that the differences' robust z-scale is 1 (within
:data:`OFFE_SCALE_RANGE`: never narrowed). A pixel without an OffE estimate or error keeps
the frames'; where OffE cannot run at all (too short, too few events) the frames' maps are
kept and the diagnostics say why.

Pure numpy; :func:`with_event_timing` runs OffE itself.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np

from .calibration import Calibration
from .errors import CalibrationError, ConfigError
from .offe import OffEConfig, offe
from .recording import Recording
from .special import classify
from .splithalf import CHI2_1_MEDIAN

# OffE's stated errors are widened by a factor in this range, never narrowed: a z-scale of
# the differences below 1 is as likely a positive correlation of the two errors
OFFE_SCALE_RANGE = (1.0, 4.0)
# the widening factor's search: its precision, and the pixels it looks at (evenly spaced)
SCALE_TOLERANCE = 1e-4
SCALE_SAMPLE = 1 << 16
# fewer pixels valid in both and nothing is fused (a median over them decides the anchors)
MIN_PIXELS = 100
FUSABLE = ("offei", "onei")


def with_event_timing(rec: Recording, cal: Calibration,
                      config: OffEConfig | None = None) -> Calibration:
    """``cal`` (OffEI or OnEI of ``rec``) fused with OffE of the same recording (the module
    docstring); ``cal`` itself when too few pixels have both (said in the diagnostics)."""
    if cal.method not in FUSABLE:
        raise ConfigError(f"event timing is fused into {' or '.join(FUSABLE)} maps, not "
                          f"{cal.method!r}")
    if "fusion" in cal.diagnostics.extra:
        raise ConfigError("this calibration holds fused maps already")
    frames_c0 = float(np.median(cal.contrast[cal.valid])) if cal.valid.any() else None
    cfg = config or OffEConfig()
    if frames_c0 is not None and frames_c0 > 0:
        cfg = replace(cfg, c0=frames_c0)
    try:
        events_only = offe(rec, cfg)
    except CalibrationError as e:  # too short, too few events: the frames' maps, and why
        return kept(cal, {"pixels": 0, "valid": int(cal.valid.sum())}, f"no OffE: {e}")
    return fuse(cal, events_only)


def kept(cal: Calibration, info: dict[str, Any], why: str) -> Calibration:
    diag = cal.diagnostics.updated(extra={**cal.diagnostics.extra,
                                          "fusion": {**info, "reason": why}})
    return cal.replace(diagnostics=diag)


def _rescale(d: np.ndarray, s_frames: np.ndarray, s_offe: np.ndarray) -> tuple[float, float]:
    """The factor ``alpha`` in :data:`OFFE_SCALE_RANGE` on OffE's errors for which the
    differences ``d`` have a robust z-scale of 1 with the frames' errors as they are (one
    factor for all pixels, found by bisection to :data:`SCALE_TOLERANCE`: the z-scale falls
    as it grows); and the z-scale with the errors as stated. Over at most
    :data:`SCALE_SAMPLE` pixels, evenly spaced: a median of that many is within a percent,
    and the service fuses every update at up to a megapixel."""
    if d.size > SCALE_SAMPLE:
        pick = np.linspace(0, d.size - 1, SCALE_SAMPLE).astype(np.int64)
        d, s_frames, s_offe = d[pick], s_frames[pick], s_offe[pick]
    d2, f2, e2 = d * d, s_frames * s_frames, s_offe * s_offe

    def z_scale(alpha: float) -> float:
        return math.sqrt(float(np.median(d2 / (f2 + alpha * alpha * e2))) / CHI2_1_MEDIAN)

    lo, hi = OFFE_SCALE_RANGE
    k = z_scale(1.0)
    if (k if lo == 1.0 else z_scale(lo)) <= 1.0:
        return lo, k
    if z_scale(hi) >= 1.0:
        return hi, k
    while hi - lo > SCALE_TOLERANCE:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if z_scale(mid) > 1.0 else (lo, mid)
    return 0.5 * (lo + hi), k


def fuse(cal: Calibration, events_only: Calibration) -> Calibration:
    """``cal``'s maps fused with ``events_only``'s (an OffE calibration of the same sensor):
    see the module docstring."""
    if events_only.method != "offe":
        raise ConfigError(f"fuse takes an OffE calibration, not {events_only.method!r}")
    if events_only.shape != cal.shape:
        raise ConfigError(f"OffE maps of shape {events_only.shape} for a calibration of "
                          f"{cal.shape}")
    both = cal.valid & events_only.valid
    for m in (cal.stderr_contrast, cal.stderr_bias, events_only.stderr_contrast,
              events_only.stderr_bias):
        both &= np.isfinite(m) & (m > 0)
    n_both = int(both.sum())
    info: dict[str, Any] = {"pixels": n_both, "valid": int(cal.valid.sum())}
    if n_both < MIN_PIXELS:
        return kept(cal, info, f"{n_both} pixels valid with stated errors in both (fewer "
                                f"than {MIN_PIXELS}): the frames' maps kept")
    # computed on the pixels valid in both only (the service fuses every update)
    idx = np.flatnonzero(both)

    def at(m: np.ndarray) -> np.ndarray:
        out: np.ndarray = m.ravel()[idx].astype(np.float64)
        return out

    fc, fb, fsc, fsb = (at(cal.contrast), at(cal.bias), at(cal.stderr_contrast),
                        at(cal.stderr_bias))
    ec, eb, esc, esb = (at(events_only.contrast), at(events_only.bias),
                        at(events_only.stderr_contrast), at(events_only.stderr_bias))
    # OffE's scale and level from the frames
    scale = float(np.median(fc) / np.median(ec))
    ec, esc = ec * scale, esc * scale
    eb, esb = eb * scale, esb * scale
    # an error of OffE's c moves its b by b / c = -m times it: the slope before the shift
    with np.errstate(divide="ignore", invalid="ignore"):
        b_per_c = eb / ec
    shift = float(np.median(fb - eb))
    eb = eb + shift
    alpha_c, k_c = _rescale(fc - ec, fsc, esc)
    alpha_b, k_b = _rescale(fb - eb, fsb, esb)
    esc_r, esb_r = alpha_c * esc, alpha_b * esb
    wc = esc_r ** 2 / (esc_r ** 2 + fsc ** 2)  # the frames' weight
    wb = esb_r ** 2 / (esb_r ** 2 + fsb ** 2)
    se_c_both = np.sqrt(wc) * fsc  # = 1 / sqrt(1/s_f^2 + 1/s_e^2)
    se_b_both = np.sqrt(wb) * fsb
    # the fused errors' correlation: the frames' own (where stated) through their weights,
    # and OffE's through b = -c m (an error of c moves b by b / c times it)
    diag = cal.diagnostics
    rho_f = getattr(diag, "error_correlation", None)
    rho = (np.zeros(cal.shape) if rho_f is None or np.shape(rho_f) != cal.shape
           else np.nan_to_num(np.asarray(rho_f, np.float64)))
    with np.errstate(divide="ignore", invalid="ignore"):
        cov = (wc * wb * rho.ravel()[idx] * fsc * fsb
               + (1 - wc) * (1 - wb) * b_per_c * esc_r ** 2)
        rho.ravel()[idx] = np.clip(cov / (se_c_both * se_b_both), -0.99, 0.99)

    def full(m: np.ndarray, values: np.ndarray) -> np.ndarray:
        out = m.astype(np.float64)  # a copy: the frames' values where not fused
        out.ravel()[idx] = values
        return out

    c = full(cal.contrast, wc * fc + (1 - wc) * ec)
    b = full(cal.bias, wb * fb + (1 - wb) * eb)
    se_c = full(cal.stderr_contrast, se_c_both)
    se_b = full(cal.stderr_bias, se_b_both)
    info.update({"offe_contrast_scale": scale, "offe_bias_shift": shift,
                 "z_scale_contrast": k_c, "z_scale_bias": k_b,
                 "offe_error_factor_contrast": alpha_c, "offe_error_factor_bias": alpha_b,
                 "frames_weight_contrast": float(np.median(wc)),
                 "frames_weight_bias": float(np.median(wb))})
    if hasattr(diag, "error_correlation"):
        diag = diag.updated(error_correlation=rho.astype(np.float32))
    diag = diag.updated(extra={**diag.extra, "fusion": info})
    special = classify(c, b, se_c, se_b, cal.valid)
    return cal.replace(contrast=c.astype(cal.contrast.dtype), bias=b.astype(cal.bias.dtype),
                       stderr_contrast=se_c.astype(cal.stderr_contrast.dtype),
                       stderr_bias=se_b.astype(cal.stderr_bias.dtype),
                       special=special, diagnostics=diag)
