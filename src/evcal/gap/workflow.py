"""The model-gap loop: fit, simulate, compare, name the missing effect, repeat.

1. Fit the base model (``c``, ``b`` by OffEI at the nominal log offset) and anchor it.
2. Simulate the measured recording under the model with ``n_seeds`` seeds (driven by its
   frames) and compute the standardised discrepancy of every statistic (:mod:`.stats`); the
   gap is their mean (about 1 when the model explains the data), on every row and on the
   held-out rows (:mod:`.runner`).
3. Null calibration (:mod:`.null`): what every candidate's fitter reads, and what its effect
   gains, on the base model's own simulations.
4. A round (:func:`.search.search`): each effect not in the model yet is fitted on the fit
   rows (its fitter may say why it sees nothing), kept when its strength stands above the
   null, simulated on one seed on top of the model; the best are simulated on every seed.
5. The best confirmed candidate is named if it lowers the held-out gap (counted down to 1)
   by more than its penalty, ``min_improvement`` and ``min_relative_improvement`` of the gap
   above 1, and by more than the gain it shows with nothing missing. Its value is then
   refitted on every row, bias-corrected by simulation and refined (:mod:`.finish`).
   Repeat from 4 until nothing is named or ``max_effects`` are.

The timestamp scheme of a frame-driven simulator (``timestamp_quantisation``) is not a
sensor effect: once its fitter sees the timestamps on a step grid, the sensor candidates are
evaluated on top of it, and it is named when it closes the gap alone or with the best of
them.

:class:`GapRun` owns a run: its evaluator, its null calibration, its rounds and steps.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any

import numpy as np

from ..jsonable import to_jsonable
from ..recording import Recording
from ..sim.effects import Effect
from . import effects as registry
from .effects import BEFORE_SENSOR_KINDS, SENSOR_KINDS, FitResult, Fitted
from .explain import unexplained
from .finish import DEBIAS_STEPS, finish, refine
from .model import fit_base
from .null import NullCalibration, calibrate
from .runner import (
    SCHEME_EFFECT,
    Evaluation,
    Evaluator,
    GapConfig,
    gain,
    moved_on,
    need,
    screening_band,
)
from .search import Candidate, Pair, Round, let_go_pairs, search, search_pairs
from .stats import GapError

__all__ = ["SCHEME_EFFECT", "Evaluation", "GapConfig", "GapResult", "GapRun", "Step",
           "n_simulations", "run_gap", "screening_band", "working_window"]

_log = logging.getLogger("evcal.gap")


@dataclass
class Step:
    effect: Effect
    before: Evaluation
    after: Evaluation
    candidates: dict[str, dict[str, Any]]
    # why it was named: its held-out gain against what naming needed (and the null's gain),
    # and the candidates it won over
    why: dict[str, Any] = field(default_factory=dict)
    # refitted in the final model (GapConfig.refit_named): the value it was named with and
    # the final gap before and after; ``effect`` then holds the refitted value
    refit: dict[str, Any] | None = None

    def moved_statistics(self, top: int = 4) -> list[str]:
        drops = {k: self.before.disc.per_stat[k] - self.after.disc.per_stat[k]
                 for k in self.before.disc.per_stat}
        ranked = sorted(drops, key=lambda k: -drops[k])
        return [k for k in ranked[:top] if drops[k] > 0.5]

    def worsened_statistics(self, top: int = 4) -> list[str]:
        """Statistics the step made clearly worse (their D up by more than 1)."""
        rises = {k: self.after.disc.per_stat[k] - self.before.disc.per_stat[k]
                 for k in self.before.disc.per_stat}
        ranked = sorted(rises, key=lambda k: -rises[k])
        return [k for k in ranked[:top] if rises[k] > 1.0]


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
    null: dict[str, Any] = field(default_factory=dict)
    # the pairs of two effects the round that named nothing tried, best first
    # (search.search_pairs; the best one's ``why`` says why it was not named)
    pairs_tried: list[dict[str, Any]] = field(default_factory=list)
    # named effects taken out of the final model again (GapConfig.prune_named): effect,
    # parameters, the step it was named in, the held-out gaps with and without it
    dropped: list[dict[str, Any]] = field(default_factory=list)

    @property
    def named_effects(self) -> list[str]:
        return [s.effect.name for s in self.steps]

    def to_json(self) -> dict[str, Any]:
        """The stable ``report.json`` schema (docs/GAP.md writes it out)."""
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
        light = float(self.recording_info.get("median_light_dn", 128.0))
        return {
            "named_effects": self.named_effects,
            "gap_initial": float(self.initial.gap),
            "gap_final": float(self.final.gap),
            "held_out_gap_initial": float(self.initial.held_gap),
            "held_out_gap_final": float(self.final.held_gap),
            "steps": [{
                "effect": s.effect.name,
                "kind": registry.spec(s.effect.name).kind,
                "parameters": to_jsonable(s.effect.parameters()),
                "value": float(registry.spec(s.effect.name).value(s.effect, light)),
                "in_words": registry.spec(s.effect.name).says(s.effect),
                "gap_before": float(s.before.gap),
                "gap_after": float(s.after.gap),
                "held_out_gap_before": float(s.before.held_gap),
                "held_out_gap_after": float(s.after.held_gap),
                "moved_statistics": s.moved_statistics(),
                "worsened_statistics": s.worsened_statistics(),
                "why": to_jsonable(s.why),
                "refit": to_jsonable(s.refit),
            } for s in self.steps],
            "not_named": {name: {k: c[k] for k in ("status", "reason", "held_out_gap")
                                 if k in c}
                          for name, c in self.rejected.items()},
            "pairs_tried": [{k: p[k] for k in ("pair", "status", "held_out_gap", "score",
                                               "parameters", "first_parameters", "why")
                             if k in p} for p in self.pairs_tried],
            "dropped": self.dropped,
            "statistics": stats,
            # what the final model still does not explain, worst first (also when nothing
            # was named): statistic, regime, direction, in words
            "unexplained": unexplained(d1),
            "window": self.recording_info.get("window"),
        }


def _list(a: np.ndarray) -> list[float | None]:
    """Values for JSON: ``None`` where a statistic had too little data (NaN)."""
    return [float(x) if np.isfinite(x) else None for x in np.asarray(a, np.float64).ravel()]


# a confirmed candidate whose held-out score is within this (or this share of the best's gap
# above 1) of the named one's explains the data as well: the report lists it beside it
EQUIVALENT_MARGIN = 0.3
EQUIVALENT_RELATIVE = 0.1
ANCHOR_SIMS = 2  # simulations an anchor takes, typically (one of them counted as a seed's)
NULL_SIMS = 3  # simulations of the null calibration's gains, typically
# the time a round takes in units of the time before the first round (the base fit, its
# simulations, the measurement's statistics, the null calibration: the same recording's
# work, on the same machine and load): a round that names nothing runs the fitters and
# screens a few candidates; one that names an effect also confirms, corrects and refines it
# (medians over dev recordings of scripts/gap_benchmark.py, 240x180 and 346x260)
ROUND_TIME_LAST = 0.6
ROUND_TIME_NAMING = 1.2
# a model whose gap, left aside what a simulator's timestamp scheme explains, is below this
# is expected to name nothing more (most candidates cannot gain what naming needs there)
GAP_EXPECTED_DONE = 3.0


def round_work(cfg: GapConfig, band_share: float, candidates: int, *, names: bool) -> float:
    """Work one round is expected to take, in simulations of the whole sensor: each of
    ``candidates`` screened candidates (on a band of ``band_share`` of the rows, see
    :func:`screening_band`), the best confirmed and, in a round that ``names`` an effect,
    its bias correction and refinement."""
    full = ANCHOR_SIMS - 1 + cfg.n_seeds
    screen = ANCHOR_SIMS * band_share if cfg.screen else full
    confirm = (full if band_share < 1.0 else cfg.n_seeds - 1) if cfg.screen else 0
    total = candidates * screen + confirm
    if names:
        debias = DEBIAS_STEPS * full if band_share >= 1.0 else \
            DEBIAS_STEPS * (cfg.n_seeds + ANCHOR_SIMS - 1) * band_share + full
        total += debias + 3 * screen
    return total


def n_simulations(cfg: GapConfig, rounds: int = 1, band_share: float = 1.0, *,
                  candidates: int | None = None, named: int = 0, base: bool = True
                  ) -> float:
    """Work the workflow expects, in simulations of the whole sensor (for the progress
    bar's estimate of the time left): the base model on every seed and its null calibration
    (``base``), ``rounds`` rounds that name an effect, and the round that names nothing,
    which ends the run (none when ``max_effects`` stops the run first; ``named``: the
    sensor effects named already).

    An estimate, not a bound: the workflow plans anew at every round from the candidates
    the last round screened (``candidates``; before the first round a third of
    ``cfg.candidates``: most fitters see no evidence on a given recording)."""
    k = max(2, len(cfg.candidates) // 3) if candidates is None else candidates
    total: float = ANCHOR_SIMS - 1 + cfg.n_seeds + NULL_SIMS if base else 0.0
    rounds = min(rounds, max(cfg.max_effects - named, 0))
    for i in range(rounds):
        total += round_work(cfg, band_share, max(k - i, 1), names=True)
    if named + rounds < cfg.max_effects:
        total += round_work(cfg, band_share, max(k - rounds, 1), names=False)
    return total


def working_window(rec: Recording, max_pixel_steps: int, internal_rate_hz: float,
                   max_events: int | None = None) -> tuple[Recording, dict[str, Any]]:
    """``rec`` cut to the contiguous frames with the most events between them whose
    simulation fits ``max_pixel_steps`` (pixels x internal samples) and that hold at most
    ``max_events`` events (at least 3 frame intervals, whatever they hold), or ``rec``
    itself when all of it fits; and what was kept (``window``: first and last frame time,
    frames, events, and the whole recording's).

    The statistics are averages over pixels and windows: a longer recording sharpens them
    far less than it costs. The busiest stretch holds the most information about the sensor
    (still parts are kept when the whole fits)."""
    fr = rec.frames
    if fr is None or len(fr) < 4:
        raise GapError(f"the recording has {0 if fr is None else len(fr)} frames; the gap "
                       "workflow needs at least 4 (APS or images.txt): simulations are driven "
                       "by the measured frames")
    n_pix = rec.sensor.height * rec.sensor.width
    t = fr.t_us
    dur_s = (int(t[-1]) - int(t[0])) * 1e-6
    info: dict[str, Any] = {"first_frame_us": int(t[0]), "last_frame_us": int(t[-1]),
                            "frames": len(fr), "of_frames": len(fr), "cut": False,
                            "of_events": rec.n_events, "of_duration_s": rec.duration_s}
    ev_t = rec.events["t_us"]
    at = np.searchsorted(ev_t, t, side="left")  # events before each frame
    fits_steps = n_pix * (dur_s * internal_rate_hz + len(fr)) <= max_pixel_steps
    if fits_steps and (max_events is None or int(at[-1] - at[0]) <= max_events):
        return rec, info
    max_s = max_pixel_steps / n_pix / internal_rate_hz
    idx = np.arange(t.size)
    # for each first frame, the last frame within max_s (and max_events); the pair with
    # the most events
    last = np.searchsorted(t, t + int(max_s * 1e6), side="right") - 1
    if max_events is not None:
        last = np.minimum(last, np.searchsorted(at, at + max_events, side="right") - 1)
    last = np.maximum(last, np.minimum(idx + 3, t.size - 1))
    counts = at[last] - at[idx]
    k0 = int(np.argmax(counts))
    k1 = int(last[k0])
    cut = rec.frame_window(k0, k1, copy=True)
    info.update({"first_frame_us": int(t[k0]), "last_frame_us": int(t[k1]),
                 "frames": k1 - k0 + 1, "cut": True, "events": cut.n_events})
    return cut, info


class GapRun:
    """One run of the workflow on one recording: the evaluator (:class:`.runner.Evaluator`),
    the null calibration, the rounds and the steps named, and the run's progress.

    ``progress(work)`` is called after every simulation with its share of a simulation of
    the whole sensor (a screening on a band of rows is less); ``plan(total)`` with the work
    the run plans (in the same unit), at the start and whenever it changes. A caller that cut
    ``rec`` to its working window (:func:`working_window`) gives ``window`` (the description
    that returned). ``released()`` is called whenever the run has let go of simulations.
    ``forecast(t_end)`` with the ``time.monotonic()`` the run is expected to end at, at the
    start of every round (:meth:`_forecast`)."""

    def __init__(self, rec: Recording, config: GapConfig | None = None, *,
                 progress: Callable[[float], None] | None = None,
                 plan: Callable[[float], None] | None = None,
                 window: dict[str, Any] | None = None,
                 released: Callable[[], object] | None = None,
                 forecast: Callable[[float], None] | None = None):
        self.cfg = config or GapConfig()
        if rec.frames is None or len(rec.frames) < 4:
            raise GapError("the gap workflow needs a recording with at least 4 frames (APS "
                           "or images.txt): simulations are driven by the measured frames")
        if window is None:
            rec, window = working_window(rec, self.cfg.max_pixel_steps,
                                         self.cfg.internal_rate_hz, self.cfg.max_events)
        self.rec = rec
        self.window = window
        self.tick = progress or (lambda _work: None)
        self.plan_to = plan
        self.forecast_to = forecast
        self._t0 = time.monotonic()
        self._base_s: float | None = None  # the time before the first round
        self.released = released
        self.steps: list[Step] = []
        self.rejected: dict[str, dict[str, Any]] = {}
        # the pairs of the last round that named nothing (search_pairs), for the report
        self.pairs_tried: list[dict[str, Any]] = []
        # named effects the backward step (_prune) took out of the final model
        self.dropped: list[dict[str, Any]] = []
        # scene effects fitted before the rounds and not named (with the reason)
        self.scene_rejected: dict[str, dict[str, Any]] = {}
        # the model each scene effect was last tried on
        self._scene_tried: dict[str, Evaluation] = {}
        self._scene_fit: dict[str, FitResult] = {}
        self.null = NullCalibration()
        # seconds each candidate's fit and screening took in its last round (the next
        # round starts the slowest first)
        self.seconds: dict[str, float] = {}
        self.ev: Evaluator | None = None

    def _plan(self, total: float) -> None:
        if self.plan_to is not None:
            self.plan_to(total)

    def _forecast(self, current: Evaluation) -> None:
        """Say when the run is expected to end (a ``time.monotonic()``) at the start of a
        round: the rounds it expects (one naming an effect where ``current``'s gap, left
        aside the statistics a timestamp scheme moves while none is named, is at least
        :data:`GAP_EXPECTED_DONE` and ``max_effects`` allows one, then one naming nothing),
        each taking a share (:data:`ROUND_TIME_NAMING`, :data:`ROUND_TIME_LAST`) of the time
        before the first round. Time, not simulations: a round's fitters and statistics
        take much of it, and a simulation's share of it differs from phase to phase."""
        now = time.monotonic() - self._t0
        if self._base_s is None:
            self._base_s = now
        if self.forecast_to is None:
            return
        per = dict(current.held.per_stat or current.disc.per_stat)
        if SCHEME_EFFECT not in current.model.effects:
            for name in registry.spec(SCHEME_EFFECT).moves:
                per.pop(name, None)
        gap = float(np.mean(list(per.values()))) if per else 0.0
        naming = int(gap >= GAP_EXPECTED_DONE and self.n_sensor() < self.cfg.max_effects)
        self.forecast_to(time.monotonic()
                         + self._base_s * (naming * ROUND_TIME_NAMING + ROUND_TIME_LAST))

    def n_sensor(self) -> int:
        """Effects named that count against ``max_effects``: the sensor's (not the timestamp
        scheme, not the scene's flicker)."""
        return sum(registry.spec(s.effect.name).kind in SENSOR_KINDS for s in self.steps)

    def run(self) -> GapResult:
        cfg = self.cfg
        pen = cfg.penalty_per_parameter
        # the base fit (its noise scale simulates) does not need the evaluator's measurement
        # statistics: each is made while the other waits on numba or OpenCV
        with ThreadPoolExecutor(max_workers=1) as pool:
            fitting = pool.submit(fit_base, self.rec)
            ev = self.ev = Evaluator(self.rec, cfg, self.tick, self.released)
            share = 1.0 if ev.band is None else ev.band.share
            self._plan(n_simulations(cfg, band_share=share))
            base = fitting.result()
        current = ev.evaluate(base, "base model")
        initial = current
        # the scene's light before the sensor: a flicker the frames cannot show moves every
        # statistic, and each sensor effect fitted under it would answer for part of it
        current = self._scenes(current)
        sensor = [n for n in cfg.candidates if registry.spec(n).kind in SENSOR_KINDS]
        self.null = calibrate(ev, current, sensor)
        screened: int | None = None
        scheme_refused = False
        while self.n_sensor() < cfg.max_effects:
            self._plan(ev.work + n_simulations(cfg, 1, share, candidates=screened,
                                               named=self.n_sensor(), base=False))
            self._forecast(current)
            # tried again on what the last round named (a flicker's gain is small beside
            # the gap of a simulator's scheme, and shows once that is named)
            current = self._scenes(current)
            scheme = self._scheme(current) if not scheme_refused else None
            on = scheme[1] if scheme is not None else current
            names = [n for n in sensor if n not in on.model.effects]
            rnd = search(ev, self.null, on, names, self.seconds)
            screened = max(sum(c.evaluation is not None for c in rnd.candidates.values()) - 1,
                           1)
            rnd.judge_signatures(on, cfg.min_signature_share)
            tried = rnd.to_json(pen)
            best = rnd.best(pen)
            if scheme is not None:
                eff_q, ev_q, entry = scheme
                tried = {SCHEME_EFFECT: entry, **tried}
                how = self._scheme_named(current, scheme, best)
                if how is None:
                    # the round again without it (its candidates were fitted on top of it)
                    self.rejected[SCHEME_EFFECT] = entry
                    scheme_refused = True
                    rnd.let_go()
                    ev_q.sims.clear()
                    continue
                # read off the timestamps: neither bias-corrected nor refined, so the
                # candidates evaluated on top of it stand
                self.steps.append(Step(eff_q, current, ev_q, {SCHEME_EFFECT: entry}, how))
                current = moved_on(current, ev_q)
            why = self._why(rnd, on, best)
            if (best is None or not why["named"]) and self._pairs_due(on):
                named = self._pair(rnd, current, on, tried)
                if named is not None:
                    current = named
                    scheme_refused = False
                    if ev.released is not None:
                        ev.released()
                    continue
            if best is None or not why["named"]:
                # the scheme's own entry (no evidence, or refused in an earlier round) stays
                # in the report (_result leaves out what the model holds)
                kept = {k: v for k, v in self.rejected.items() if k == SCHEME_EFFECT}
                self.rejected = {**kept, **tried}
                rnd.let_go()
                break
            assert best.evaluation is not None
            assert best.effect is not None
            rnd.let_go(on, best.evaluation)
            eff, after, info = self._finish(on, best)
            tried[best.name]["status"] = "named"
            tried[best.name]["finish"] = to_jsonable(info)
            self.steps.append(Step(eff, current, after, tried, why))
            if after is not best.evaluation:
                moved_on(best.evaluation, after)
            current = moved_on(current, after)
            # a scheme refused beside this round's best is tried again beside the next one
            # (v2e's dead time, which shows only in its slots, may come after a low-pass)
            scheme_refused = False
            if ev.released is not None:
                ev.released()
        current = self._scenes(current)
        if cfg.prune_named:
            current = self._prune(current)
        if cfg.refit_named:
            todo = [i for i, s in enumerate(self.steps)
                    if registry.spec(s.effect.name).kind in SENSOR_KINDS][:-1]
            if todo:  # each: three screenings and a confirmation
                self._plan(ev.work + len(todo) * round_work(cfg, share, 3, names=False))
            for i in todo:
                current = self._refit(current, i)
        self._plan(ev.work)
        return self._result(initial, current)

    def _scenes(self, current: Evaluation) -> Evaluation:
        """``current`` with the effects tried before the sensor's (the scene's light, how
        the recording began: ``BEFORE_SENSOR_KINDS``) it lacks that :meth:`_scene` names,
        each tried once on a given model."""
        for name in self.cfg.candidates:
            if registry.spec(name).kind not in BEFORE_SENSOR_KINDS or \
                    name in current.model.effects or \
                    self._scene_tried.get(name) is current:
                continue
            self._scene_tried[name] = current
            current = self._scene(current, name)
        return current

    def _scene(self, current: Evaluation, name: str) -> Evaluation:
        """Effect ``name`` of a kind tried before the sensor's (a flicker of the light, a
        reset at the start) fitted on the fit rows (by simulations of the model with it),
        evaluated on every seed and named when it gains on the held-out rows what naming
        needs; ``current`` unchanged otherwise (the reason in the report's candidates of the
        last round)."""
        ev = self.ev
        assert ev is not None
        cfg = self.cfg
        # fitted once, on the first model tried (the base model: a simulator's scheme named
        # later stamps the simulations on steps that reshape the line the fit matches),
        # judged again on each model after it
        res = self._scene_fit.get(name)
        if res is None:
            ctx = replace(ev.fit_context(current.model, current.sims),
                          simulate=partial(ev.simulate_with, current.model))
            res = self._scene_fit[name] = registry.spec(name).fit(ctx)
        if not isinstance(res, Fitted):
            self.scene_rejected[name] = {"status": "no evidence", "reason": res.reason}
            return current
        eff = res.effect
        out = ev.evaluate(ev.candidate_model(current.model, eff), f"candidate {name}")
        pen = cfg.penalty_per_parameter * eff.n_fitted
        score = float(out.held_gap + pen)
        g = gain(current.held_gap, score)
        needed = need(cfg, current.held_gap)
        entry = {"status": "confirmed", "parameters": to_jsonable(eff.parameters()),
                 "gap": float(out.gap), "held_out_gap": float(out.held_gap), "score": score,
                 "seeds": out.disc.n_sims, "fit": to_jsonable(res.detail),
                 "held_out_statistics": {k: float(v) for k, v in out.held.per_stat.items()}}
        if g <= needed:
            entry["status"] = "not named"
            entry["reason"] = (f"its held-out gain {g:.3g} is below the {needed:.3g} naming "
                               "needs")
            self.scene_rejected[name] = entry
            out.sims.clear()
            return current
        entry["status"] = "named"
        self.scene_rejected.pop(name, None)
        why = {"named": True, "effect": name, "held_out_gap": float(current.held_gap),
               "score": score, "held_out_gain": float(g), "needed_gain": float(needed),
               "null_gain": 0.0, "ranked_below": [], "equivalent": [],
               registry.spec(name).kind: True}
        self.steps.append(Step(eff, current, out, {name: entry}, why))
        return moved_on(current, out)

    def _scheme(self, current: Evaluation) -> tuple[Effect, Evaluation, dict[str, Any]] | None:
        """The timestamp scheme fitted (on every row: a property of every event's stamp)
        and evaluated on every seed, when it is a candidate not yet in the model and its
        fitter sees it."""
        ev = self.ev
        assert ev is not None
        if SCHEME_EFFECT not in self.cfg.candidates or SCHEME_EFFECT in current.model.effects:
            return None
        res = registry.spec(SCHEME_EFFECT).fit(
            ev.fit_context(current.model, current.sims, held_out=False))
        if not isinstance(res, Fitted):
            self.rejected[SCHEME_EFFECT] = {"status": "no evidence", "reason": res.reason}
            return None
        eff = res.effect
        out = ev.evaluate(ev.candidate_model(current.model, eff), f"candidate {eff.name}")
        entry = {"status": "confirmed", "parameters": to_jsonable(eff.parameters()),
                 "gap": float(out.gap), "held_out_gap": float(out.held_gap),
                 "score": float(out.held_gap + self.cfg.penalty_per_parameter * eff.n_fitted),
                 "seeds": out.disc.n_sims}
        return eff, out, entry

    def _scheme_named(self, current: Evaluation,
                      scheme: tuple[Effect, Evaluation, dict[str, Any]],
                      best: Candidate | None) -> dict[str, bool] | None:
        """Whether the timestamp scheme is named against ``current`` (how: ``alone``,
        ``with_the_best``), or ``None`` (its entry then says why not). Alone when it
        closes the gap by what naming needs; with the round's best sensor effect (evaluated
        on top of it) when the pair does and beats that effect fitted without the scheme by
        what naming needs: a scheme that helps only beside an effect which does as well
        without it is that effect's doing (a simulator's leak stamped on its steps puts
        events on a grid too), while v2e's dead time shows only in its slots, with the
        scheme."""
        cfg = self.cfg
        pen = cfg.penalty_per_parameter
        eff_q, ev_q, entry = scheme
        pen_q = pen * eff_q.n_fitted
        if gain(current.held_gap, ev_q.held_gap + pen_q) > need(cfg, current.held_gap):
            return {"alone": True, "with_the_best": False}
        joint = best is not None and \
            gain(ev_q.held_gap, best.score(pen)) > need(cfg, ev_q.held_gap) and \
            gain(current.held_gap, best.score(pen) + pen_q) > need(cfg, current.held_gap)
        if joint:
            assert best is not None
            alone = self._without_scheme(current, best.name)
            if alone is not None:
                entry["best_without_scheme"] = float(alone.held_gap)
                joint = gain(alone.held_gap, best.score(pen) + pen_q) > \
                    need(cfg, alone.held_gap)
                alone.sims.clear()
        if joint:
            return {"alone": False, "with_the_best": True}
        entry["status"] = "not named"
        entry["reason"] = ("the timestamps lie on a grid, but a simulator's scheme neither "
                           "closes the gap alone nor, beside the best sensor effect, beats "
                           "that effect without it")
        return None

    def _without_scheme(self, current: Evaluation, name: str) -> Evaluation | None:
        """Effect ``name`` fitted on ``current`` (no timestamp scheme) and evaluated on
        every seed; ``None`` when its fitter sees nothing there."""
        ev = self.ev
        assert ev is not None
        res = registry.spec(name).fit(ev.fit_context(current.model, current.sims))
        if not isinstance(res, Fitted):
            return None
        return ev.evaluate(ev.candidate_model(current.model, res.effect), f"{name} alone")

    def _why(self, rnd: Round, on: Evaluation, best: Candidate | None) -> dict[str, Any]:
        """Whether ``best`` is named, and why: its held-out gain, what naming needs (the
        configured least gain, and the gain its effect shows with nothing missing), and
        the candidates it was ranked above."""
        cfg = self.cfg
        pen = cfg.penalty_per_parameter
        needed = need(cfg, on.held_gap)
        if best is None:
            passed_over = [c.name for c in rnd.ranked(pen) if c.passed_over]
            reason = ("no candidate stood above the null and gained enough on one seed to be "
                      "confirmed") if not passed_over else (
                f"the gain of the confirmed {', '.join(passed_over)} lay outside the "
                "statistics their effects move")
            return {"named": False, "held_out_gap": float(on.held_gap),
                    "needed_gain": float(needed), "reason": reason}
        g = gain(on.held_gap, best.score(pen))
        assert self.ev is not None
        # what the effect gains with nothing missing: measured only for a candidate that
        # would be named without it (a simulation or three)
        null_gain = self.null.gain(self.ev, best.name) if g > needed else 0.0
        others = [{"effect": c.name, "status": c.status, "score": float(c.score(pen))}
                  for c in rnd.ranked(pen) if c is not best]
        # confirmed alternatives the held-out rows cannot tell from it: both at the floor
        # of the comparison (a gap of 1), or within a close margin of it
        close = max(EQUIVALENT_MARGIN, EQUIVALENT_RELATIVE * (best.score(pen) - 1.0))
        floor = max(best.score(pen), 1.0) + close
        equivalent = [c.name for c in rnd.ranked(pen) if c is not best and
                      c.status == "confirmed" and max(c.score(pen), 1.0) <= floor]
        return {"named": bool(g > needed + null_gain), "effect": best.name,
                "held_out_gap": float(on.held_gap), "score": float(best.score(pen)),
                "held_out_gain": float(g), "needed_gain": float(needed),
                "null_gain": float(null_gain), "ranked_below": others,
                "equivalent": equivalent}

    def _pairs_due(self, on: Evaluation) -> bool:
        """Whether a round that named no single effect tries pairs: room for two more sensor
        effects and a held-out gap still above ``pair_min_gap``."""
        cfg = self.cfg
        return cfg.pair_top >= 2 and self.n_sensor() + 2 <= cfg.max_effects and \
            on.held_gap > cfg.pair_min_gap

    def _pair_why(self, pair: Pair, on: Evaluation) -> dict[str, Any]:
        """Whether ``pair`` is named, and why: its held-out gain over ``on`` against what
        naming needs plus both effects' gains with nothing missing; what each effect adds to
        the other alone (each must add what naming a single needs); the share of its gain
        on the statistics either effect moves."""
        cfg = self.cfg
        pen = cfg.penalty_per_parameter
        assert self.ev is not None
        score = pair.score(pen)
        g = gain(on.held_gap, score)
        needed = need(cfg, on.held_gap)
        adds: dict[str, dict[str, Any]] = {}
        for c, other in ((pair.first, pair.second.name), (pair.alone, pair.first.name)):
            alone = c.score(pen) if c.status == "confirmed" else math.inf
            adds[other] = {"alone": c.name, "alone_score": float(alone),
                           "added_gain": float(gain(alone, score)) if math.isfinite(alone)
                           else math.nan,
                           "needed_gain": float(need(cfg, alone)) if math.isfinite(alone)
                           else math.nan}
        each = all(math.isfinite(a["alone_score"]) and a["added_gain"] > a["needed_gain"]
                   for a in adds.values())
        null_gain = (self.null.gain(self.ev, pair.first.name) +
                     self.null.gain(self.ev, pair.second.name)) if g > needed and each else 0.0
        share = pair.signature_share(on)
        sig_ok = cfg.min_signature_share <= 0 or not math.isfinite(share) or \
            share >= cfg.min_signature_share * pair.even_share(on)
        named = bool(g > needed + null_gain and each and sig_ok)
        reason = "" if named else (
            f"the pair's held-out gain {g:.2f} is below the {needed + null_gain:.2f} needed"
            if g <= needed + null_gain else
            "one of the two adds less to the other alone than naming a single needs"
            if not each else
            f"{100 * share:.0f} % of its held-out gain falls on the statistics its effects "
            "move: it absorbs a misfit they do not describe")
        return {"named": named, "effect": pair.first.name, "pair": list(pair.names),
                "held_out_gap": float(on.held_gap), "score": float(score),
                "held_out_gain": float(g), "needed_gain": float(needed),
                "null_gain": float(null_gain), "each_adds": adds,
                "signature_share": float(share), "reason": reason}

    def _pair(self, rnd: Round, current: Evaluation, on: Evaluation,
              tried: dict[str, dict[str, Any]]) -> Evaluation | None:
        """Two effects named at once (:func:`.search.search_pairs`) when the round named
        no single one; the model with both (the second finished as a single is), or
        ``None`` (the pairs tried kept for the report)."""
        ev = self.ev
        assert ev is not None
        pen = self.cfg.penalty_per_parameter
        pairs = search_pairs(ev, on, rnd)
        conf = [p for p in pairs if p.second.status == "confirmed"]
        whys = {id(p): self._pair_why(p, on) for p in conf[:1]}
        self.pairs_tried = [{**p.to_json(pen), **({"why": whys[id(p)]} if id(p) in whys
                                                   else {})} for p in pairs]
        if not conf or not whys[id(conf[0])]["named"]:
            let_go_pairs(pairs)
            return None
        p = conf[0]
        a, b = p.first, p.second
        assert a.effect is not None
        assert a.evaluation is not None
        assert b.effect is not None
        assert b.evaluation is not None
        why = whys[id(p)]
        rnd.let_go(on, a.evaluation)
        let_go_pairs(pairs, b.evaluation)
        tried[a.name]["status"] = "named"
        tried[a.name]["pair"] = list(p.names)
        self.steps.append(Step(a.effect, current, a.evaluation, tried, why))
        eff, after, info = self._finish(a.evaluation, b)
        entry = b.to_json(pen)
        entry.update(status="named", finish=to_jsonable(info), pair=list(p.names))
        self.steps.append(Step(eff, a.evaluation, after, {b.name: entry},
                               {**why, "effect": b.name}))
        self.pairs_tried = []
        if after is not b.evaluation:
            moved_on(b.evaluation, after)
        moved_on(current, a.evaluation)
        return moved_on(a.evaluation, after)

    def _finish(self, on: Evaluation, best: Candidate
                ) -> tuple[Effect, Evaluation, dict[str, Any]]:
        """``best`` refitted on every row (its moment), bias-corrected and refined."""
        ev = self.ev
        assert ev is not None
        assert best.effect is not None
        assert best.evaluation is not None
        spec = registry.spec(best.name)
        key = best.effect.primary
        res = spec.fit(ev.fit_context(on.model, on.sims, held_out=False))
        moment = float(res.effect.parameters()[key]) if isinstance(res, Fitted) else \
            float(best.effect.parameters()[key])
        eff, after, info = finish(ev, on, best.evaluation, best.effect, moment)
        info["fit_rows_value"] = float(best.effect.parameters()[key])
        return eff, after, info

    def _prune(self, current: Evaluation) -> Evaluation:
        """Each sensor effect of a final model of two or more taken out in turn
        (:meth:`_prune_one`) until none can be. A single named in an early round can be made
        redundant by what later rounds named (a power law of the thresholds in the dark,
        then a dark level with a frame lag as a pair); the workflow's rounds only add."""
        while True:
            out = self._prune_one(current)
            if out is None:
                return current
            current = out

    def _keeps(self, current: Evaluation, name: str, without: float, on: float) -> float:
        """What effect ``name`` of ``current`` gains over the model without it (held-out
        gaps ``without`` and ``on``, its complexity penalty counted), less what naming it
        would need."""
        cfg = self.cfg
        n = current.model.effects[name].n_fitted
        return gain(without, on + cfg.penalty_per_parameter * n) - need(cfg, without)

    def _prune_one(self, current: Evaluation) -> Evaluation | None:
        """Every sensor effect of ``current`` (two or more) taken out, screened on one seed;
        the one whose absence costs least, unless its screening shows it gaining twice what
        naming needs, confirmed on every seed and dropped when its gain there is less than
        naming it last would need: the model without it, or ``None``."""
        ev = self.ev
        assert ev is not None
        cfg = self.cfg
        names = [s.effect.name for s in self.steps
                 if registry.spec(s.effect.name).kind in SENSOR_KINDS]
        if len(names) < 2:
            return None
        share = 1.0 if ev.band is None else ev.band.share
        self._plan(ev.work + round_work(cfg, share, len(names), names=False))
        base = ev.screen_gap(current) if cfg.screen else current.held_gap
        with ThreadPoolExecutor(max_workers=max(1, min(ev.workers, len(names)))) as pool:
            screened = dict(zip(names, pool.map(
                lambda n: ev.evaluate(ev.model_without(current.model, n),
                                      f"screen without {n}",
                                      spread=current if cfg.screen else None), names),
                strict=True))
        order = sorted(names, key=lambda n: self._keeps(current, n, screened[n].held_gap,
                                                        base))
        name = order[0]
        for n in order[1:]:
            screened[n].sims.clear()
        if self._keeps(current, name, screened[name].held_gap, base) > \
                need(cfg, screened[name].held_gap):
            screened[name].sims.clear()
            return None
        without = ev.confirm(screened[name], f"confirm without {name}")
        if without is not screened[name]:
            screened[name].sims.clear()
        if self._keeps(current, name, without.held_gap, current.held_gap) > 0.0:
            without.sims.clear()
            return None
        i = next(i for i, s in enumerate(self.steps) if s.effect.name == name)
        step = self.steps.pop(i)
        self.dropped.append({
            "effect": name, "parameters": to_jsonable(step.effect.parameters()),
            "named_in_step": i + 1, "held_out_gap_with": float(current.held_gap),
            "held_out_gap_without": float(without.held_gap), "gap_without": float(without.gap),
            "needed_gain": float(need(cfg, without.held_gap))})
        _log.info("dropped %s: the model without it has a held-out gap of %.2f, with it %.2f",
                  name, without.held_gap, current.held_gap)
        return moved_on(current, without)

    def _refit(self, current: Evaluation, i: int) -> Evaluation:
        """Step ``i``'s effect refined anew (:func:`.finish.refine`, the three-point
        search) in the final model ``current``; the step then holds the value kept and its
        ``refit`` what it was named with. Each effect's value is settled in the model of its
        round: an effect named later may explain part of what it took on. The search keeps
        the named value unless another clearly beats it on every seed."""
        ev = self.ev
        assert ev is not None
        step = self.steps[i]
        eff = current.model.effects[step.effect.name]
        key = eff.primary
        new_eff, out = refine(ev, current.model, current, eff)
        step.refit = {"named_value": step.effect.parameters()[key], "parameter": key,
                      "gap_before": float(current.gap), "gap_after": float(out.gap)}
        step.effect = new_eff
        return moved_on(current, out)

    def _result(self, initial: Evaluation, current: Evaluation) -> GapResult:
        ev = self.ev
        assert ev is not None
        cfg = self.cfg
        window = self.window
        rec = self.rec
        info = {"sensor": str(rec.sensor), "n_events": window.get("of_events", rec.n_events),
                "n_frames": window["of_frames"],
                "duration_s": window.get("of_duration_s", rec.duration_s), "window": window,
                "screen_band_rows": None if ev.band is None else
                [ev.band.rows.start, ev.band.rows.stop],
                "simulations": ev.simulations,
                "median_light_dn": ev.light_dn,
                "subframe_motion": dict(ev.shift_info) if ev.shift_info else None}
        settings = {"seed": cfg.seed, "n_seeds": cfg.n_seeds,
                    "internal_rate_hz": cfg.internal_rate_hz,
                    "read_noise_dn": ev.settings.read_noise_dn,
                    "penalty_per_parameter": cfg.penalty_per_parameter,
                    "min_improvement": cfg.min_improvement,
                    "min_relative_improvement": cfg.min_relative_improvement,
                    "min_signature_share": cfg.min_signature_share,
                    "null_factor": cfg.null_factor}
        # the result keeps each evaluation's model and statistics, not its simulated
        # observations (about 200 MB per evaluation at 2 s of 96x128)
        light: dict[int, Evaluation] = {}

        def lighten(e: Evaluation) -> Evaluation:
            return light.setdefault(id(e), e.lightened())

        steps = [Step(s.effect, lighten(s.before), lighten(s.after), s.candidates, s.why,
                      s.refit) for s in self.steps]
        # what the last round tried and the model does not hold (the scheme named in that
        # round is in its candidates, and in the model)
        not_named = {k: v for k, v in {**self.scene_rejected, **self.rejected}.items()
                     if k not in current.model.effects}
        return GapResult(info, ev.meas_stats, lighten(initial), lighten(current), steps,
                         settings, not_named, self.null.to_json(), self.pairs_tried,
                         self.dropped)


def run_gap(rec: Recording, config: GapConfig | None = None, *,
            progress: Callable[[float], None] | None = None,
            plan: Callable[[float], None] | None = None,
            window: dict[str, Any] | None = None,
            released: Callable[[], object] | None = None,
            forecast: Callable[[float], None] | None = None) -> GapResult:
    """Run the gap workflow on ``rec`` (measured or simulated; it needs frames): see
    :class:`GapRun` for the arguments.

    Raises
    ------
    GapError
        When the recording lacks frames or events between them.
    """
    return GapRun(rec, config, progress=progress, plan=plan, window=window,
                  released=released, forecast=forecast).run()
