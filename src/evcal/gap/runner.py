"""The gap workflow's evaluations of models (:class:`Runner`): anchored, simulated with the
run's seeds (or screened with one, on a band of rows), summarised and compared with the
measurement; the configuration (:class:`GapConfig`) and what the loop keeps of each model
(:class:`Evaluation`). The loop itself is :mod:`.workflow`; the search over candidates
:mod:`.search`; what a named effect goes through before it is named, :mod:`.finish`.
"""

from __future__ import annotations

import math
import threading
import weakref
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import partial

import numpy as np

from ..errors import ConfigError
from ..online import usable_cores
from ..recording import Recording
from ..sim.effects import EFFECT_NAMES, Effect
from .compare import Discrepancy, discrepancy
from .model import (
    Band,
    Model,
    SimSettings,
    anchor,
    estimate_read_noise,
    fit_base,
    population,
    simulate_model,
)
from .render import RenderCache
from .stats import (
    GapError,
    Observation,
    StatValue,
    observe,
    rows_of,
    summarise,
)


@dataclass(frozen=True, kw_only=True)
class GapConfig:
    max_effects: int = 3
    seed: int = 0
    n_seeds: int = 3
    internal_rate_hz: float = 1000.0
    interpolation: str = "flow"  # between frames: "flow" (evcal.gap.flow) or "linear"
    # timing statistics only in windows whose flow is consistent and at most this many pixels
    # (evcal.gap.flow.trusted_windows) and whose frames are not clipped at full scale
    # (unclipped_windows); None: every window
    trusted_max_px: float | None = math.inf
    penalty_per_parameter: float = 0.1
    min_improvement: float = 0.3
    min_relative_improvement: float = 0.25
    refine: bool = True
    # once nothing more is named, each sensor effect named before the last is refined
    # again (the three-point search) in the final model: its value was settled in a model
    # that lacked the effects named after it, which may explain part of what it took on
    refit_named: bool = True
    # bias-correct each named effect's moment estimate by refitting it on the simulations
    # made with it (see evcal.gap.finish.debias)
    debias: bool = True
    candidates: tuple[str, ...] = EFFECT_NAMES
    # screening: every candidate is simulated with one seed (the spread of the statistics
    # from the current model's seeds) and only the best ``confirm_top`` with all of them
    screen: bool = True
    confirm_top: int = 2
    # ... those after the best only when their screened score is within this many close
    # margins (close_margin, close_relative) of the best's (inf: all of the top)
    confirm_within: float = 2.0
    # when no single candidate qualifies and the gap is still above this, pairs of the best
    # ``beam_width`` singles are tried together (two effects that explain the data only
    # together are named together)
    beam_width: int = 3
    beam_min_gap: float = 3.0
    # the best candidate and a confirmed one of another effect within this score of it are
    # both bias-corrected (and refined) before one is named
    close_margin: float = 0.5
    close_relative: float = 0.25  # ... or within this share of its gap above 1
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
        if self.n_seeds < 2:
            raise ConfigError(f"n_seeds={self.n_seeds} must be >= 2 (the spread needs two)")
        if not self.confirm_within >= 0.0:
            raise ConfigError(f"confirm_within={self.confirm_within} must be >= 0")
        if self.confirm_top < 1 or self.beam_width < 0:
            raise ConfigError(f"confirm_top={self.confirm_top} must be >= 1 and "
                             f"beam_width={self.beam_width} >= 0")
        if self.max_pixel_steps < 1_000_000:
            raise ConfigError(f"max_pixel_steps={self.max_pixel_steps} must be >= 1e6")
        if self.max_events is not None and self.max_events < 10_000:
            raise ConfigError(f"max_events={self.max_events} must be >= 10000")
        if not 0.0 < self.screen_rows <= 1.0:
            raise ConfigError(f"screen_rows={self.screen_rows} must be in (0, 1]")
        if self.workers is not None and self.workers < 1:
            raise ConfigError(f"workers={self.workers} must be >= 1")
        unknown = set(self.candidates) - set(EFFECT_NAMES)
        if unknown:
            raise ConfigError(f"unknown candidate effect(s) {sorted(unknown)}")


@dataclass
class Evaluation:
    model: Model
    sims: list[Observation]  # during a run; empty in a GapResult (see run_gap)
    disc: Discrepancy
    summaries: list[dict[str, StatValue]] = field(default_factory=list)
    # screened on the run's band of rows (GapConfig.screen_rows): its statistics and sims are
    # the band's, ``model`` the whole sensor's (not anchored yet: confirm() evaluates it)
    on_band: bool = False

    @property
    def gap(self) -> float:
        return self.disc.gap

    @property
    def screened(self) -> bool:
        """Evaluated on one seed only (its spread borrowed): a candidate not yet confirmed."""
        return self.disc.n_sims < 2


class Runner:
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
        self.meas = observe(rec, trusted=self.trusted)
        self.meas_stats = summarise(self.meas)
        self.meas_pop = population(self.meas)
        self.settings = SimSettings(internal_rate_hz=cfg.internal_rate_hz,
                                    read_noise_dn=estimate_read_noise(rec.frames),
                                    interpolation=cfg.interpolation)
        # common random numbers: every model is simulated with the same seeds, the first of
        # them also the anchor's (its last simulation, when it agreed, is that seed's)
        self.seeds = [cfg.seed * 1000 + k for k in range(cfg.n_seeds)]
        self.workers = cfg.workers or usable_cores()
        self.render = RenderCache(on_use=self._counted, workers=self.workers)
        self.simulations = 0
        self.work = 0.0  # simulations done, in simulations of the whole sensor
        self._lock = threading.Lock()
        # the round's candidates as screened (the beam's pairs start from them), and those
        # confirmed on every seed, best first
        self.screened_pool: dict[str, tuple[Effect, Evaluation]] = {}
        self.confirmed: list[tuple[float, Effect, Evaluation]] = []
        # the gap the round's screenings are compared with (the band's, on a band)
        self.screen_base = math.inf
        # seconds each candidate's fit and screening took in its last round (the next
        # round starts the slowest first)
        self.task_s: dict[str, float] = {}
        self.band = screening_band(rec, cfg)
        if self.band is not None:
            rows = self.band.rows
            w = rec.sensor.width
            self.trusted_band = None if self.trusted is None else \
                self.trusted[:, rows.start * w:rows.stop * w]
            self.meas_band = observe(self.band.rec, trusted=self.trusted_band)
            self.meas_stats_band = summarise(self.meas_band)
        # the band's discrepancy of an evaluation whose spread screenings borrow, by id
        # (held weakly: the cache must not keep an evaluation's simulations alive)
        self._band_spread: dict[int, tuple[weakref.ref[Evaluation], Discrepancy]] = {}

    def _counted(self, share: float) -> None:
        """One more simulation, of ``share`` of the sensor's rows (the render cache serves
        each one once)."""
        with self._lock:
            self.simulations += 1
            self.work += share
        self.tick(share)

    def _simulate(self, model: Model, seed: int) -> Observation:
        return observe(simulate_model(model, self.rec, seed, self.settings, self.render),
                       trusted=self.trusted)

    def _simulate_summarised(self, model: Model, seed: int
                             ) -> tuple[Observation, dict[str, StatValue]]:
        obs = self._simulate(model, seed)
        return obs, summarise(obs)

    def evaluate(self, model: Model, what: str, *, spread: Evaluation | None = None
                 ) -> Evaluation:
        """Anchor ``model`` and simulate it with every seed (in parallel), or, with
        ``spread``, with the first seed only (a screening; the seed-to-seed spread is
        ``spread``'s)."""
        if spread is not None and self.band is not None:
            return self.screen_on_band(model, spread)
        model, first = anchor(model, self.rec, self.meas, self.seeds[0], self.settings,
                              render=self.render, trusted=self.trusted)
        sims = [first] if first is not None else []
        n = 1 if spread is not None else len(self.seeds)
        ev = Evaluation(model, sims, self.meas_disc([], None), [])
        return self.extend(ev, n, what, spread=spread)

    def extend(self, ev: Evaluation, n: int, what: str, *, spread: Evaluation | None = None
               ) -> Evaluation:
        """``ev`` with simulations up to ``n`` seeds (the missing ones run in parallel, each
        summarised in its thread, beside the summaries ``ev`` still lacks). An evaluation
        that let go of its simulations (a round's candidates not kept) is simulated anew:
        its summaries would otherwise count its first seed twice."""
        if len(ev.sims) < len(ev.summaries):
            ev = Evaluation(ev.model, [], ev.disc, [])
        todo = self.seeds[len(ev.sims):n]
        sims = list(ev.sims)
        unsummarised = sims[len(ev.summaries):]
        jobs: list[Callable[[], tuple[Observation, dict[str, StatValue]]]] = [
            partial(_summarised, o) for o in unsummarised]
        jobs += [partial(self._simulate_summarised, ev.model, s) for s in todo]
        done: list[tuple[Observation, dict[str, StatValue]]] = []
        if len(jobs) == 1:
            done = [jobs[0]()]
        elif jobs:
            with ThreadPoolExecutor(max_workers=min(self.workers, len(jobs))) as pool:
                done = list(pool.map(lambda job: job(), jobs))
        sims = sims[:len(ev.summaries)] + [o for o, _ in done]
        summaries = list(ev.summaries) + [s for _, s in done]
        # the derived arrays (per-window fits, intervals, per-event windows: half an
        # observation's memory, more with many events) are dropped once summarised; the
        # fitters recompute them on the few simulations they read (Observation.extra is a
        # cache), the others would hold them as long as their evaluation lives
        for o in sims:
            o.extra.clear()
        disc = self.meas_disc(summaries, spread if len(sims) < 2 else None)
        return Evaluation(ev.model, sims, disc, summaries)

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
        band = self.band
        assert band is not None
        m_band, first = anchor(band.model(model), self.rec, self.meas_band, self.seeds[0],
                               self.settings, render=self.render, trusted=self.trusted_band,
                               band=band)

        def sim(seed: int) -> tuple[Observation, dict[str, StatValue]]:
            obs = observe(simulate_model(m_band, self.rec, seed, self.settings, self.render,
                                         band), trusted=self.trusted_band)
            return obs, summarise(obs)

        jobs: list[Callable[[], tuple[Observation, dict[str, StatValue]]]] = [
            partial(_summarised, first) if first is not None else partial(sim, self.seeds[0])]
        jobs += [partial(sim, s) for s in self.seeds[1:n]]
        if len(jobs) == 1:
            done = [jobs[0]()]
        else:
            with ThreadPoolExecutor(max_workers=min(self.workers, len(jobs))) as pool:
                done = list(pool.map(lambda job: job(), jobs))
        sims = [o for o, _ in done]
        summaries = [sm for _, sm in done]
        if n == 1:
            sims[0].extra.clear()
        disc = discrepancy(self.meas_stats_band, summaries,
                           spread=self.band_spread(spread) if n == 1 and spread is not None
                           else None)
        return Evaluation(model, sims, disc, summaries, on_band=True)

    def band_spread(self, ev: Evaluation) -> Discrepancy:
        """``ev``'s discrepancy on the band (its simulations cut to the band's rows): the
        spread that screenings on the band borrow."""
        hit = self._band_spread.get(id(ev))
        if hit is not None and hit[0]() is ev:
            return hit[1]
        if len(ev.sims) < 2:
            raise GapError("a screening on the band needs an evaluation with simulations on "
                           "every seed for its spread")
        assert self.band is not None
        sums = [summarise(rows_of(o, self.band.rows)) for o in ev.sims]
        disc = discrepancy(self.meas_stats_band, sums)
        if len(self._band_spread) >= 4:  # the round's current and best are what is asked for
            self._band_spread.pop(next(iter(self._band_spread)))
        self._band_spread[id(ev)] = (weakref.ref(ev), disc)
        return disc

    def meas_disc(self, summaries: list[dict[str, StatValue]], spread: Evaluation | None
                  ) -> Discrepancy:
        if not summaries:
            return Discrepancy({}, {}, {}, {}, {}, {}, 0)
        return discrepancy(self.meas_stats, summaries,
                           spread=spread.disc if spread is not None else None)

    def candidate_model(self, current: Model, eff: Effect) -> Model:
        if eff.name == "log_offset":
            base = fit_base(self.rec, log_offset=float(eff.parameters()["dark_dn"]))
            m = Model(base.contrast, base.bias, base.log_offset, dict(current.effects))
            return m.with_effect(eff)  # refitted maps: not anchored
        return current.with_effect(eff)

    def near_model(self, current: Model, near: Model, eff: Effect) -> Model:
        """``eff`` (a new value of an effect ``near`` has) on top of ``current``, starting
        from ``near``'s anchored maps when they are (the anchor then starts close to where
        it ends, often taking one simulation)."""
        if eff.name == "log_offset" or not near.anchored:
            return self.candidate_model(current, eff)
        return near.with_effect(eff)

    def let_go(self, *keep: Evaluation | None) -> None:
        """The round's screened and confirmed evaluations let go of their simulations, but
        for ``keep``: once the round has chosen what it finishes, no other candidate is
        simulated on top of or refitted from (a few hundred MB each on a user's
        recording)."""
        kept = {id(ev) for ev in keep if ev is not None}
        for ev in [ev for _, ev in self.screened_pool.values()] + \
                [ev for _, _, ev in self.confirmed]:
            if id(ev) not in kept:
                ev.sims.clear()
        self.released()

    def evaluate_many(self, models: list[tuple[Effect, Model]], current: Evaluation
                      ) -> list[Evaluation]:
        """Each model evaluated on top of ``current``: screened on one seed when the config
        says so (the models in parallel), else on every seed (one after the other, each on
        every core)."""
        if not self.cfg.screen:
            return [self.evaluate(m, f"candidate {e.name}") for e, m in models]
        if self.band is not None:
            self.band_spread(current)  # once, before the threads ask for it
        with ThreadPoolExecutor(max_workers=self.workers) as pool:
            return list(pool.map(lambda em: self.evaluate(em[1], f"screen {em[0].name}",
                                                          spread=current), models))


SCHEME_EFFECT = "timestamp_quantisation"  # a simulator's timestamp scheme, not a sensor effect


def _summarised(obs: Observation) -> tuple[Observation, dict[str, StatValue]]:
    return obs, summarise(obs)


def need(cfg: GapConfig, current: Evaluation) -> float:
    """The least gain that names a candidate against ``current``."""
    return max(cfg.min_improvement, cfg.min_relative_improvement * (current.gap - 1.0))


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
