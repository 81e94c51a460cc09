"""The model-gap loop: fit, simulate, compare, name the missing effect, repeat.

1. Fit the base model (``c``, ``b`` by OffEI at the nominal log offset) and anchor it.
2. Simulate the measured recording under the model with ``n_seeds`` seeds (driven by its
   frames) and compute the standardised discrepancy of every statistic (:mod:`.stats`); the
   gap is their mean (about 1 when the model explains the data).
3. For each effect not in the model yet: estimate its parameters (:func:`.model.fit_candidate`),
   anchor, simulate with the same seeds, and compute the gap. The score is the gap plus
   ``penalty_per_parameter`` per fitted parameter.
4. The best candidate is named if it lowers the gap (counted down to 1, what a model that
   explains the data leaves) by more than its penalty plus ``min_improvement`` and by at
   least ``min_relative_improvement`` of the part of the gap above 1. Its moment estimate is
   bias-corrected by simulation and, unless that confirms it, refined by a three-point
   search. Repeat from 3 until nothing is named or ``max_effects`` are.

The timestamp scheme of a frame-driven simulator (``timestamp_quantisation``) is not a
sensor effect: once its fitter sees the timestamps on a step grid, the sensor candidates are
evaluated on top of it, and it is named when it closes the gap alone or with the best of
them.
"""

from __future__ import annotations

import math
import threading
import weakref
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import numpy as np

from ..errors import ConfigError
from ..jsonable import to_jsonable
from ..online import usable_cores
from ..recording import Recording
from ..sim.effects import EFFECT_NAMES, Effect
from .explain import unexplained
from .model import (
    Band,
    Model,
    SimSettings,
    anchor,
    estimate_read_noise,
    fit_base,
    fit_candidate,
    population,
    simulate_model,
    variants,
)
from .render import RenderCache
from .stats import (
    Discrepancy,
    GapError,
    Observation,
    StatValue,
    discrepancy,
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
    # (evcal.gap.flow.trusted_windows); None: every window
    trusted_max_px: float | None = math.inf
    penalty_per_parameter: float = 0.1
    min_improvement: float = 0.3
    min_relative_improvement: float = 0.25
    refine: bool = True
    # bias-correct each named effect's moment estimate by refitting it on the simulations
    # made with it (see _Runner.debias)
    debias: bool = True
    candidates: tuple[str, ...] = EFFECT_NAMES
    # screening: every candidate is simulated with one seed (the spread of the statistics
    # from the current model's seeds) and only the best ``confirm_top`` with all of them
    screen: bool = True
    confirm_top: int = 2
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
        if self.confirm_top < 1 or self.beam_width < 0:
            raise ConfigError(f"confirm_top={self.confirm_top} must be >= 1 and "
                             f"beam_width={self.beam_width} >= 0")
        if self.max_pixel_steps < 1_000_000:
            raise ConfigError(f"max_pixel_steps={self.max_pixel_steps} must be >= 1e6")
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


@dataclass
class Step:
    effect: Effect
    before: Evaluation
    after: Evaluation
    candidates: dict[str, dict[str, Any]]

    def moved_statistics(self, top: int = 4) -> list[str]:
        drops = {k: self.before.disc.per_stat[k] - self.after.disc.per_stat[k]
                 for k in self.before.disc.per_stat}
        ranked = sorted(drops, key=lambda k: -drops[k])
        return [k for k in ranked[:top] if drops[k] > 0.5]


@dataclass
class GapResult:
    recording_info: dict[str, Any]
    measured: dict[str, Any]
    initial: Evaluation
    final: Evaluation
    steps: list[Step] = field(default_factory=list)
    settings: dict[str, Any] = field(default_factory=dict)
    # candidates of the round that named nothing (why the loop stopped)
    rejected: dict[str, dict[str, Any]] = field(default_factory=dict)

    @property
    def named_effects(self) -> list[str]:
        return [s.effect.name for s in self.steps]

    def to_json(self) -> dict[str, Any]:
        """The stable ``report.json`` schema."""
        d0, d1 = self.initial.disc, self.final.disc
        stats = []
        for name in d0.per_stat:
            stats.append({
                "name": name,
                "measured": _list(d0.measured[name]),
                "simulated_initial": _list(d0.sim_mean[name]),
                "simulated_final": _list(d1.sim_mean[name]),
                "z_initial": float(np.sqrt(d0.per_stat[name])),
                "z_final": float(np.sqrt(d1.per_stat[name])),
            })
        return {
            "named_effects": self.named_effects,
            "gap_initial": float(self.initial.gap),
            "gap_final": float(self.final.gap),
            "steps": [{
                "effect": s.effect.name,
                "parameters": to_jsonable(s.effect.parameters()),
                "gap_before": float(s.before.gap),
                "gap_after": float(s.after.gap),
                "moved_statistics": s.moved_statistics(),
            } for s in self.steps],
            "statistics": stats,
            # what the final model still does not explain, worst first (also when nothing
            # was named): statistic, regime, direction, in words
            "unexplained": unexplained(d1),
            "window": self.recording_info.get("window"),
        }


def _list(a: np.ndarray) -> list[float | None]:
    """Values for JSON: ``None`` where a statistic had too little data (NaN)."""
    return [float(x) if np.isfinite(x) else None for x in np.asarray(a, np.float64).ravel()]


class _Runner:
    DEBIAS_STEPS = 2  # bootstrap steps per named effect (an evaluation each)

    def __init__(self, rec: Recording, cfg: GapConfig, tick: Callable[[float], None]):
        self.rec = rec
        self.cfg = cfg
        self.tick = tick
        self.trusted = None
        if cfg.trusted_max_px is not None:
            from .flow import trusted_windows  # noqa: PLC0415

            self.trusted = trusted_windows(rec.frames, max_px=cfg.trusted_max_px)
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
            return self._screen_on_band(model, spread)
        model, first = anchor(model, self.rec, self.meas, self.seeds[0], self.settings,
                              render=self.render, trusted=self.trusted)
        sims = [first] if first is not None else []
        n = 1 if spread is not None else len(self.seeds)
        ev = Evaluation(model, sims, self.meas_disc([], None), [])
        return self.extend(ev, n, what, spread=spread)

    def extend(self, ev: Evaluation, n: int, what: str, *, spread: Evaluation | None = None
               ) -> Evaluation:
        """``ev`` with simulations up to ``n`` seeds (the missing ones run in parallel, each
        summarised in its thread, beside the summaries ``ev`` still lacks)."""
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

    def _screen_on_band(self, model: Model, spread: Evaluation | None, n: int = 1
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

    def debias(self, current: Evaluation, best: Evaluation, eff: Effect
               ) -> tuple[Effect, Evaluation, dict[str, Any]]:
        """The moment estimate's own bias, removed by simulation (a parametric bootstrap):
        the fitter applied to the simulations made *with* the effect at ``v`` (in place of
        the measurement, against the same effect-free simulations) returns ``f(v)``; where
        ``f(v) != v`` the estimator is biased on data like these (leak's excess of ON events
        in still windows misses the drift a pixel pays off before the pause ends: at 25 Hz
        with short pauses ``f(v)`` is ~0.4 v). The value whose simulations give the measured
        moment ``m`` solves ``f(v) = m``: ``v <- v m / f(v)`` from ``v = m``, up to
        ``DEBIAS_STEPS`` times (each step's factor clipped to [1/4, 4]) while it moves by
        more than 5 %. The result is kept when its gap is not clearly worse than the moment
        estimate's (the gap is noisy; the bootstrap is the better-founded value)."""
        key = eff.primary
        m = float(eff.parameters()[key])
        info: dict[str, Any] = {"moment": m, "value": m, "steps": []}
        if m <= 0:
            return eff, best, info
        if self.band is not None:
            return self._debias_on_band(current, best, eff, info)
        def refit(sim: Observation) -> Effect | None:
            return fit_candidate(eff.name, sim, current.sims, current.model, self.rec)

        def evaluate(nxt: Effect, at: Evaluation) -> Evaluation:
            ev = self.evaluate(self.near_model(current.model, at.model, nxt),
                               f"debias {eff.name}")
            info["steps"][-1]["gap_next"] = float(ev.gap)
            return ev

        cur_eff, cur_ev = self._bootstrap(eff, m, best, refit, evaluate, info)
        _drop_derived(current.sims)
        if cur_eff is eff or cur_ev.gap > best.gap + max(0.3, 0.1 * best.gap):
            return eff, best, info
        info["value"] = float(cur_eff.parameters()[key])
        return cur_eff, cur_ev, info

    def _bootstrap(self, eff: Effect, m: float, start: Evaluation,
                   refit: Callable[[Observation], Effect | None],
                   evaluate: Callable[[Effect, Evaluation], Evaluation],
                   info: dict[str, Any]) -> tuple[Effect, Evaluation]:
        """The steps of :meth:`debias` from ``start`` (the evaluation at the moment
        estimate): ``refit`` of each simulation gives ``f(v)``, ``evaluate`` the evaluation
        at the next value; returns the last value and its evaluation."""
        key = eff.primary
        cur_eff, cur_ev = eff, start
        for _ in range(self.DEBIAS_STEPS):
            v = float(cur_eff.parameters()[key])
            again = [float(e.parameters()[key]) for e in map(refit, cur_ev.sims)
                     if e is not None and float(e.parameters()[key]) > 0]
            _drop_derived(cur_ev.sims)
            if len(again) < max(2, len(cur_ev.sims) // 2):
                info["note"] = "the fitter did not find the effect in its own simulations"
                break
            f_v = float(np.exp(np.mean(np.log(again))))
            factor = float(np.clip(m / f_v, 0.25, 4.0))
            info["steps"].append({"value": v, "refits": again, "factor": round(factor, 4)})
            if abs(np.log(factor)) < 0.05:
                break
            try:
                nxt = cur_eff.with_params(**{key: _cast(eff, key, v * factor)})
            except ValueError:  # outside the parameter's range
                info["note"] = "the corrected value is outside the parameter's range"
                break
            cur_ev = evaluate(nxt, cur_ev)
            cur_eff = nxt
        return cur_eff, cur_ev

    def _debias_on_band(self, current: Evaluation, best: Evaluation, eff: Effect,
                        info: dict[str, Any]) -> tuple[Effect, Evaluation, dict[str, Any]]:
        """:meth:`debias` with its bootstrap on the band of rows: the moment ``m`` is the
        band's measurement's, each ``f(v)`` the fitter's on the band's rows of simulations
        at ``v`` (``best``'s own cut to the band first, then the band's simulations on every
        seed), both against ``current``'s simulations cut to the band. Only a corrected value
        not clearly worse on the band is evaluated on the whole sensor."""
        band = self.band
        assert band is not None
        key = eff.primary
        cur_band = [rows_of(o, band.rows) for o in current.sims]
        model_band = band.model(current.model)

        def refit(sim: Observation) -> Effect | None:
            return fit_candidate(eff.name, sim, cur_band, model_band, band.rec)

        def evaluate(nxt: Effect, _at: Evaluation) -> Evaluation:
            ev = self._screen_on_band(self.near_model(current.model, best.model, nxt), None,
                                      len(self.seeds))
            info["steps"][-1]["gap_next_band"] = float(ev.gap)
            return ev

        m_fit = refit(self.meas_band)
        if m_fit is None or float(m_fit.parameters()[key]) <= 0:
            info["note"] = "the fitter does not see the effect on the band of rows"
            return eff, best, info
        m = float(m_fit.parameters()[key])
        info["moment_band"] = m
        at_m = Evaluation(best.model, [rows_of(o, band.rows) for o in best.sims], best.disc)
        best_band = discrepancy(self.meas_stats_band, [summarise(o) for o in at_m.sims]).gap
        cur_eff, band_ev = self._bootstrap(eff, m, at_m, refit, evaluate, info)
        if cur_eff is eff:
            return eff, best, info
        info["gap_band"] = {"moment": best_band, "corrected": float(band_ev.gap)}
        if band_ev.gap > best_band + max(0.3, 0.1 * best_band):
            info["note"] = "the corrected value explains the band of rows worse"
            return eff, best, info
        ev = self.evaluate(self.near_model(current.model, best.model, cur_eff),
                           f"debias {eff.name}")
        if ev.gap > best.gap + max(0.3, 0.1 * best.gap):
            return eff, best, info
        info["value"] = float(cur_eff.parameters()[key])
        return cur_eff, ev, info

    def scheme_candidate(self, current: Evaluation, tried: dict[str, dict[str, Any]]
                         ) -> tuple[Effect, Evaluation] | None:
        """The timestamp scheme fitted and evaluated, when it is a candidate not yet in the
        model and its fitter sees it."""
        if SCHEME_EFFECT not in self.cfg.candidates or SCHEME_EFFECT in current.model.effects:
            return None
        eff = fit_candidate(SCHEME_EFFECT, self.meas, current.sims, current.model, self.rec)
        if eff is None:
            tried[SCHEME_EFFECT] = {"parameters": None, "gap": None}
            return None
        ev = self.evaluate(self.candidate_model(current.model, eff), f"candidate {eff.name}")
        tried[SCHEME_EFFECT] = {"parameters": eff.parameters(), "gap": ev.gap,
                                "score": ev.gap + self.cfg.penalty_per_parameter * eff.n_fitted}
        return eff, ev

    def best_candidate(self, current: Evaluation, tried: dict[str, dict[str, Any]], *,
                       skip: str) -> tuple[float, Effect, Evaluation] | None:
        """Every candidate but ``skip`` not in ``current``'s model, fitted from its
        simulations and evaluated on top of it; the one of the lowest score.

        Screened first (one seed each, the candidates in parallel, the spread of the
        statistics from ``current``); the ``confirm_top`` best are simulated with every seed
        and compared on that."""
        self.screened_pool = {}
        self.confirmed = []
        fitted: list[tuple[str, Effect]] = []
        evals: list[Evaluation] = []
        names = [n for n in self.cfg.candidates if n not in current.model.effects and n != skip]
        if self.cfg.screen and self.band is not None:
            self.band_spread(current)  # once, before the threads ask for it

        def fit_and_screen(name: str) -> tuple[Effect | None, list[Effect], list[Evaluation]]:
            """A candidate fitted and, when screening, its variants screened at once: the
            fitters (numpy, holding the GIL in part) and the simulations of the candidates
            fitted first (numba, without it) share the cores."""
            eff = fit_candidate(name, self.meas, current.sims, current.model, self.rec)
            if eff is None:
                return None, [], []
            # discrete alternatives the moment estimate cannot tell: the gap decides
            alts = variants(eff)
            if not self.cfg.screen:
                return eff, alts, []
            return eff, alts, [self.evaluate(self.candidate_model(current.model, e),
                                             f"screen {e.name}", spread=current)
                               for e in alts]

        with ThreadPoolExecutor(max_workers=self.workers) as pool:
            done = list(pool.map(fit_and_screen, names))
        _drop_derived(current.sims)
        for name, (eff, alts, screened) in zip(names, done, strict=True):
            if eff is None:
                tried[name] = {"parameters": None, "gap": None}
                continue
            fitted += [(name, e) for e in alts]
            evals += screened
        if not fitted:
            return None
        if not self.cfg.screen:
            evals = self.evaluate_many([(e, self.candidate_model(current.model, e))
                                        for _, e in fitted], current)
        pen = self.cfg.penalty_per_parameter
        ranked = sorted(range(len(fitted)),
                        key=lambda i: evals[i].gap + pen * fitted[i][1].n_fitted)
        if self.cfg.screen:
            self._confirm_ranked(current, fitted, evals, ranked)
        best: tuple[float, Effect, Evaluation] | None = None
        for (name, eff), ev in zip(fitted, evals, strict=True):
            score = ev.gap + pen * eff.n_fitted
            entry = {"parameters": eff.parameters(), "gap": ev.gap, "score": score,
                     "seeds": ev.disc.n_sims}
            old = tried.get(name)
            if old is not None and old.get("score") is not None and \
                    (old["seeds"], -old["score"]) >= (entry["seeds"], -score):
                old.setdefault("variants", []).append(
                    {"parameters": eff.parameters(), "gap": ev.gap})
            else:
                entry["variants"] = [] if old is None or old.get("score") is None else \
                    [{"parameters": old["parameters"], "gap": old["gap"]}]
                tried[name] = entry
            if not ev.screened:
                self.confirmed.append((score, eff, ev))
                if best is None or score < best[0]:
                    best = (score, eff, ev)
            self.screened_pool[name] = (eff, ev)
        self.confirmed.sort(key=lambda t: t[0])
        # only the beam's candidates are simulated on top of; the others' observations
        # (a hundred MB each at 240x180) are let go now, not at the end of the round
        keep = {id(self.screened_pool[n][1]) for n in self.beam_top(tried)}
        keep |= {id(ev) for _, _, ev in self.confirmed}
        for ev in evals:
            if id(ev) not in keep:
                ev.sims.clear()
        return best

    def _confirm_ranked(self, current: Evaluation, fitted: list[tuple[str, Effect]],
                        evals: list[Evaluation], ranked: list[int]) -> None:
        """The ``confirm_top`` best screened candidates confirmed, each only when its
        screened gain reaches half the gain that names, against the current model's gap
        where it was screened (on the band, the band's): what falls that short does not
        qualify on every seed either. Each of them is confirmed otherwise, also one whose
        screening looks far worse than the best's: one seed can misjudge a candidate by
        more than the margin between two (a frame lag and a bandwidth limit explain the
        same delay), which the comparison of bias-corrected values settles."""
        cfg = self.cfg
        pen = cfg.penalty_per_parameter
        base = self.band_spread(current).gap if self.band is not None else current.gap
        need = max(cfg.min_improvement, cfg.min_relative_improvement * (base - 1.0))
        todo: list[int] = []
        for i in ranked[:cfg.confirm_top]:
            score = evals[i].gap + pen * fitted[i][1].n_fitted
            if not evals[i].screened:
                continue
            if _gain(base, score) <= 0.5 * need:
                break
            todo.append(i)
        # side by side: each anchor's simulations run one after the other
        with ThreadPoolExecutor(max_workers=max(1, min(self.workers, len(todo)))) as pool:
            done = list(pool.map(lambda i: self.confirm(evals[i], f"confirm {fitted[i][0]}"),
                                 todo))
        for i, ev in zip(todo, done, strict=True):
            evals[i] = ev

    def beam_top(self, tried: dict[str, dict[str, Any]]) -> list[str]:
        """The ``beam_width`` screened candidates of the lowest score."""
        singles = sorted((tried[n]["score"], n) for n in self.screened_pool
                         if tried.get(n, {}).get("score") is not None)
        return [n for _, n in singles[:self.cfg.beam_width]]

    def runner_up(self, best: tuple[float, Effect, Evaluation]
                  ) -> tuple[float, Effect, Evaluation] | None:
        """The confirmed candidate of another effect whose score is within ``close_margin``
        of ``best``'s (or ``close_relative`` of its gap above 1): moment estimates can be
        biased (a threshold that grows in the dark reads 0.8x its exponent, a bandwidth
        limit 0.5x its cutoff, and a frame lag then explains its delay better), so two
        effects that explain the data about as well are compared once both are
        bias-corrected."""
        margin = max(self.cfg.close_margin, self.cfg.close_relative * (best[0] - 1.0))
        for c in self.confirmed:
            if c[1].name != best[1].name and c[0] <= best[0] + margin:
                return c
        return None

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

    def best_pair(self, current: Evaluation, tried: dict[str, dict[str, Any]]
                  ) -> tuple[float, list[tuple[Effect, Evaluation]]] | None:
        """When no single candidate qualifies: pairs of the ``beam_width`` best singles of
        the round, the second fitted on top of the first's simulations (two effects that
        explain the data only together: each hides the other's signature). The pair of the
        lowest score, confirmed on every seed, with the evaluation of its first effect
        alone."""
        top = self.beam_top(tried)
        jobs: list[tuple[Effect, Evaluation, Effect, Model]] = []
        for a in top:  # the pairs are fitted on the whole sensor's simulations
            eff_a, ev_a = self.screened_pool[a]
            if ev_a.on_band:
                self.screened_pool[a] = (eff_a, self.confirm(ev_a, f"confirm {a}"))
        for i, a in enumerate(top):
            eff_a, ev_a = self.screened_pool[a]
            for b in top[i + 1:]:
                eff_b = fit_candidate(b, self.meas, ev_a.sims, ev_a.model, self.rec)
                if eff_b is None:
                    continue
                jobs.append((eff_a, ev_a, eff_b, self.candidate_model(ev_a.model, eff_b)))
            _drop_derived(ev_a.sims)
        if not jobs:
            return None
        evals = self.evaluate_many([(j[2], j[3]) for j in jobs], current)
        pen = self.cfg.penalty_per_parameter
        scores = [ev.gap + pen * (j[0].n_fitted + j[2].n_fitted) for j, ev in zip(
            jobs, evals, strict=True)]
        k = int(np.argmin(scores))
        eff_a, ev_a, eff_b, _ = jobs[k]
        ev_pair = self.confirm(evals[k], f"confirm {eff_a.name} + {eff_b.name}")
        ev_a = self.confirm(ev_a, f"confirm {eff_a.name}")
        score = ev_pair.gap + pen * (eff_a.n_fitted + eff_b.n_fitted)
        tried[f"{eff_a.name} + {eff_b.name}"] = {
            "parameters": {eff_a.name: eff_a.parameters(), eff_b.name: eff_b.parameters()},
            "gap": ev_pair.gap, "score": score, "seeds": ev_pair.disc.n_sims,
            "pairs_screened": {f"{j[0].name} + {j[2].name}": float(ev.gap)
                               for j, ev in zip(jobs, evals, strict=True)}}
        return score, [(eff_a, ev_a), (eff_b, ev_pair)]

    def finish(self, current: Evaluation, ev: Evaluation, eff: Effect,
               tried: dict[str, dict[str, Any]]) -> tuple[Effect, Evaluation]:
        """A named candidate's estimate bias-corrected and refined (as configured)."""
        if self.cfg.debias:
            eff, ev, info = self.debias(current, ev, eff)
            tried[eff.name]["debias"] = info
            if info["steps"] and abs(np.log(info["steps"][0]["factor"])) < 0.05:
                # the fitter gives back its own value on the model's simulations: the
                # estimate is consistent, and a search of the gap would trade it against
                # what the model misses elsewhere (interpolated frames)
                return eff, ev
        if self.cfg.refine:
            eff, ev = self.refine(current.model, ev, eff)
        return eff, ev

    def refine(self, current: Model, best: Evaluation, eff: Effect) -> tuple[Effect, Evaluation]:
        key = eff.primary
        v0 = float(eff.parameters()[key])
        if v0 <= 0:
            return eff, best
        factors = (0.7, 1.0, 1 / 0.7)
        points: list[Effect] = []
        for f in factors:
            try:
                points.append(eff if f == 1.0 else
                              eff.with_params(**{key: _cast(eff, key, v0 * f)}))
            except ValueError:  # outside the parameter's range (e.g. sigma above 1)
                return eff, best  # no three-point search: the moment estimate stands
        # screened (one seed, ``best``'s spread; side by side): only a winner is confirmed.
        # On the band (the busiest rows) screenings are compared with each other, not with
        # ``best``'s gap on the whole sensor: the centre is screened too
        todo = [e for f, e in zip(factors, points, strict=True)
                if f != 1.0 or self.band is not None]
        with ThreadPoolExecutor(max_workers=max(1, min(self.workers, len(todo)))) as pool:
            screened = dict(zip(map(id, todo), pool.map(
                lambda e: self.evaluate(self.near_model(current, best.model, e),
                                        f"refine {eff.name}", spread=best), todo),
                strict=True))
        gaps = []
        evals = []
        for f, e in zip(factors, points, strict=True):
            ev = screened.get(id(e), best)
            gaps.append(ev.gap)
            evals.append((e, best if f == 1.0 else ev))
        y = np.asarray(gaps)
        x = np.log(np.asarray(factors))
        den = y[0] - 2 * y[1] + y[2]
        if den > 0:
            xv = float(np.clip(x[1] + 0.5 * (x[1] - x[0]) * (y[0] - y[2]) / den, x[0], x[2]))
            if abs(xv) > 0.05 and int(np.argmin(y)) != 0 and int(np.argmin(y)) != 2:
                e = eff.with_params(**{key: _cast(eff, key, v0 * np.exp(xv))})
                ev = self.evaluate(self.near_model(current, best.model, e), f"refine {eff.name}",
                                   spread=best)
                gaps.append(ev.gap)
                evals.append((e, ev))
        i = int(np.argmin(gaps))
        # keep the moment estimate unless the search clearly beats it (the gap is noisy),
        # screened and then on every seed
        margin = max(0.3, 0.1 * best.gap)
        if gaps[i] < gaps[1] - max(0.3, 0.1 * gaps[1]) and evals[i][1] is not best:
            e, ev = evals[i]
            ev = self.confirm(ev, f"confirm refined {eff.name}")
            if ev.gap < best.gap - margin:
                return e, ev
        return eff, best


SCHEME_EFFECT = "timestamp_quantisation"  # a simulator's timestamp scheme, not a sensor effect


def _summarised(obs: Observation) -> tuple[Observation, dict[str, StatValue]]:
    return obs, summarise(obs)


def _need(cfg: GapConfig, current: Evaluation) -> float:
    """The least gain that names a candidate against ``current``."""
    return max(cfg.min_improvement, cfg.min_relative_improvement * (current.gap - 1.0))


def _gain(gap: float, score: float) -> float:
    """How much a candidate of ``score`` (its gap plus penalty) takes off ``gap``, counted
    down to 1 only: a model that explains the data leaves a gap of about 1, and what a
    candidate takes off below that fits the noise of the comparison."""
    return gap - max(score, 1.0)


def _cast(eff: Effect, key: str, value: float) -> Any:
    old = eff.parameters()[key]
    if isinstance(old, int) and not isinstance(old, bool):
        return max(1, int(round(value)))
    return round(float(value), 6)


ANCHOR_SIMS = 2  # simulations an anchor takes, typically (one of them counted as a seed's)


def n_simulations(cfg: GapConfig, rounds: int | None = None, band_share: float = 1.0
                  ) -> float:
    """Work the workflow plans, in simulations of the whole sensor (for the progress bar's
    estimate of the time left): the base model on every seed, then per round every
    candidate screened (on a band of ``band_share`` of the rows, see
    :func:`screening_band`), the best confirmed, and the named one's bias correction and
    refinement; ``rounds`` (default: as many as ``max_effects`` allows, plus the round that
    names nothing)."""
    n_rounds = cfg.max_effects + 1 if rounds is None else rounds
    full = ANCHOR_SIMS - 1 + cfg.n_seeds
    k = len(cfg.candidates)
    screen = ANCHOR_SIMS * band_share if cfg.screen else full
    # a screening on the band is confirmed anew on the whole sensor, one on it is extended
    confirm = (full if band_share < 1.0 else cfg.n_seeds - 1) if cfg.screen else 0
    total: float = full
    for i in range(n_rounds):
        cands = max(k - i, 0)
        total += cands * screen + cfg.confirm_top * confirm
        if i < n_rounds - 1:
            # the named effect: bias correction (its steps on the band with every seed, the
            # corrected value on the whole sensor), refinement (three screenings)
            debias = _Runner.DEBIAS_STEPS * full if band_share >= 1.0 else \
                _Runner.DEBIAS_STEPS * (cfg.n_seeds + ANCHOR_SIMS - 1) * band_share + full
            total += debias + 3 * screen
    return total


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


def working_window(rec: Recording, max_pixel_steps: int, internal_rate_hz: float
                   ) -> tuple[Recording, dict[str, Any]]:
    """``rec`` cut to the contiguous frames with the most events between them whose
    simulation fits ``max_pixel_steps`` (pixels x internal samples), or ``rec`` itself when
    all of it fits; and what was kept (``window``: first and last frame time, frames, events,
    and the whole recording's).

    The statistics are averages over pixels and windows: a longer recording sharpens them
    far less than it costs. The busiest stretch holds the most information about the sensor
    (still parts are kept when the whole fits)."""
    fr = rec.frames
    n_pix = rec.sensor.height * rec.sensor.width
    t = fr.t_us
    dur_s = (int(t[-1]) - int(t[0])) * 1e-6
    info: dict[str, Any] = {"first_frame_us": int(t[0]), "last_frame_us": int(t[-1]),
                            "frames": len(fr), "of_frames": len(fr), "cut": False}
    if n_pix * (dur_s * internal_rate_hz + len(fr)) <= max_pixel_steps:
        return rec, info
    max_s = max_pixel_steps / n_pix / internal_rate_hz
    ev_t = rec.events["t_us"]
    at = np.searchsorted(ev_t, t, side="left")  # events before each frame
    # for each first frame, the last frame within max_s; the pair with the most events
    last = np.searchsorted(t, t + int(max_s * 1e6), side="right") - 1
    last = np.maximum(last, np.minimum(np.arange(t.size) + 3, t.size - 1))
    counts = at[last] - at[np.arange(t.size)]
    k0 = int(np.argmax(counts))
    k1 = int(last[k0])
    sub = fr.select(slice(k0, k1 + 1))
    events = rec.events_between(int(t[k0]), int(t[k1]) + 1)
    cut = Recording(rec.sensor, events.copy(), sub, dict(rec.metadata))
    info.update({"first_frame_us": int(t[k0]), "last_frame_us": int(t[k1]),
                 "frames": k1 - k0 + 1, "cut": True, "events": int(events.size),
                 "of_events": rec.n_events})
    return cut, info


def _drop_derived(sims: list[Observation]) -> None:
    """The fitters' derived arrays of ``sims`` let go once a phase of fits is over (they
    are a cache, recomputed when asked for again: a few hundred MB per simulation on a
    user's recording, more than the observation itself)."""
    for o in sims:
        o.extra.clear()


def _moved_on(old: Evaluation, new: Evaluation) -> Evaluation:
    """``new``, once the workflow has moved on from ``old``: ``old``'s simulated
    observations are let go (its statistics stay, for the report; nothing simulates on top
    of it again)."""
    if old is not new:
        old.sims.clear()
    return new


def run_gap(rec: Recording, config: GapConfig | None = None, *,
            progress: Callable[[float], None] | None = None,
            plan: Callable[[float], None] | None = None) -> GapResult:
    """Run the gap workflow on ``rec`` (measured or simulated; it needs frames).

    ``progress(work)`` is called after every simulation with its share of a simulation of
    the whole sensor (a screening on a band of rows is less); ``plan(total)`` with the work
    the run plans (in the same unit), at the start and whenever it changes (it names nothing
    more: the rounds left drop out).

    Raises
    ------
    GapError
        When the recording lacks frames or events between them.
    """
    cfg = config or GapConfig()
    if len(rec.frames) < 4:
        raise GapError("the gap workflow needs a recording with at least 4 frames (APS or "
                       "images.txt): simulations are driven by the measured frames")
    tick = progress or (lambda _work: None)
    full = rec
    rec, window = working_window(rec, cfg.max_pixel_steps, cfg.internal_rate_hz)
    run = _Runner(rec, cfg, tick)
    share = 1.0 if run.band is None else run.band.share
    if plan is not None:
        plan(n_simulations(cfg, band_share=share))
    base = fit_base(rec)
    current = run.evaluate(base, "base model")
    initial = current
    steps: list[Step] = []
    rejected: dict[str, dict[str, Any]] = {}

    def n_sensor() -> int:  # max_effects counts sensor effects, not the timestamp scheme
        return sum(s.effect.name != SCHEME_EFFECT for s in steps)

    while n_sensor() < cfg.max_effects:
        if plan is not None:
            plan(run.work + n_simulations(cfg, cfg.max_effects - n_sensor() + 1, share)
                 - n_simulations(cfg, 0, share))
        tried: dict[str, dict[str, Any]] = {}
        # the timestamp scheme first: once the timestamps are seen to lie on a step grid,
        # every sensor candidate is fitted and simulated with the scheme (how a frame-driven
        # simulator stamps its events changes what its dead time, noise and jitter look like:
        # v2e's refractory period shows only in its slots, neither alone)
        scheme = run.scheme_candidate(current, tried)
        on = scheme[1] if scheme is not None else current
        best = run.best_candidate(on, tried, skip=SCHEME_EFFECT)
        if scheme is not None:
            eff_q, ev_q = scheme
            pen_q = cfg.penalty_per_parameter * eff_q.n_fitted
            q_alone = _gain(current.gap, ev_q.gap + pen_q) > _need(cfg, current)
            joint = best is not None and _gain(ev_q.gap, best[0]) > _need(cfg, ev_q) and \
                _gain(current.gap, best[0] + pen_q) > _need(cfg, current)
            if not (q_alone or joint):
                rejected = tried
                break
            # read off the timestamps: neither bias-corrected nor refined, so the candidates
            # evaluated on top of it stand
            steps.append(Step(eff_q, current, ev_q, tried))
            current = _moved_on(current, ev_q)
            tried = {k: v for k, v in tried.items() if k != SCHEME_EFFECT}
        if best is None or _gain(current.gap, best[0]) <= _need(cfg, current):
            pair = None
            if cfg.beam_width >= 2 and current.gap > cfg.beam_min_gap and \
                    n_sensor() + 2 <= cfg.max_effects:
                pair = run.best_pair(current, tried)
            if pair is None or _gain(current.gap, pair[0]) <= _need(cfg, current):
                rejected = tried
                break
            # named together: each step as the loop would have named it
            (eff_a, ev_a), (eff_b, ev_pair) = pair[1]
            steps.append(Step(eff_a, current, ev_a, tried))
            steps.append(Step(eff_b, ev_a, ev_pair, {}))
            _moved_on(ev_a, ev_pair)
            current = _moved_on(current, ev_pair)
            run.let_go(current)
            continue
        close = run.runner_up(best)
        run.let_go(current, best[2], None if close is None else close[2])
        _, eff, ev = best
        eff, ev = run.finish(current, ev, eff, tried)
        finished = [ev]
        if close is not None:
            # a close second, compared at its bias-corrected value too
            eff2, ev2 = run.finish(current, close[2], close[1], tried)
            finished.append(ev2)
            pen = cfg.penalty_per_parameter
            tried[eff2.name]["finished_gap"] = ev2.gap
            if ev2.gap + pen * eff2.n_fitted < ev.gap + pen * eff.n_fitted and \
                    _gain(current.gap, ev2.gap + pen * eff2.n_fitted) > _need(cfg, current):
                eff, ev = eff2, ev2
        steps.append(Step(eff, current, ev, tried))
        current = _moved_on(current, ev)
        for other in finished:
            _moved_on(other, current)
        run.let_go(current)
    if plan is not None:
        plan(run.work)
    info = {"sensor": str(rec.sensor), "n_events": full.n_events,
            "n_frames": len(full.frames), "duration_s": full.duration_s, "window": window,
            "screen_band_rows": None if run.band is None else
            [run.band.rows.start, run.band.rows.stop],
            "simulations": run.simulations}
    settings = {"seed": cfg.seed, "n_seeds": cfg.n_seeds, "internal_rate_hz": cfg.internal_rate_hz,
                "read_noise_dn": run.settings.read_noise_dn,
                "penalty_per_parameter": cfg.penalty_per_parameter,
                "min_improvement": cfg.min_improvement,
                "min_relative_improvement": cfg.min_relative_improvement}
    # the result keeps each evaluation's model and statistics, not its simulated
    # observations (about 200 MB per evaluation at 2 s of 96x128: a run held 0.4 GB)
    light: dict[int, Evaluation] = {}

    def lighten(ev: Evaluation) -> Evaluation:
        return light.setdefault(id(ev), Evaluation(ev.model, [], ev.disc))

    steps = [Step(s.effect, lighten(s.before), lighten(s.after), s.candidates) for s in steps]
    return GapResult(info, run.meas_stats, lighten(initial), lighten(current), steps, settings,
                     rejected)
