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

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..jsonable import to_jsonable
from ..recording import Recording
from ..sim.effects import Effect
from .explain import unexplained
from .finish import DEBIAS_STEPS, finish, refine
from .model import fit_base
from .runner import (
    SCHEME_EFFECT,
    Evaluation,
    GapConfig,
    Runner,
    gain,
    moved_on,
    need,
    screening_band,
)
from .search import best_candidate, best_pair, runner_up, same_signature, scheme_candidate
from .stats import GapError

__all__ = ["SCHEME_EFFECT", "Evaluation", "GapConfig", "GapResult", "Step", "n_simulations",
           "run_gap", "screening_band", "working_window"]


@dataclass
class Step:
    effect: Effect
    before: Evaluation
    after: Evaluation
    candidates: dict[str, dict[str, Any]]
    # refitted in the final model (GapConfig.refit_named): the value it was named with and
    # the final gap before and after; ``effect`` then holds the refitted value
    refit: dict[str, Any] | None = None

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
                "refit": to_jsonable(s.refit),
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


ANCHOR_SIMS = 2  # simulations an anchor takes, typically (one of them counted as a seed's)


def round_work(cfg: GapConfig, band_share: float, candidates: int, *, names: bool,
               confirms: bool = True) -> float:
    """Work one round is expected to take, in simulations of the whole sensor: each of
    ``candidates`` fitted candidates screened (on a band of ``band_share`` of the rows, see
    :func:`screening_band`), the best confirmed when it ``confirms`` (a second one only on
    a close call, which is not planned) and, in a round that ``names`` an effect, its bias
    correction and refinement."""
    full = ANCHOR_SIMS - 1 + cfg.n_seeds
    screen = ANCHOR_SIMS * band_share if cfg.screen else full
    # a screening on the band is confirmed anew on the whole sensor, one on it is extended
    confirm = (full if band_share < 1.0 else cfg.n_seeds - 1) if cfg.screen else 0
    total = candidates * screen + (confirm if confirms else 0)
    if names:
        # bias correction (its steps on the band with every seed, the corrected value on
        # the whole sensor), refinement (three screenings)
        debias = DEBIAS_STEPS * full if band_share >= 1.0 else \
            DEBIAS_STEPS * (cfg.n_seeds + ANCHOR_SIMS - 1) * band_share + full
        total += debias + 3 * screen
    return total


def n_simulations(cfg: GapConfig, rounds: int = 1, band_share: float = 1.0, *,
                  candidates: int | None = None, named: int = 0, base: bool = True
                  ) -> float:
    """Work the workflow expects, in simulations of the whole sensor (for the progress
    bar's estimate of the time left): the base model on every seed (``base``), ``rounds``
    rounds that name an effect, and the round that names nothing, which ends the run (its
    screenings: a screening that gains too little to name is not confirmed; none when
    ``max_effects`` stops the run first; ``named``: the sensor effects named already).

    An estimate, not a bound: the workflow plans anew at every round, from the candidates
    the last round's fitters found evidence for (``candidates``; all of
    ``cfg.candidates`` before the first round), which are most often far fewer. Planning
    every round that ``max_effects`` allows put the estimate of a run at 2.6x its length."""
    k = len(cfg.candidates) if candidates is None else candidates
    total: float = ANCHOR_SIMS - 1 + cfg.n_seeds if base else 0.0
    rounds = min(rounds, max(cfg.max_effects - named, 0))
    for i in range(rounds):
        total += round_work(cfg, band_share, max(k - i, 0), names=True)
    if named + rounds < cfg.max_effects:
        total += round_work(cfg, band_share, max(k - rounds, 0), names=False, confirms=False)
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
    sub = fr.select(slice(k0, k1 + 1))
    events = rec.events_between(int(t[k0]), int(t[k1]) + 1)
    cut = Recording(rec.sensor, events.copy(), sub, dict(rec.metadata))
    info.update({"first_frame_us": int(t[k0]), "last_frame_us": int(t[k1]),
                 "frames": k1 - k0 + 1, "cut": True, "events": int(events.size)})
    return cut, info


def lookahead(run: Runner, ev: Evaluation, eff: Effect) -> dict[str, Any]:
    """Where naming ``eff`` (evaluated as ``ev``) leads: the round after it screened and
    its best confirmed (:func:`.search.best_candidate`), and the path's score, the next
    effect's when it would be named, else ``ev``'s own (each with ``eff``'s penalty)."""
    pen = run.cfg.penalty_per_parameter
    score = ev.gap + pen * eff.n_fitted
    nxt = best_candidate(run, ev, {}, skip=SCHEME_EFFECT)
    out: dict[str, Any] = {"gap": ev.gap, "next": None, "score": score}
    if nxt is not None:
        out["next"] = {"effect": nxt[1].name, "parameters": nxt[1].parameters(),
                       "gap": nxt[2].gap}
        if gain(ev.gap, nxt[0]) > need(run.cfg, ev):
            out["score"] = nxt[0] + pen * eff.n_fitted
    return out


def refit_named(run: Runner, current: Evaluation, steps: list[Step], i: int) -> Evaluation:
    """Step ``i``'s effect refined anew (:func:`.finish.refine`, the three-point search)
    in the final model ``current``; the step then holds the value kept and its ``refit``
    what it was named with. Each effect's value is settled in the model of its round: an
    effect named later may explain part of what it took on (on the v2e mix a low-pass named
    before the 1 ms dead time read 19.1 Hz for v2e's 16.2, and 16.6 Hz in the final model;
    gap 3.54 -> 1.71). The search keeps the named value unless another clearly beats it on
    every seed."""
    step = steps[i]
    eff = current.model.effects[step.effect.name]
    key = eff.primary
    new_eff, ev = refine(run, current.model, current, eff)
    step.refit = {"named_value": step.effect.parameters()[key], "parameter": key,
                  "gap_before": float(current.gap), "gap_after": float(ev.gap)}
    step.effect = new_eff
    return moved_on(current, ev)


def run_gap(rec: Recording, config: GapConfig | None = None, *,
            progress: Callable[[float], None] | None = None,
            plan: Callable[[float], None] | None = None,
            window: dict[str, Any] | None = None,
            released: Callable[[], object] | None = None) -> GapResult:
    """Run the gap workflow on ``rec`` (measured or simulated; it needs frames).

    ``rec`` is first cut to its working window (:func:`working_window`). A caller that cut
    it already gives ``window`` (the description that returned): the whole recording need
    not stay in memory during the run. ``released()`` is called whenever the run has let go
    of simulations (``evcal gap`` hands the freed memory back to the system there).

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
    if rec.frames is None or len(rec.frames) < 4:
        raise GapError("the gap workflow needs a recording with at least 4 frames (APS or "
                       "images.txt): simulations are driven by the measured frames")
    tick = progress or (lambda _work: None)
    if window is None:
        rec, window = working_window(rec, cfg.max_pixel_steps, cfg.internal_rate_hz,
                                     cfg.max_events)
    # the base fit (its noise scale simulates) does not need the runner's measurement
    # statistics: each is made while the other waits on numba or OpenCV
    with ThreadPoolExecutor(max_workers=1) as pool:
        fitting = pool.submit(fit_base, rec)
        run = Runner(rec, cfg, tick, released)
        share = 1.0 if run.band is None else run.band.share
        if plan is not None:
            plan(n_simulations(cfg, band_share=share))
        base = fitting.result()
    current = run.evaluate(base, "base model")
    initial = current
    steps: list[Step] = []
    rejected: dict[str, dict[str, Any]] = {}

    def n_sensor() -> int:  # max_effects counts sensor effects, not the timestamp scheme
        return sum(s.effect.name != SCHEME_EFFECT for s in steps)

    fitted: int | None = None  # candidates the last round's fitters found evidence for

    while n_sensor() < cfg.max_effects:
        if plan is not None:  # this round and the one that names nothing
            plan(run.work + n_simulations(cfg, 1, share, candidates=fitted, named=n_sensor(),
                                          base=False))
        tried: dict[str, dict[str, Any]] = {}
        # the timestamp scheme first: once the timestamps are seen to lie on a step grid,
        # every sensor candidate is fitted and simulated with the scheme (how a frame-driven
        # simulator stamps its events changes what its dead time, noise and jitter look like:
        # v2e's refractory period shows only in its slots, neither alone)
        scheme = scheme_candidate(run, current, tried)
        on = scheme[1] if scheme is not None else current
        best = best_candidate(run, on, tried, skip=SCHEME_EFFECT)
        n_fitted = len(run.screened_pool)  # the candidates fitted this round
        fitted = max(n_fitted - 1, 0)  # the next round's: one of them is named
        if scheme is not None:
            eff_q, ev_q = scheme
            pen_q = cfg.penalty_per_parameter * eff_q.n_fitted
            q_alone = gain(current.gap, ev_q.gap + pen_q) > need(cfg, current)
            joint = best is not None and gain(ev_q.gap, best[0]) > need(cfg, ev_q) and \
                gain(current.gap, best[0] + pen_q) > need(cfg, current)
            if not (q_alone or joint):
                rejected = tried
                break
            # read off the timestamps: neither bias-corrected nor refined, so the candidates
            # evaluated on top of it stand
            steps.append(Step(eff_q, current, ev_q, tried))
            current = moved_on(current, ev_q)
            tried = {k: v for k, v in tried.items() if k != SCHEME_EFFECT}
        if best is None or gain(current.gap, best[0]) <= need(cfg, current):
            pair = None
            if cfg.beam_width >= 2 and current.gap > cfg.beam_min_gap and \
                    n_sensor() + 2 <= cfg.max_effects:
                pair = best_pair(run, current, tried)
            if pair is None or gain(current.gap, pair[0]) <= need(cfg, current):
                rejected = tried
                break
            (eff_a, ev_a), (eff_b, ev_pair) = pair[1]
            pen = cfg.penalty_per_parameter
            score_a = ev_a.gap + pen * eff_a.n_fitted
            if gain(current.gap, score_a) > need(cfg, current) and \
                    gain(ev_a.gap, ev_pair.gap + pen * eff_b.n_fitted) <= need(cfg, ev_a):
                # the first explains what the pair does alone (confirmed on every seed, it
                # clears the bar that one seed on the band did not), and the second adds
                # nothing that would name it: the first is named as a single, finished
                # like one, and the loop goes on from it
                tried[f"{eff_a.name} + {eff_b.name}"]["note"] = \
                    f"{eff_b.name} adds nothing to {eff_a.name} alone"
                ev_pair.sims.clear()
                best = (score_a, eff_a, ev_a)
            else:
                # named together: each step as the loop would have named it
                steps.append(Step(eff_a, current, ev_a, tried))
                steps.append(Step(eff_b, ev_a, ev_pair, {}))
                moved_on(ev_a, ev_pair)
                current = moved_on(current, ev_pair)
                run.let_go(current)
                continue
        close = runner_up(run, best, current)
        run.let_go(current, best[2], None if close is None else close[2])
        _, eff, ev = best
        eff, ev = finish(run, current, ev, eff, tried)
        finished = [ev]
        if close is not None:
            # a close second, compared at its bias-corrected value too
            eff2, ev2 = finish(run, current, close[2], close[1], tried)
            finished.append(ev2)
            pen = cfg.penalty_per_parameter
            tried[eff2.name]["finished_gap"] = ev2.gap
            qualifies = gain(current.gap, ev2.gap + pen * eff2.n_fitted) > need(cfg, current)
            if qualifies and same_signature(eff.name, eff2.name) and \
                    n_sensor() + 1 < cfg.max_effects:
                # two explanations of the same signature (a late frame stamp and a slow
                # photoreceptor both delay the events): compared by where each leads, the
                # best of the round after it, not by this round alone
                if plan is not None:  # a screened round on each, then the rest as planned
                    one = round_work(cfg, share, n_fitted, names=False)
                    plan(run.work + 2 * one + n_simulations(
                        cfg, 1, share, candidates=fitted, named=n_sensor() + 1, base=False))
                ahead = {e.name: lookahead(run, v, e) for e, v in ((eff, ev), (eff2, ev2))}
                tried[eff2.name]["lookahead"] = ahead
                run.let_go(current, ev, ev2)
                if ahead[eff2.name]["score"] < ahead[eff.name]["score"]:
                    eff, ev = eff2, ev2
            elif ev2.gap + pen * eff2.n_fitted < ev.gap + pen * eff.n_fitted and qualifies:
                eff, ev = eff2, ev2
        steps.append(Step(eff, current, ev, tried))
        current = moved_on(current, ev)
        for other in finished:
            moved_on(other, current)
        run.let_go(current)
    if cfg.refit_named:
        todo = [i for i, s in enumerate(steps) if s.effect.name != SCHEME_EFFECT][:-1]
        if plan is not None and todo:  # each: three screenings and a confirmation
            plan(run.work + len(todo) * round_work(cfg, share, 3, names=False))
        for i in todo:
            current = refit_named(run, current, steps, i)
    if plan is not None:
        plan(run.work)
    info = {"sensor": str(rec.sensor), "n_events": window.get("of_events", rec.n_events),
            "n_frames": window["of_frames"],
            "duration_s": window.get("of_duration_s", rec.duration_s), "window": window,
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

    steps = [Step(s.effect, lighten(s.before), lighten(s.after), s.candidates, s.refit)
             for s in steps]
    return GapResult(info, run.meas_stats, lighten(initial), lighten(current), steps, settings,
                     rejected)
