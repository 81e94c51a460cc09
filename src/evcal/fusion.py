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
    factor for all pixels, found by bisection: the z-scale falls as it grows); and the
    z-scale with the errors as stated."""

    def z_scale(alpha: float) -> float:
        z2 = d ** 2 / (s_frames ** 2 + (alpha * s_offe) ** 2)
        return math.sqrt(float(np.median(z2)) / CHI2_1_MEDIAN)

    lo, hi = OFFE_SCALE_RANGE
    k = z_scale(1.0)
    if (k if lo == 1.0 else z_scale(lo)) <= 1.0:
        return lo, k
    if z_scale(hi) >= 1.0:
        return hi, k
    for _ in range(40):
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
    fc, fb = cal.contrast.astype(np.float64), cal.bias.astype(np.float64)
    fsc, fsb = cal.stderr_contrast.astype(np.float64), cal.stderr_bias.astype(np.float64)
    ec, eb = events_only.contrast.astype(np.float64), events_only.bias.astype(np.float64)
    esc = events_only.stderr_contrast.astype(np.float64)
    esb = events_only.stderr_bias.astype(np.float64)
    both = (cal.valid & events_only.valid & np.isfinite(fsc) & np.isfinite(fsb)
            & np.isfinite(esc) & np.isfinite(esb) & (fsc > 0) & (fsb > 0) & (esc > 0)
            & (esb > 0))
    n_both = int(both.sum())
    info: dict[str, Any] = {"pixels": n_both, "valid": int(cal.valid.sum())}
    if n_both < MIN_PIXELS:
        return kept(cal, info, f"{n_both} pixels valid with stated errors in both (fewer "
                                f"than {MIN_PIXELS}): the frames' maps kept")
    # OffE's scale and level from the frames
    scale = float(np.median(fc[both]) / np.median(ec[both]))
    ec, esc = ec * scale, esc * scale
    eb, esb = eb * scale, esb * scale
    # an error of OffE's c moves its b by b / c = -m times it: the slope before the shift
    b_per_c = np.where(both, eb / np.where(both, ec, 1.0), 0.0)
    shift = float(np.median(fb[both] - eb[both]))
    eb = eb + shift
    alpha_c, k_c = _rescale((fc - ec)[both], fsc[both], esc[both])
    alpha_b, k_b = _rescale((fb - eb)[both], fsb[both], esb[both])
    esc_r, esb_r = alpha_c * esc[both], alpha_b * esb[both]
    wc = np.zeros(cal.shape)
    wb = np.zeros(cal.shape)
    wc[both] = esc_r ** 2 / (esc_r ** 2 + fsc[both] ** 2)  # the frames' weight
    wb[both] = esb_r ** 2 / (esb_r ** 2 + fsb[both] ** 2)
    c = np.where(both, wc * fc + (1 - wc) * ec, fc)
    b = np.where(both, wb * fb + (1 - wb) * eb, fb)
    se_c = fsc.copy()
    se_b = fsb.copy()
    se_c[both] = np.sqrt(wc[both]) * fsc[both]  # = 1 / sqrt(1/s_f^2 + 1/s_e^2)
    se_b[both] = np.sqrt(wb[both]) * fsb[both]
    # the fused errors' correlation: the frames' own (where stated) through their weights,
    # and OffE's through b = -c m (an error of c moves b by b / c times it)
    diag = cal.diagnostics
    rho_f = getattr(diag, "error_correlation", None)
    rho_f = (np.zeros(cal.shape) if rho_f is None or np.shape(rho_f) != cal.shape
             else np.nan_to_num(np.asarray(rho_f, np.float64)))
    e_sc_full = np.zeros(cal.shape)
    e_sc_full[both] = esc_r
    with np.errstate(divide="ignore", invalid="ignore"):
        cov = wc * wb * rho_f * fsc * fsb + (1 - wc) * (1 - wb) * b_per_c * e_sc_full ** 2
        rho = np.where(both, np.clip(cov / (se_c * se_b), -0.99, 0.99), rho_f)
    info.update({"offe_contrast_scale": scale, "offe_bias_shift": shift,
                 "z_scale_contrast": k_c, "z_scale_bias": k_b,
                 "offe_error_factor_contrast": alpha_c, "offe_error_factor_bias": alpha_b,
                 "frames_weight_contrast": float(np.median(wc[both])),
                 "frames_weight_bias": float(np.median(wb[both]))})
    if hasattr(diag, "error_correlation"):
        diag = diag.updated(error_correlation=rho.astype(np.float32))
    diag = diag.updated(extra={**diag.extra, "fusion": info})
    special = classify(c, b, se_c, se_b, cal.valid)
    return cal.replace(contrast=c.astype(cal.contrast.dtype), bias=b.astype(cal.bias.dtype),
                       stderr_contrast=se_c.astype(cal.stderr_contrast.dtype),
                       stderr_bias=se_b.astype(cal.stderr_bias.dtype),
                       special=special, diagnostics=diag)
