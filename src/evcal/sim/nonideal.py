"""The non-ideal simulator: the ideal one (same config, maps, scenes, crossings) plus effects.

:func:`simulate` draws the per-pixel ``c``, ``b`` maps exactly as
:func:`~evcal.sim.ideal.simulate_ideal` does (:func:`~evcal.sim.ideal.draw_maps`, same seed,
same reference initialisation), renders the intensity at the internal rate
(:func:`~evcal.sim.ideal.internal_times_us`) in blocks of ``chunk_steps`` (through the
source's ``render_block`` where it has one), and runs the numba kernel of
:mod:`evcal.sim.kernel` over each block, appending to event buffers kept for the whole run
(the kernel sorts each step's events, so steps come out in time order). Effects that need no
per-pixel sequence (hot pixels, row noise, timestamp jitter) are applied to the event arrays
afterwards. With no effect it reproduces the ideal simulator's events.

The simulator names no effect: it asks each, through the hooks of
:class:`~evcal.sim.effects.Effect`, stage by stage in the fixed order of
:func:`~evcal.sim.effects.simulation_order` (the stages and the order are in the module doc
of :mod:`evcal.sim.effects`): the frame model, the log offset, the kernel's parameters
(:class:`~evcal.sim.effects.KernelParams`), the events after the kernel, their timestamps.
What effects tell each other goes through the run's :class:`~evcal.sim.effects.SimContext`.

Truth (``SimResult.truth``): ``contrast``, ``bias`` maps, the effective ``log_offset``, the
``seed``, ``effects`` (``{name: parameters}``), ``labels`` (uint8 per event, see
:data:`~evcal.sim.effects.LABEL_LEGEND`), ``leak_rate_hz`` map and ``hot_pixels`` mask.
Deterministic for a seed: every random draw comes from ``np.random.default_rng(cfg.seed)``
and generators spawned from it: the maps and the initial references from it, then five
spawned in this order for the kernel (``SimContext.rng_kernel``: the per-pixel generator
states first, then the effects' draws), the events added after the kernel, the timestamps,
the APS frames' read noise and the per-pixel parameter maps; an effect may spawn more
(``SimContext.spawn_rng``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from ..errors import ConfigError
from ..events import EVENTS_DTYPE
from ..recording import Frames, Recording
from .effects import (
    LABEL_LEGEND,
    ApsConfig,
    Effect,
    KernelParams,
    SimContext,
    SimEvents,
    describe,
    effect_set,
    simulation_order,
)
from .ideal import SimConfig, SimResult, draw_maps, frame_times_us, internal_times_us
from .kernel import concat_runs, fill_events, merge_runs, run_steps
from .sources import MovingScene

Source = Callable[[float], np.ndarray]


def effective_log_offset(cfg: SimConfig, effects: Mapping[str, Effect]) -> float:
    """The log offset the sensor sees: the config's nominal one as the ``effects`` change it
    (:meth:`~evcal.sim.effects.Effect.log_offset`; ``dark_dn`` of a ``log_offset`` effect)."""
    offset = float(cfg.log_offset)
    for e in simulation_order(effects.values()):
        offset = float(e.log_offset(offset))
    return offset


class _LitSource:
    """``source`` (a callable of time in seconds, relative to the run) under the light
    factors of the effects with an ``on_light`` hook (functions of output time): what the
    events and the frames both see. Keeps the source's ``render_block`` where it has one."""

    def __init__(self, source: Source, effects: list[Effect], t_origin_us: int):
        self.source = source
        self.effects = effects
        self.t_origin_s = int(t_origin_us) * 1e-6
        if getattr(source, "render_block", None) is not None:
            self.render_block = self._render_block

    def factor(self, t_s: np.ndarray | float) -> np.ndarray:
        t = np.asarray(t_s, np.float64) + self.t_origin_s
        out = np.ones(t.shape)
        for e in self.effects:
            g = e.on_light(t)
            if g is not None:
                out = out * g
        return out

    def __call__(self, t_s: float) -> np.ndarray:
        img = np.asarray(self.source(t_s), np.float32)
        out: np.ndarray = img * np.float32(self.factor(t_s))
        return out

    def _render_block(self, t_s: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        block = np.asarray(self.source.render_block(t_s, out=out), np.float32)  # type: ignore[attr-defined]
        g = self.factor(t_s).astype(np.float32).reshape((-1,) + (1,) * (block.ndim - 1))
        # a new array: the source may hand out a cached render
        result: np.ndarray = block * g
        return result


def _aps_frame(source: Source, t_us: int, aps: ApsConfig, rng: np.random.Generator,
               first: np.ndarray | None = None) -> np.ndarray:
    """The APS frame stamped ``t_us``: the intensity averaged over the exposure (centred
    ``aps.centre_lag_us`` after the stamp), plus the pixels' dark offsets (DSNU, which only
    the frame readout sees), read noise, quantisation."""
    centre_us = t_us + aps.centre_lag_us
    if aps.exposure_us > 0:
        offs = (np.arange(aps.blur_samples) + 0.5) / aps.blur_samples - 0.5
        img = np.mean([source(max(0.0, (centre_us + o * aps.exposure_us) * 1e-6))
                       for o in offs], axis=0)
    elif centre_us != t_us or first is None:
        img = source(max(0.0, centre_us * 1e-6))
    else:
        img = first
    img = np.asarray(img, np.float64)
    dark = aps.dark_offsets_dn(img.shape[-2:])
    if dark is not None:
        img = img + dark
    if aps.read_noise_dn > 0:
        img = img + rng.normal(0.0, aps.read_noise_dn, img.shape)
    if aps.quantise:
        result: np.ndarray = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        return result
    result_72: np.ndarray = np.maximum(img, 0.0).astype(np.float32)
    return result_72


def _resized(buf: np.ndarray, size: int, n: int) -> np.ndarray:
    out = np.empty(size, buf.dtype)
    out[:n] = buf[:n]
    return out


def simulate(
    cfg: SimConfig,
    effects: Iterable[Effect] | Mapping[str, Effect] | None = (),
    *,
    aps: ApsConfig | None = None,
    source: Source | None = None,
    maps: tuple[np.ndarray, np.ndarray] | None = None,
    frames: Frames | None = None,
    times_us: np.ndarray | None = None,
    t_origin_us: int = 0,
    chunk_steps: int = 64,
    progress: Callable[[int], None] | None = None,
    expected_events: int = 0,
    threads: int = 1,
) -> SimResult:
    """Simulate a recording with the given effects.

    Parameters
    ----------
    cfg
        Sensor size, duration, rates, map statistics, scene, trajectory and seed.
    effects
        Any of :data:`~evcal.sim.effects.EFFECTS` (or other
        :class:`~evcal.sim.effects.Effect` subclasses), at most one of each name.
    aps
        Frame model (default: instantaneous frames, quantised when ``cfg.quantise_frames``).
    source
        Intensity ``t_s -> [H, W]`` in DN; default the moving photo of ``cfg``.
    maps
        ``(contrast, bias)`` to use instead of drawing them from ``cfg`` (the draw is skipped,
        the rest of the random stream is unchanged in kind).
    frames
        Frames to attach to the recording instead of rendering APS frames (e.g. the measured
        frames that drive a re-simulation).
    times_us
        Internal sample times (relative, from 0); default :func:`internal_times_us` of ``cfg``.
    t_origin_us
        Added to every timestamp of the output (not to ``frames``, which are kept as given).
    expected_events
        About how many events the run will make (e.g. those of the recording it re-simulates):
        the event buffers start that large, instead of growing as the run goes.
    threads
        Ranges of pixels simulated side by side (the events do not depend on it).

    Examples
    --------
    >>> from evcal.sim.ideal import SimConfig
    >>> from evcal.sim.effects import Refractory
    >>> res = simulate(SimConfig(height=16, width=20, duration_s=0.2, seed=1),
    ...                [Refractory(period_us=500.0)])
    >>> res.recording.n_events == res.truth["labels"].size
    True
    """
    eff = effect_set(effects)
    ordered = simulation_order(eff.values())
    # the frame-side effects (Effect.on_aps) act on the APS frames only
    aps = (aps if aps is not None else ApsConfig(quantise=cfg.quantise_frames)).with_effects(eff)
    rng = np.random.default_rng(cfg.seed)
    if maps is None:
        c, b = draw_maps(cfg, rng)
    else:
        c, b = (np.asarray(m, np.float64) for m in maps)
        if c.shape != (cfg.height, cfg.width) or b.shape != c.shape:
            raise ConfigError(f"maps have shapes {c.shape}, {b.shape}; the sensor is "
                             f"{cfg.width}x{cfg.height}")
    th_on_nom = (c + b).ravel().copy()
    th_off_nom = (c - b).ravel().copy()
    if (th_on_nom <= 0).any() or (th_off_nom <= 0).any():
        raise ConfigError("every pixel needs c + b > 0 and c - b > 0 (|b| < c)")
    if source is None:
        source = MovingScene(cfg.scene, (cfg.height, cfg.width), cfg.trajectory,
                             min_dn=cfg.min_dn, max_dn=cfg.max_dn)
    lights = [e for e in ordered if "on_light" in e.hooks()]
    if lights:
        source = _LitSource(source, lights, int(t_origin_us))
    times = internal_times_us(cfg) if times_us is None else np.asarray(times_us, np.int64)
    if times.size < 2 or (np.diff(times) <= 0).any():
        raise ConfigError("internal sample times must be at least two, increasing")
    offset = effective_log_offset(cfg, eff)
    npix = cfg.height * cfg.width

    i0 = np.asarray(source(times[0] * 1e-6), np.float32)
    # as IdealDvs.reset: residual L - ref uniform in (-th_off, th_on) (the comparator's input
    # L is known once the effects have set the kernel's parameters, below)
    u = rng.uniform(0.0, 1.0, npix)
    # one stream per stage, spawned in this fixed order so that no draw moves (the events'
    # stream serves hot pixels, the stamps' the jitter, the maps' the leak rates)
    r_kernel, r_events, r_stamps, r_aps, r_maps = rng.spawn(5)
    rng_state = r_kernel.integers(1, 2**63 - 1, npix, dtype=np.uint64)
    ctx = SimContext(shape=(cfg.height, cfg.width), times_us=times,
                     t_origin_us=int(t_origin_us), log_offset=offset, rng_kernel=r_kernel,
                     rng_maps=r_maps, rng_events=r_events, rng_timestamps=r_stamps,
                     root_rng=rng,
                     stamps_apply_dead_time=any(e.applies_dead_time() for e in ordered))
    kp = KernelParams.ideal(th_on_nom, th_off_nom)
    for e in ordered:
        e.kernel_setup(kp, ctx)
    l0 = kp.comparator_input(i0, offset)
    ref = l0 - (u * (th_on_nom + th_off_nom) - th_off_nom)
    if kp.start_reset:
        ref = l0.copy()
    refr_us, refr_delay = kp.refr_us, kp.refr_delay

    lf = l0.copy()
    lf_ok = np.ones(npix, np.uint8)
    i_prev = i0.astype(np.float32).ravel()
    # intensity-domain bounds of the levels; 0 until a pixel's first step computes them
    hi_i = np.zeros(npix, np.float32)
    lo_i = np.zeros(npix, np.float32)
    ref_i = ref.copy()
    dead = np.full(npix, -np.inf)
    last_fire = np.full(npix, -np.inf)
    debt = np.zeros(npix)

    frame_t = frame_times_us(cfg) if frames is None else np.zeros(0, np.int64)
    frame_t = frame_t[np.isin(frame_t, times)]
    frame_pos = 0
    f_t: list[int] = []
    f_img: list[np.ndarray] = []
    if frame_t.size and frame_t[0] == times[0]:
        f_t.append(int(times[0]))
        f_img.append(_aps_frame(source, int(times[0]), aps, r_aps, i0))
        frame_pos = 1

    render_block = getattr(source, "render_block", None)
    n_steps = times.size - 1
    block_buf = np.empty((min(chunk_steps, n_steps), cfg.height, cfg.width), np.float32)
    # pixel ranges simulated side by side (their events merged by time are those of one run
    # over all pixels: the thread count changes the speed, not the events)
    bounds = np.linspace(0, npix, max(1, min(int(threads), npix)) + 1).astype(np.int64)
    ranges = [(int(p0), int(p1)) for p0, p1 in zip(bounds[:-1], bounds[1:], strict=True)
              if p1 > p0]
    # event buffers for the whole run per range, grown by the kernel when full and ahead of
    # it when the rate so far says they will be (one early copy instead of doublings)
    parts: list[list[Any]] = []
    for p0, p1 in ranges:
        share = (p1 - p0) / npix
        cap = max(4096, int((p1 - p0) * min(n_steps, chunk_steps) * 0.02),
                  int(1.2 * expected_events * share))
        parts.append([np.empty(cap, np.float64), np.empty(cap, np.int64),
                      np.empty(cap, np.int32), np.empty(cap, np.int8), np.empty(cap, np.uint8),
                      0])
    pool = ThreadPoolExecutor(len(ranges)) if len(ranges) > 1 else None
    k = 0
    try:
        while k < n_steps:
            kk = min(chunk_steps, n_steps - k)
            t_blk = times[k + 1 : k + kk + 1]
            if render_block is not None:
                block = np.asarray(render_block(t_blk * 1e-6, out=block_buf[:kk]),
                                   np.float32).reshape(kk, npix)
            else:
                block = block_buf[:kk].reshape(kk, npix)
                for j in range(kk):
                    block[j] = np.asarray(source(int(t_blk[j]) * 1e-6), np.float32).ravel()
            for j in range(kk):
                t = int(t_blk[j])
                if frame_pos < frame_t.size and frame_t[frame_pos] == t:
                    f_t.append(t)
                    f_img.append(_aps_frame(source, t, aps, r_aps,
                                            block[j].reshape(cfg.height, cfg.width)))
                    frame_pos += 1
            t_chunk = times[k : k + kk + 1]

            def run_range(j: int, block: np.ndarray = block, t_chunk: np.ndarray = t_chunk
                          ) -> None:
                part = parts[j]
                part[:] = run_steps(
                    block, t_chunk, offset, lf, lf_ok, i_prev, hi_i, lo_i, ref_i, ref,
                    kp.th_on_nom, kp.th_off_nom, kp.th_on, kp.th_off, dead, last_fire,
                    kp.leak_rate_hz, debt, rng_state, kp.shot_next_us, kp.th_sigma, refr_us,
                    refr_delay, kp.leak_exp, kp.leak_ref_dn, kp.shot_rate_hz, kp.shot_ref_dn,
                    kp.shot_exp, kp.bw_cutoff_hz, kp.bw_ref_dn, kp.bw_min_cutoff_hz,
                    kp.response_exp, kp.response_ref_dn, *part, p0=ranges[j][0],
                    p1=ranges[j][1])

            if pool is None:
                run_range(0)
            else:
                list(pool.map(run_range, range(len(ranges))))
            k += kk
            for part in parts:
                n_part = part[5]
                want = int(1.1 * n_part * n_steps / k) + 1024
                if k < n_steps and want > part[0].size:
                    # by half again at least: the projection creeps up chunk by chunk as the
                    # scene gets busier, and a copy per chunk would cost a tenth of the run
                    want = max(want, part[0].size + part[0].size // 2)
                    part[:5] = [_resized(buf, want, n_part) for buf in part[:5]]
            if progress is not None:
                progress(k)
    finally:
        if pool is not None:
            pool.shutdown()

    buf_tf, buf_ti, buf_pix, buf_p, buf_lab, n_ev = parts[0]
    for part in parts[1:]:
        # in delay mode the runs are not in time order yet: sorted below, from the
        # concatenation (two pixels' events at one float time would come in range order,
        # where one run has them in the order of their steps: times drawn and interpolated
        # in floats do not meet so)
        buf_tf, buf_ti, buf_pix, buf_p, buf_lab = (
            merge_runs if not refr_delay or refr_us <= 0 else concat_runs)(
            buf_tf, buf_ti, buf_pix, buf_p, buf_lab, n_ev, *part)
        n_ev += part[5]
    t_int, pix, pol, lab = buf_ti[:n_ev], buf_pix[:n_ev], buf_p[:n_ev], buf_lab[:n_ev]
    if refr_delay and refr_us > 0:
        # delayed events can leave their step: the kernel leaves those in emission order
        order = np.argsort(buf_tf[:n_ev], kind="stable")
        t_int, pix, pol, lab = t_int[order], pix[order], pol[order], lab[order]

    events = SimEvents(t_int, pix, pol, lab)
    for e in ordered:
        events = e.after_kernel(events, ctx)
    if t_origin_us:
        events = events._replace(t_us=events.t_us + int(t_origin_us))
    for e in ordered:
        events = e.on_timestamps(events, ctx)
    t_int, pix, pol, lab = events

    ev = np.empty(t_int.size, EVENTS_DTYPE)
    fill_events(ev["t_us"], ev["x"], ev["y"], ev["p"], t_int, pix, pol, cfg.width)
    if frames is None:
        if f_img:
            frames = Frames(t_us=np.asarray(f_t, np.int64) + int(t_origin_us),
                            images=np.stack(f_img),
                            exposure_us=np.full(len(f_t), int(aps.exposure_us), np.int64))
        else:
            frames = Frames.empty(cfg.height, cfg.width)
    rec = Recording(cfg.sensor, ev, frames, {
        "source": "evcal.sim.nonideal", "sim_config": cfg.to_dict(),
        "effects": describe(eff), "aps": vars(aps).copy() if hasattr(aps, "__dict__") else {},
    })
    # the per-pixel truth maps every result has (none of them: zeros), and any an effect adds
    pixel_truth = {"leak_rate_hz": kp.leak_rate_hz.astype(np.float32),
                   "hot_pixels": np.zeros(npix, bool), **ctx.pixel_truth}
    truth: dict[str, Any] = {
        "contrast": c.astype(np.float32),
        "bias": b.astype(np.float32),
        "log_offset": offset,
        "seed": int(cfg.seed),
        "effects": describe(eff),
        "labels": lab,
        "label_legend": dict(LABEL_LEGEND),
        **{k: v.reshape(cfg.height, cfg.width) for k, v in pixel_truth.items()},
    }
    return SimResult(rec, truth)
