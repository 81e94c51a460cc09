"""The gap workflow's evaluations of models (:class:`Evaluator`): anchored, simulated with the
run's seeds (or screened with one, on a band of rows), summarised and compared with the
measurement, on every row and on the held-out rows; the configuration (:class:`GapConfig`)
and what the workflow keeps of each model (:class:`Evaluation`).

Held-out rows: a candidate effect is fitted on the even rows of the sensor (the *fit*
rows) and judged by the discrepancy on the odd rows (the *held-out* rows), which its fit has
not seen. A parameter fitted to the noise of some pixels then gains nothing on the others,
however many parameters it has (a per-pixel map included). The gap the report gives is that
of every row.

The evaluator holds no state of the search: the run (:mod:`.workflow`) owns its rounds.
"""

from __future__ import annotations

import math
import threading
import weakref
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any

import numpy as np

from ..errors import ConfigError
from ..online import usable_cores
from ..recording import Recording
from ..sim.effects import Effect
from . import effects as registry
from .compare import Discrepancy, discrepancy
from .effects import FitContext
from .model import (
    Band,
    Model,
    SimSettings,
    anchor,
    estimate_read_noise,
    fit_base,
    population,
    simulate_model,
    subframe_shift,
)
from .render import RenderCache
from .stats import GapError, Observation, StatValue, observe, rows_of, summarise


@dataclass(frozen=True, kw_only=True)
class GapConfig:
    max_effects: int = 3
    seed: int = 0
    n_seeds: int = 3
    internal_rate_hz: float = 1000.0
    interpolation: str = "flow"  # between frames: "flow" (evcal.gap.flow) or "linear"
    # the image's motion between frames off the straight path read from the events
    # (evcal.gap.motion; with "flow" only)
    subframe_motion: bool = True
    # timing statistics only in windows whose flow is consistent and at most this many pixels
    # (evcal.gap.flow.trusted_windows) and whose frames are not clipped at full scale
    # (unclipped_windows); None: every window
    trusted_max_px: float | None = math.inf
    penalty_per_parameter: float = 0.1
    min_improvement: float = 0.3
    min_relative_improvement: float = 0.25
    # a candidate is named only when at least this share of what an even spread over every
    # statistic would put there of its held-out gain falls on the statistics its effect
    # moves (evcal.gap.search.signature_ok); 0 turns the check off
    min_signature_share: float = 0.5
    refine: bool = True
    # once nothing more is named, each sensor effect named before the last is refined
    # again (the three-point search) in the final model: its value was settled in a model
    # that lacked the effects named after it, which may explain part of what it took on
    refit_named: bool = True
    # then each sensor effect of a final model of two or more taken out in turn: one whose
    # absence costs less on the held-out rows than naming needs is dropped (a single named
    # early that a pair named later makes redundant)
    prune_named: bool = True
    # bias-correct each named effect's moment estimate by refitting it on the simulations
    # made with it (see evcal.gap.finish.debias)
    debias: bool = True
    candidates: tuple[str, ...] = field(default_factory=registry.names)
    # screening: every candidate is simulated with one seed (the spread of the statistics
    # from the current model's seeds) and only the best ``confirm_top`` with all of them
    screen: bool = True
    confirm_top: int = 2
    # two effects at once when no single one is named and the held-out gap is still above
    # pair_min_gap: pairs of the pair_top best candidates of the round, the second fitted on
    # the simulations of the first (effects that explain the data only together, such as a
    # frame lag and a dark level whose lags and sensitivities interlock); 0 turns it off
    pair_top: int = 5
    pair_min_gap: float = 3.0
    # a fitted value is a candidate only when its strength (evcal.gap.effects) exceeds this
    # many times the largest the fitter reads on the current model's own simulations (the
    # null calibration, evcal.gap.null)
    null_factor: float = 2.0
    # the workflow analyses at most this many pixel-steps of simulation (pixels x internal
    # samples): a longer recording is cut to its busiest contiguous frames that fit (the
    # statistics need events, not hours; the rendered frames stay in memory)
    max_pixel_steps: int = 250_000_000
    # ... and at most this many events: each statistic's bins then hold enough events that
    # the comparison's relative floor (3 % of the simulated mean, see evcal.gap.compare), not
    # the count, sets its resolution; more events cost memory and time in proportion and
    # sharpen nothing (None: no limit)
    max_events: int | None = 4_000_000
    # threads that simulate at once (None: the usable cores)
    workers: int | None = None
    # screening on a band of sensor rows: this share of the rows (the busiest contiguous
    # ones), when the recording has more than ``screen_band_min`` pixel-steps; the spread of
    # the statistics and the measurement's are then the band's too
    screen_rows: float = 0.25
    screen_band_min: int = 40_000_000

    def __post_init__(self) -> None:
        if self.max_effects < 0:
            raise ConfigError(f"max_effects={self.max_effects} must be >= 0")
        if self.n_seeds < 3:
            raise ConfigError(f"n_seeds={self.n_seeds} must be >= 3 (the spread needs two, "
                              "the null calibration one more)")
        if self.pair_top < 0:
            raise ConfigError(f"pair_top must be >= 0, got {self.pair_top}")
        if self.confirm_top < 1:
            raise ConfigError(f"confirm_top={self.confirm_top} must be >= 1")
        if not self.min_signature_share >= 0.0:
            raise ConfigError(f"min_signature_share={self.min_signature_share} must be >= 0")
        if not self.null_factor >= 1.0:
            raise ConfigError(f"null_factor={self.null_factor} must be >= 1")
        if self.max_pixel_steps < 1_000_000:
            raise ConfigError(f"max_pixel_steps={self.max_pixel_steps} must be >= 1e6")
        if self.max_events is not None and self.max_events < 10_000:
            raise ConfigError(f"max_events={self.max_events} must be >= 10000")
        if not 0.0 < self.screen_rows <= 1.0:
            raise ConfigError(f"screen_rows={self.screen_rows} must be in (0, 1]")
        if self.workers is not None and self.workers < 1:
            raise ConfigError(f"workers={self.workers} must be >= 1")
        unknown = set(self.candidates) - set(registry.names())
        if unknown:
            raise ConfigError(f"unknown candidate effect(s) {sorted(unknown)}; known: "
                              f"{', '.join(registry.names())}")


@dataclass
class Evaluation:
    """A model, its simulations (during a run; none in a :class:`~.workflow.GapResult`)
    and its discrepancy with the measurement on every row (``disc``) and on the held-out
    rows (``held``)."""

    model: Model
    sims: list[Observation]
    disc: Discrepancy
    held: Discrepancy
    summaries: list[dict[str, StatValue]] = field(default_factory=list)
    held_summaries: list[dict[str, StatValue]] = field(default_factory=list)
    # screened on the run's band of rows (GapConfig.screen_rows): its statistics and sims are
    # the band's, ``model`` the whole sensor's (not anchored yet: confirm() evaluates it)
    on_band: bool = False

    @property
    def gap(self) -> float:
        return self.disc.gap

    @property
    def held_gap(self) -> float:
        """The gap on the held-out rows: what candidates are judged by."""
        return self.held.gap

    @property
    def screened(self) -> bool:
        """Evaluated on one seed only (its spread borrowed): a candidate not yet confirmed."""
        return self.disc.n_sims < 2

    def lightened(self) -> Evaluation:
        """This evaluation without its simulations and summaries (what a result keeps)."""
        return Evaluation(self.model, [], self.disc, self.held, on_band=self.on_band)


def _empty() -> Discrepancy:
    return Discrepancy({}, {}, {}, {}, {}, {}, 0)


@dataclass
class _Measurement:
    """The measurement as one evaluation compares with it: its observation on the rows
    simulated (the whole sensor or the band), and its statistics there and on the held-out
    rows among them."""

    obs: Observation
    stats: dict[str, StatValue]
    held_rows: np.ndarray
    fit_rows: np.ndarray
    held_stats: dict[str, StatValue]
    held_cache: dict[str, Any]
    fit_cache: dict[str, Any]

    @classmethod
    def of(cls, obs: Observation, first_row: int) -> _Measurement:
        """``obs`` (rows ``first_row`` on of the sensor): the held-out rows are the odd rows
        of the sensor, the fit rows the even ones."""
        h = obs.shape[0]
        r = np.arange(h)
        held_rows = r[(r + first_row) % 2 == 1]
        fit_rows = r[(r + first_row) % 2 == 0]
        held_cache: dict[str, Any] = {}
        held = summarise(rows_of(obs, held_rows, held_cache))
        return cls(obs, summarise(obs), held_rows, fit_rows, held, held_cache, {})

    def held_of(self, obs: Observation) -> Observation:
        return rows_of(obs, self.held_rows, self.held_cache)

    def fit_of(self, obs: Observation) -> Observation:
        return rows_of(obs, self.fit_rows, self.fit_cache)


class Evaluator:
    """Evaluations of models against one measured recording (see the module docstring):
    the measurement's statistics, the simulation settings, the seeds (common random
    numbers: every model is simulated with the same ones), the render cache and the count of
    simulations run."""

    def __init__(self, rec: Recording, cfg: GapConfig, tick: Callable[[float], None],
                 released: Callable[[], object] | None = None):
        self.rec = rec
        # called whenever the run has let go of simulations (the command line hands the
        # freed memory back to the system there)
        self.released = released or (lambda: None)
        self.cfg = cfg
        self.tick = tick
        self.trusted = None
        if cfg.trusted_max_px is not None:
            from .flow import trusted_windows, unclipped_windows  # noqa: PLC0415

            self.trusted = (trusted_windows(rec.frames, max_px=cfg.trusted_max_px)
                            & unclipped_windows(rec.frames))
        self.meas_obs = observe(rec, trusted=self.trusted)
        self.whole = _Measurement.of(self.meas_obs, 0)
        self.meas_pop = population(self.meas_obs)
        self.settings = SimSettings(internal_rate_hz=cfg.internal_rate_hz,
                                    read_noise_dn=estimate_read_noise(rec.frames),
                                    interpolation=cfg.interpolation)
        self.shift_info: dict[str, float] = {}
        if cfg.subframe_motion and cfg.interpolation == "flow":
            shift, self.shift_info = subframe_shift(rec, self.settings, self.meas_pop)
            self.settings = replace(self.settings, shift=shift)
        # the recording's median frame value (DN): where light-dependent laws are read
        self.light_dn = float(np.median(rec.frames.images))
        self.seeds = [cfg.seed * 1000 + k for k in range(cfg.n_seeds)]
        self.workers = cfg.workers or usable_cores()
        self.render = RenderCache(on_use=self._counted, workers=self.workers)
        self.simulations = 0
        self.work = 0.0  # simulations done, in simulations of the whole sensor
        self._lock = threading.Lock()
        self.band = screening_band(rec, cfg)
        self.on_band: _Measurement | None = None
        self.trusted_band = None
        if self.band is not None:
            rows = self.band.rows
            w = rec.sensor.width
            self.trusted_band = None if self.trusted is None else \
                self.trusted[:, rows.start * w:rows.stop * w]
            self.on_band = _Measurement.of(observe(self.band.rec, trusted=self.trusted_band),
                                           rows.start)
        # the band's discrepancies of an evaluation whose spread screenings borrow, by id
        # (held weakly: the cache must not keep an evaluation's simulations alive)
        self._band_spread: dict[int, tuple[weakref.ref[Evaluation],
                                           tuple[Discrepancy, Discrepancy]]] = {}

    # ------------------------------------------------------------------ the measurement

    @property
    def meas(self) -> Observation:
        return self.meas_obs

    @property
    def meas_stats(self) -> dict[str, StatValue]:
        return self.whole.stats

    def fit_context(self, model: Model, sims: list[Observation], *, held_out: bool = True,
                    meas: Observation | None = None) -> FitContext:
        """What a fitter sees of ``model`` and its (whole-sensor) simulations ``sims``: the
        fit rows only when ``held_out``, else every row. ``meas`` in place of the
        measurement (the null calibration's pseudo-measurements, simulations themselves)."""
        m = self.meas_obs if meas is None else meas
        if not held_out:
            return FitContext(m, list(sims), model, self.rec, m, None, self.cfg.seed,
                              simulate=partial(self.simulate_with, model, rows=False))
        w = self.whole
        return FitContext(w.fit_of(m), [w.fit_of(s) for s in sims],
                          model_on_rows(model, w.fit_rows), self.rec, m, w.fit_rows,
                          self.cfg.seed, simulate=partial(self.simulate_with, model))

    def simulate_with(self, model: Model, eff: Effect, *, rows: bool = True) -> Observation:
        """``model`` with ``eff`` added, simulated on the first seed (not anchored: a
        fitter's trial), its observation on the fit rows (as a held-out fit sees them;
        every row with ``rows=False``)."""
        obs = observe(simulate_model(model.with_effect(eff), self.rec, self.seeds[0],
                                     self.settings, self.render), trusted=self.trusted)
        self._counted(1.0)
        return self.whole.fit_of(obs) if rows else obs

    # -------------------------------------------------------------------- simulations

    def _counted(self, share: float) -> None:
        """One more simulation, of ``share`` of the sensor's rows (the render cache serves
        each one once)."""
        with self._lock:
            self.simulations += 1
            self.work += share
        self.tick(share)

    def _simulate(self, model: Model, seed: int, target: _Measurement,
                  band: Band | None) -> tuple[Observation, dict[str, StatValue],
                                              dict[str, StatValue]]:
        trusted = self.trusted if band is None else self.trusted_band
        obs = observe(simulate_model(model, self.rec, seed, self.settings, self.render, band),
                      trusted=trusted)
        return _summarised(target, obs)

    def evaluate(self, model: Model, what: str, *, spread: Evaluation | None = None
                 ) -> Evaluation:
        """Anchor ``model`` and simulate it with every seed (in parallel), or, with
        ``spread``, with the first seed only (a screening; the seed-to-seed spread is
        ``spread``'s)."""
        if spread is not None and self.band is not None:
            return self.screen_on_band(model, spread)
        model, first = anchor(model, self.rec, self.meas_obs, self.seeds[0], self.settings,
                              render=self.render, trusted=self.trusted)
        sims = [first] if first is not None else []
        n = 1 if spread is not None else len(self.seeds)
        ev = Evaluation(model, sims, _empty(), _empty())
        return self.extend(ev, n, what, spread=spread)

    def extend(self, ev: Evaluation, n: int, what: str, *, spread: Evaluation | None = None
               ) -> Evaluation:
        """``ev`` with simulations up to ``n`` seeds (the missing ones run in parallel, each
        summarised in its thread, beside the summaries ``ev`` still lacks). An evaluation
        that let go of its simulations (a round's candidates not kept) is simulated anew:
        its summaries would otherwise count its first seed twice."""
        if len(ev.sims) < len(ev.summaries):
            ev = Evaluation(ev.model, [], ev.disc, ev.held)
        todo = self.seeds[len(ev.sims):n]
        sims = list(ev.sims)
        unsummarised = sims[len(ev.summaries):]
        target = self.whole
        jobs: list[Callable[[], tuple[Observation, dict[str, StatValue],
                                      dict[str, StatValue]]]] = [
            partial(_summarised, target, o) for o in unsummarised]
        jobs += [partial(self._simulate, ev.model, s, target, None) for s in todo]
        done = _run_all(jobs, self.workers)
        sims = sims[:len(ev.summaries)] + [o for o, _, _ in done]
        summaries = list(ev.summaries) + [s for _, s, _ in done]
        held = list(ev.held_summaries) + [h for _, _, h in done]
        # the derived arrays (per-window fits, intervals, per-event windows: half an
        # observation's memory, more with many events) are dropped once summarised; the
        # fitters recompute them on the few simulations they read (Observation.extra is a
        # cache), the others would hold them as long as their evaluation lives
        for o in sims:
            o.extra.clear()
        borrowed = spread if len(sims) < 2 else None
        disc = discrepancy(target.stats, summaries,
                           spread=None if borrowed is None else borrowed.disc)
        held_disc = discrepancy(target.held_stats, held,
                                spread=None if borrowed is None else borrowed.held)
        return Evaluation(ev.model, sims, disc, held_disc, summaries, held)

    def confirm(self, ev: Evaluation, what: str) -> Evaluation:
        """A screened evaluation completed with every seed (on the band: evaluated anew on
        the whole sensor)."""
        if ev.on_band:
            # anchored anew on the whole sensor: started from the band anchor's correction, a
            # first simulation within tolerance stands with maps less well anchored than the
            # correction of the whole sensor's own fits gives, and the gaps compared carry it
            return self.evaluate(ev.model, what)
        return self.extend(ev, len(self.seeds), what) if ev.screened else ev

    def screen_on_band(self, model: Model, spread: Evaluation | None, n: int = 1
                       ) -> Evaluation:
        """``model`` on the band's rows with the first ``n`` seeds: anchored there, its
        statistics against the band's measurement; with one seed (a screening) the spread
        is that of ``spread``'s simulations cut to the band."""
        band, target = self.band, self.on_band
        assert band is not None
        assert target is not None
        m_band, first = anchor(band.model(model), self.rec, target.obs, self.seeds[0],
                               self.settings, render=self.render, trusted=self.trusted_band,
                               band=band)
        jobs: list[Callable[[], tuple[Observation, dict[str, StatValue],
                                      dict[str, StatValue]]]] = [
            partial(_summarised, target, first) if first is not None
            else partial(self._simulate, m_band, self.seeds[0], target, band)]
        jobs += [partial(self._simulate, m_band, s, target, band) for s in self.seeds[1:n]]
        done = _run_all(jobs, self.workers)
        sims = [o for o, _, _ in done]
        if n == 1:
            sims[0].extra.clear()
        spreads = self.band_spread(spread) if n == 1 and spread is not None else None
        disc = discrepancy(target.stats, [s for _, s, _ in done],
                           spread=None if spreads is None else spreads[0])
        held = discrepancy(target.held_stats, [h for _, _, h in done],
                           spread=None if spreads is None else spreads[1])
        return Evaluation(model, sims, disc, held, [s for _, s, _ in done],
                          [h for _, _, h in done], on_band=True)

    def band_spread(self, ev: Evaluation) -> tuple[Discrepancy, Discrepancy]:
        """``ev``'s discrepancies on the band (its simulations cut to the band's rows; on
        every row of it and on its held-out rows): the spread that screenings on the band
        borrow."""
        hit = self._band_spread.get(id(ev))
        if hit is not None and hit[0]() is ev:
            return hit[1]
        if len(ev.sims) < 2:
            raise GapError("a screening on the band needs an evaluation with simulations on "
                           "every seed for its spread")
        assert self.band is not None
        assert self.on_band is not None
        target = self.on_band
        done = [_summarised(target, rows_of(o, self.band.rows)) for o in ev.sims]
        discs = (discrepancy(target.stats, [s for _, s, _ in done]),
                 discrepancy(target.held_stats, [h for _, _, h in done]))
        if len(self._band_spread) >= 4:  # the round's current and best are what is asked for
            self._band_spread.pop(next(iter(self._band_spread)))
        self._band_spread[id(ev)] = (weakref.ref(ev), discs)
        return discs

    def screen_gap(self, ev: Evaluation) -> float:
        """The held-out gap a screening on ``ev`` is compared with (the band's, on a
        band)."""
        if self.band is not None:
            return self.band_spread(ev)[1].gap
        return ev.held_gap

    # ------------------------------------------------------------------------ models

    def candidate_model(self, current: Model, eff: Effect) -> Model:
        if eff.name == "log_offset":
            base = fit_base(self.rec, log_offset=float(eff.parameters()["dark_dn"]))
            m = Model(base.contrast, base.bias, base.log_offset, dict(current.effects))
            return m.with_effect(eff)  # refitted maps: not anchored
        return current.with_effect(eff)

    def model_without(self, current: Model, name: str) -> Model:
        """``current`` without effect ``name`` (without a dark level, the maps refitted at
        the nominal log offset; not anchored)."""
        effects = {k: v for k, v in current.effects.items() if k != name}
        if name == "log_offset":
            base = fit_base(self.rec)
            return Model(base.contrast, base.bias, base.log_offset, effects)
        return replace(current, effects=effects)

    def near_model(self, current: Model, near: Model, eff: Effect) -> Model:
        """``eff`` (a new value of an effect ``near`` has) on top of ``current``, starting
        from ``near``'s anchored maps when they are (the anchor then starts close to where
        it ends, often taking one simulation)."""
        if eff.name == "log_offset" or not near.anchored:
            return self.candidate_model(current, eff)
        return near.with_effect(eff)


def _summarised(target: _Measurement, obs: Observation
                ) -> tuple[Observation, dict[str, StatValue], dict[str, StatValue]]:
    return obs, summarise(obs), summarise(target.held_of(obs))


def _run_all(jobs: list[Callable[[], Any]], workers: int) -> list[Any]:
    if len(jobs) == 1:
        return [jobs[0]()]
    if not jobs:
        return []
    with ThreadPoolExecutor(max_workers=min(workers, len(jobs))) as pool:
        return list(pool.map(lambda job: job(), jobs))


def model_on_rows(model: Model, rows: np.ndarray) -> Model:
    """``model`` with its maps and its effects' per-pixel maps on the sensor rows ``rows``
    only (what a fitter on those rows compares with)."""
    from dataclasses import replace  # noqa: PLC0415

    return replace(model, contrast=model.contrast[rows], bias=model.bias[rows],
                   effects={k: e.on_rows(rows) for k, e in model.effects.items()})  # type: ignore[arg-type]


# the candidates' fit and screening, slowest first, before a run has timed them (their
# fitters scan grids of offsets, lags or jitters over every pixel, or render frames anew)
SLOW_FIRST = ("aps_fpn", "bandwidth", "exposure", "timestamp_jitter", "threshold_light",
              "refractory", "threshold_noise")


def longest_first(names: list[str], seconds: dict[str, float]) -> list[str]:
    """``names`` by their time in ``seconds`` (those timed) or by :data:`SLOW_FIRST`
    (the others, after them), longest first; ties keep the given order."""
    def key(item: tuple[int, str]) -> tuple[int, float, int]:
        i, n = item
        if n in seconds:
            return 0, -seconds[n], i
        return 1, float(SLOW_FIRST.index(n)) if n in SLOW_FIRST else len(SLOW_FIRST), i
    return [n for _, n in sorted(enumerate(names), key=key)]


SCHEME_EFFECT = "timestamp_quantisation"  # a simulator's timestamp scheme, not a sensor effect


def need(cfg: GapConfig, gap: float) -> float:
    """The least gain that names a candidate against a model whose gap is ``gap``."""
    return max(cfg.min_improvement, cfg.min_relative_improvement * (gap - 1.0))


def gain(gap: float, score: float) -> float:
    """How much a candidate of ``score`` (its gap plus penalty) takes off ``gap``, counted
    down to 1 only: a model that explains the data leaves a gap of about 1, and what a
    candidate takes off below that fits the noise of the comparison."""
    return gap - max(score, 1.0)


def screening_band(rec: Recording, cfg: GapConfig) -> Band | None:
    """The band of rows screenings run on: ``cfg.screen_rows`` of the sensor's rows (at
    least 16), the contiguous ones with the most measured events; ``None`` when screening
    is off, the band would be the whole sensor, or the recording is small enough
    (``cfg.screen_band_min`` pixel-steps) for screenings on all of it."""
    h, w = rec.sensor.shape
    fr = rec.frames
    steps = (int(fr.t_us[-1]) - int(fr.t_us[0])) * 1e-6 * cfg.internal_rate_hz + len(fr)
    n = max(16, int(round(cfg.screen_rows * h)))
    if not cfg.screen or n >= h or h * w * steps <= cfg.screen_band_min:
        return None
    per_row = np.bincount(rec.events["y"], minlength=h).astype(np.int64)
    in_band = np.convolve(per_row, np.ones(n, np.int64), mode="valid")  # rows y..y+n-1
    y0 = int(np.argmax(in_band))
    return Band.of(rec, y0, y0 + n)


def drop_derived(sims: list[Observation]) -> None:
    """The fitters' derived arrays of ``sims`` let go once a phase of fits is over (they
    are a cache, recomputed when asked for again: a few hundred MB per simulation on a
    user's recording, more than the observation itself)."""
    for o in sims:
        o.extra.clear()


def moved_on(old: Evaluation, new: Evaluation) -> Evaluation:
    """``new``, once the workflow has moved on from ``old``: ``old``'s simulated
    observations are let go (its statistics stay, for the report; nothing simulates on top
    of it again)."""
    if old is not new:
        old.sims.clear()
    return new
