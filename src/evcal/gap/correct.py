"""Model-corrected calibration: remove the bias that named sensor effects put into OffEI.

Effects bias the per-pixel least squares in ways that depend on the pixel: refractory drops
more events of busy pixels (their fitted ``c`` comes out too large), shot noise adds
polarity-balanced events mostly to dark pixels (their ``c`` comes out too small), leak adds ON
events to quiet pixels (``b`` shifts). Once :mod:`evcal.gap` has named the effects of a
recording, the model predicts that bias, and this module removes it:

1. Fit OffEI on the measurement (``c_m``, ``b_m``), at the model's log offset when it names
   one.
2. Simulate the measurement under the model, with maps ``c0``, ``b0`` (the fit shrunk towards
   the population by its standard errors, scaled to the fit's scatter on the recording as
   the gap's base model is, :func:`evcal.gap.model.noise_scale`; so estimation noise is not
   simulated as fixed pattern), ``n_seeds`` times, and fit each simulation exactly as the
   measurement.
3. Per pixel, the simulated fits give a gain ``a = mean(c_s) / c0`` and an offset
   ``o = mean(b_s) - a b0`` (the fit of a pixel is ``c_fit = a c``, ``b_fit = a b + o``).
   Single pixels are too noisy for that, so ``a`` and ``o`` are taken as medians over cells of
   the pixels' covariates that the effects depend on: measured event count (activity) and
   median log intensity (light), ``activity_bins x intensity_bins`` quantile cells (cells with
   fewer than ``min_cell_pixels`` valid pixels take their activity bin's value, then the
   population's).
4. Invert: ``c = c_m / a``, ``b = (b_m - o) / a``; repeat from 2 with the corrected maps as
   the model (``iterations`` times), since the bias depends on the parameters themselves.

Noise events (a model naming ``shot_noise`` or ``leak``): they are isolated in space-time,
so the measurement is first cleaned with the background-activity filter
(:func:`evcal.denoise.background_activity_filter`, ``denoise_us``). That removes most of the
variance they add (the bias alone is what steps 2-4 can remove); it also drops real events of
isolated pixels, a bias of its own. So the simulations *with* the effects are filtered the
same way and the ideal ones are not: the gain ``a`` then holds the effects' bias and the
filter's together, and step 4 removes both (what the filter and the correction each take
off: docs/MEASUREMENTS.md and tests/test_v2e.py).

Pixels that OffEI marked invalid stay invalid with their defaults. The gains and offsets
applied (population median and the range over cells) are reported in the diagnostics.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..calibration import Calibration
from ..denoise import background_activity_filter, still_interval_mask
from ..errors import ConfigError
from ..offline import OffEIConfig, offei
from ..online import usable_cores
from ..recording import Recording
from ..sim.effects import Effect, LogOffset, effect_set, make_effect
from .model import (
    Model,
    SimSettings,
    _shrink,
    estimate_read_noise,
    noise_scale,
    simulate_model,
    subframe_shift,
)
from .render import RenderCache
from .stats import NOMINAL_LOG_OFFSET_DN


class ModelFileError(ConfigError):
    """A model file (``report.json`` of ``evcal gap``) that cannot be read as a model."""


def load_model_effects(path: str | os.PathLike[str]) -> dict[str, Effect]:
    """The effects named in a ``report.json`` written by ``evcal gap`` (its ``steps``), or in a
    plain ``{"effects": [{"name": ..., "parameters": {...}}, ...]}`` file."""
    p = Path(path)
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ModelFileError(f"model file {p} does not exist") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ModelFileError(f"model file {p} is not readable JSON: {exc}") from None
    if not isinstance(doc, dict):
        raise ModelFileError(f"model file {p}: expected a JSON object, got {type(doc).__name__}")
    if "steps" in doc:
        items = [{"name": s.get("effect"), "parameters": s.get("parameters", {})}
                 for s in doc["steps"] if isinstance(s, dict)]
    elif "effects" in doc:
        items = doc["effects"]
    else:
        raise ModelFileError(f"model file {p} has neither 'steps' (a gap report.json) nor "
                             "'effects'")
    effects: list[Effect] = []
    for i, item in enumerate(items):
        if not isinstance(item, dict) or not isinstance(item.get("name"), str) \
                or not isinstance(item.get("parameters", {}), dict):
            raise ModelFileError(f"model file {p}: effect {i} is not "
                                 "{'name': str, 'parameters': {...}}")
        try:
            effects.append(make_effect(item["name"], **item.get("parameters", {})))
        except (TypeError, ValueError) as exc:
            raise ModelFileError(f"model file {p}: effect {i} ({item['name']}): {exc}") from None
    return effect_set(effects)


@dataclass(frozen=True, kw_only=True)
class CorrectionConfig:
    """Settings of :func:`model_corrected`."""

    n_seeds: int = 3
    iterations: int = 2
    activity_bins: int = 4
    intensity_bins: int = 3
    min_cell_pixels: int = 20
    internal_rate_hz: float = 1000.0
    interpolation: str = "flow"  # between frames: see evcal.gap.flow
    seed: int = 0
    # background-activity filter window (µs) for models with noise events; "auto": 10 ms
    # when the model names shot_noise or leak, else none; None: never
    denoise_us: int | str | None = "auto"
    # the filter's support: from a neighbour's event of the same polarity, before or after
    denoise_same_polarity: bool = True
    denoise_two_sided: bool = True
    # with the filter, events of frame intervals whose change of log intensity is below this
    # fraction of the median threshold are dropped too (None: not)
    still_fraction: float | None = 0.1

    def __post_init__(self) -> None:
        for name in ("n_seeds", "iterations", "activity_bins", "intensity_bins",
                     "min_cell_pixels"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"{name}={getattr(self, name)} must be >= 1")
        d = self.denoise_us
        if not (d is None or d == "auto" or (isinstance(d, int) and d > 0)):
            raise ConfigError(f"denoise_us={d!r} must be 'auto', None or a window > 0 µs")
        f = self.still_fraction
        if f is not None and not 0 < f < 1:
            raise ConfigError(f"still_fraction={f!r} must be None or in (0, 1)")

    def denoise_window_us(self, effects: Mapping[str, Effect]) -> int | None:
        """The filter window for a model with ``effects`` (None: no filtering)."""
        if self.denoise_us == "auto":
            return 10_000 if NOISE_EFFECTS & set(effects) else None
        return None if self.denoise_us is None else int(self.denoise_us)


NOISE_EFFECTS = frozenset({"shot_noise", "leak"})  # isolated events a filter can remove


@dataclass(frozen=True)
class _Denoiser:
    """The filters of :func:`model_corrected`, applied alike to the measurement and to the
    simulations with the effects."""

    window_us: int | None
    same_polarity: bool
    two_sided: bool
    still_dl: float | None  # log-intensity change below which a frame interval is still
    log_offset: float

    def __call__(self, rec: Recording) -> Recording:
        if self.window_us is None:
            return rec
        keep = background_activity_filter(rec.events, rec.sensor, self.window_us,
                                          same_polarity=self.same_polarity,
                                          two_sided=self.two_sided)
        if self.still_dl is not None:
            keep &= still_interval_mask(rec.events, rec.frames, rec.sensor, self.still_dl,
                                        self.log_offset)
        return rec.with_events(rec.events[keep])


def _quantile_bins(v: np.ndarray, ok: np.ndarray, n: int) -> np.ndarray:
    edges = np.unique(np.quantile(v[ok], np.linspace(0, 1, n + 1)))
    if edges.size < 2:
        return np.zeros(v.shape, np.int64)
    edges[0], edges[-1] = -np.inf, np.inf
    out: np.ndarray = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, edges.size - 2)
    return out


def _cell_medians(values: np.ndarray, ok: np.ndarray, cells: np.ndarray, coarse: np.ndarray,
                  min_pixels: int) -> np.ndarray:
    """Per pixel: the median of ``values`` over the valid pixels of its cell; cells with too
    few take their coarse bin's median, then the population's."""
    pop = float(np.median(values[ok]))
    out = np.full(values.shape, pop)
    for key_map in (coarse, cells):  # coarse first, fine cells overwrite where they can
        for key in np.unique(key_map):
            m = key_map == key
            sel = m & ok
            if sel.sum() >= min_pixels:
                out[m] = np.median(values[sel])
    return out


def _covariates(rec: Recording, cal: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel: the events OffEI used (between the first and the last frame) and the median
    log intensity."""
    fr = rec.frames
    count = cal.n_events.astype(np.float64).ravel()
    off = cal.log_offset if np.isfinite(cal.log_offset) else 1.0
    light = np.median(np.log(fr.images.reshape(len(fr), -1).astype(np.float64) + max(off, 0.5)),
                      axis=0)
    return count, light


def model_corrected(rec: Recording, effects: Mapping[str, Effect] | list[Effect],
                    offei_config: OffEIConfig | None = None,
                    config: CorrectionConfig | None = None) -> Calibration:
    """OffEI of ``rec`` with the bias of ``effects`` removed (see the module docstring).

    The log offset is the model's (its ``log_offset`` effect) when it names one, else
    ``offei_config.log_offset`` (``"auto"``: estimated).
    """
    cfg = config or CorrectionConfig()
    eff = effect_set(effects)
    base_cfg = offei_config or OffEIConfig()
    lo = eff.get(LogOffset.name)
    if isinstance(lo, LogOffset):
        base_cfg = replace(base_cfg, log_offset=float(lo.dark_dn))
    if not eff:
        return offei(rec, base_cfg).with_warning("model has no effects: nothing to correct")
    window_us = cfg.denoise_window_us(eff)
    n_in = rec.n_events
    still_dl = None
    offset_in = base_cfg.log_offset
    if window_us is not None and (cfg.still_fraction is not None or offset_in == "auto"):
        # the median threshold and the offset, from the unfiltered data
        pre = offei(rec, base_cfg)
        offset_in = float(pre.log_offset)
        base_cfg = replace(base_cfg, log_offset=offset_in)
        if cfg.still_fraction is not None and pre.valid.any():
            still_dl = cfg.still_fraction * float(np.median(pre.contrast[pre.valid]))
    denoise = _Denoiser(window_us, cfg.denoise_same_polarity, cfg.denoise_two_sided, still_dl,
                        float(offset_in) if offset_in != "auto" else NOMINAL_LOG_OFFSET_DN)
    rec = denoise(rec)
    cal_m = offei(rec, base_cfg)
    offset = float(cal_m.log_offset)
    sim_cfg = replace(base_cfg, log_offset=offset)
    settings = SimSettings(internal_rate_hz=cfg.internal_rate_hz,
                           read_noise_dn=estimate_read_noise(rec.frames),
                           interpolation=cfg.interpolation)
    if cfg.interpolation == "flow":
        # the light the gap workflow fitted the effects in: shaken between frames as the
        # events say (evcal.gap.motion)
        settings = replace(settings, shift=subframe_shift(rec, settings,
                                                          (float("nan"), float("nan")))[0])
    # the interpolated frames, rendered once (on every core) for every simulation
    render = RenderCache(workers=usable_cores())
    valid = cal_m.valid.ravel()
    c_m = cal_m.contrast.astype(np.float64).ravel()
    b_m = cal_m.bias.astype(np.float64).ravel()
    count, light = _covariates(rec, cal_m)
    act = _quantile_bins(count, valid, cfg.activity_bins)
    cells = act * cfg.intensity_bins + _quantile_bins(light, valid, cfg.intensity_bins)
    shape = rec.sensor.shape

    # the fit's errors scaled to its scatter on this recording, as the gap's base model
    # (evcal.gap.model.noise_scale), measured once: every iteration keeps cal_m's errors
    scale = noise_scale(rec, sim_cfg, cal_m, Model(*_shrink(cal_m, offset), offset),
                        settings=settings, render=render)
    cur = cal_m
    gain = np.ones(c_m.shape)
    shift = np.zeros(c_m.shape)
    for _ in range(cfg.iterations):
        c0, b0 = _shrink(cur, offset, scale)
        fits = {}
        ok = valid.copy()
        for label, with_eff in (("effects", dict(eff)), ("ideal", {})):
            cs = np.zeros(c_m.shape)
            bs = np.zeros(c_m.shape)
            for k in range(cfg.n_seeds):
                sim = simulate_model(Model(c0, b0, offset, with_eff), rec,
                                     cfg.seed * 1000 + k, settings, render)
                if label == "effects":  # filtered as the measurement was; the ideal not
                    sim = denoise(sim)
                fit = offei(sim, sim_cfg)
                ok &= fit.valid.ravel()
                cs += fit.contrast.astype(np.float64).ravel() / cfg.n_seeds
                bs += fit.bias.astype(np.float64).ravel() / cfg.n_seeds
            fits[label] = (cs, bs)
        if ok.sum() < cfg.min_cell_pixels:
            return cal_m.with_warning(
                f"model correction skipped: {int(ok.sum())} pixels valid in both the "
                "measurement and its simulations")
        (cs, bs), (ci, bi) = fits["effects"], fits["ideal"]
        a_pix = cs / np.maximum(ci, 1e-6)
        o_pix = bs - a_pix * bi
        gain = _cell_medians(np.log(np.maximum(a_pix, 1e-6)), ok, cells, act,
                             cfg.min_cell_pixels)
        gain = np.exp(np.clip(gain, -1.0, 1.0))
        shift = _cell_medians(o_pix, ok, cells, act, cfg.min_cell_pixels)
        c = np.where(valid, c_m / gain, c_m)
        b = np.where(valid, (b_m - shift) / gain, b_m)
        b = np.clip(b, -0.95 * c, 0.95 * c)
        cur = cal_m.replace(contrast=c.reshape(shape).astype(cal_m.contrast.dtype),
                            bias=b.reshape(shape).astype(cal_m.bias.dtype))
    report: dict[str, Any] = {
        "effects": {n: e.parameters() for n, e in eff.items()},
        "n_seeds": cfg.n_seeds, "iterations": cfg.iterations,
        "denoise_us": window_us,
        "denoise_same_polarity": cfg.denoise_same_polarity,
        "denoise_two_sided": cfg.denoise_two_sided,
        "still_max_dl": still_dl,
        "denoise_kept_fraction": rec.n_events / n_in if n_in else 1.0,
        "cells": int(np.unique(cells).size),
        "noise_scale": {"contrast": scale.contrast, "bias": scale.bias,
                        "n_pixels": scale.n_pixels, "reason": scale.reason},
        "gain_median": float(np.median(gain[valid])) if valid.any() else 1.0,
        "gain_range": [float(gain[valid].min()), float(gain[valid].max())]
        if valid.any() else [1.0, 1.0],
        "bias_shift_median": float(np.median(shift[valid])) if valid.any() else 0.0,
        "bias_shift_range": [float(shift[valid].min()), float(shift[valid].max())]
        if valid.any() else [0.0, 0.0],
    }
    diag = cur.diagnostics.updated(model_correction=report)
    return cur.replace(diagnostics=diag)
