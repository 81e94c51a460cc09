"""The search over candidate effects in a round of the gap workflow: the timestamp scheme,
every sensor candidate fitted and screened (the best confirmed on every seed), the close
runner-up, and pairs of the best singles when no single one qualifies."""

from __future__ import annotations

import math
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from ..sim.effects import Effect
from .model import Model, fit_candidate, variants
from .runner import SCHEME_EFFECT, Evaluation, Runner, drop_derived, gain


def scheme_candidate(run: Runner, current: Evaluation, tried: dict[str, dict[str, Any]]
                     ) -> tuple[Effect, Evaluation] | None:
    """The timestamp scheme fitted and evaluated, when it is a candidate not yet in the
    model and its fitter sees it."""
    if SCHEME_EFFECT not in run.cfg.candidates or SCHEME_EFFECT in current.model.effects:
        return None
    eff = fit_candidate(SCHEME_EFFECT, run.meas, current.sims, current.model, run.rec)
    if eff is None:
        tried[SCHEME_EFFECT] = {"parameters": None, "gap": None}
        return None
    ev = run.evaluate(run.candidate_model(current.model, eff), f"candidate {eff.name}")
    tried[SCHEME_EFFECT] = {"parameters": eff.parameters(), "gap": ev.gap,
                            "score": ev.gap + run.cfg.penalty_per_parameter * eff.n_fitted}
    return eff, ev


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


def best_candidate(run: Runner, current: Evaluation, tried: dict[str, dict[str, Any]], *,
                   skip: str) -> tuple[float, Effect, Evaluation] | None:
    """Every candidate but ``skip`` not in ``current``'s model, fitted from its
    simulations and evaluated on top of it; the one of the lowest score.

    Screened first (one seed each, the candidates in parallel, the spread of the
    statistics from ``current``); the ``confirm_top`` best are simulated with every seed
    and compared on that."""
    run.screened_pool = {}
    run.confirmed = []
    run.screen_base = math.inf
    fitted: list[tuple[str, Effect]] = []
    evals: list[Evaluation] = []
    names = [n for n in run.cfg.candidates if n not in current.model.effects and n != skip]
    if run.cfg.screen and run.band is not None:
        run.band_spread(current)  # once, before the threads ask for it

    def fit_and_screen(name: str) -> tuple[Effect | None, list[Effect], list[Evaluation]]:
        """A candidate fitted and, when screening, its variants screened at once: the
        fitters (numpy, holding the GIL in part) and the simulations of the candidates
        fitted first (numba, without it) share the cores."""
        t0 = time.perf_counter()
        try:
            eff = fit_candidate(name, run.meas, current.sims, current.model, run.rec)
            if eff is None:
                return None, [], []
            # discrete alternatives the moment estimate cannot tell: the gap decides
            alts = variants(eff)
            if not run.cfg.screen:
                return eff, alts, []
            return eff, alts, [run.evaluate(run.candidate_model(current.model, e),
                                             f"screen {e.name}", spread=current)
                               for e in alts]
        finally:
            run.task_s[name] = time.perf_counter() - t0

    with ThreadPoolExecutor(max_workers=run.workers) as pool:
        # longest first (each candidate's time in the last round, else the usual order of
        # costs): the round ends when its last task does, and a long one started last
        # leaves the other cores idle while it runs
        order = longest_first(names, run.task_s)
        done = dict(zip(order, pool.map(fit_and_screen, order), strict=True))
    done_in_order = [done[n] for n in names]
    drop_derived(current.sims)
    for name, (eff, alts, screened) in zip(names, done_in_order, strict=True):
        if eff is None:
            tried[name] = {"parameters": None, "gap": None}
            continue
        fitted += [(name, e) for e in alts]
        evals += screened
    if not fitted:
        return None
    if not run.cfg.screen:
        evals = run.evaluate_many([(e, run.candidate_model(current.model, e))
                                    for _, e in fitted], current)
    pen = run.cfg.penalty_per_parameter
    ranked = sorted(range(len(fitted)),
                    key=lambda i: evals[i].gap + pen * fitted[i][1].n_fitted)
    if run.cfg.screen:
        _confirm_ranked(run, current, fitted, evals, ranked)
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
            run.confirmed.append((score, eff, ev))
            if best is None or score < best[0]:
                best = (score, eff, ev)
        run.screened_pool[name] = (eff, ev)
    run.confirmed.sort(key=lambda t: t[0])
    # only the beam's candidates are simulated on top of; the others' observations
    # (a hundred MB each at 240x180) are let go now, not at the end of the round
    keep = {id(run.screened_pool[n][1]) for n in beam_top(run, tried)}
    keep |= {id(ev) for _, _, ev in run.confirmed}
    for ev in evals:
        if id(ev) not in keep:
            ev.sims.clear()
    return best


def _confirm_ranked(run: Runner, current: Evaluation, fitted: list[tuple[str, Effect]],
                    evals: list[Evaluation], ranked: list[int]) -> None:
    """The ``confirm_top`` best screened candidates confirmed, each only when its
    screened gain reaches half the gain that names, against the current model's gap
    where it was screened (on the band, the band's): what falls that short does not
    qualify on every seed either. The ones after the best only when their screened
    score is within ``confirm_within`` close margins (:func:`runner_up`) of the best's:
    one seed misjudges a candidate by less than that, so one further behind would be
    neither named nor a close call on every seed (road.aedat4's second, 23.1 on the band
    against the lag's 10.3, was confirmed at 33.4 against 8.8: 16 s for nothing). An
    effect whose moment estimate is biased far from its value while another explains
    the same signature is finished beside that one anyway (:data:`SAME_SIGNATURE`)."""
    cfg = run.cfg
    pen = cfg.penalty_per_parameter
    base = run.band_spread(current).gap if run.band is not None else current.gap
    run.screen_base = base
    need = max(cfg.min_improvement, cfg.min_relative_improvement * (base - 1.0))
    todo: list[int] = []
    lead = math.inf
    for i in ranked[:cfg.confirm_top]:
        score = evals[i].gap + pen * fitted[i][1].n_fitted
        lead = min(lead, score)
        margin = max(cfg.close_margin, cfg.close_relative * (lead - 1.0))
        if score > lead + cfg.confirm_within * margin:
            break
        if not evals[i].screened:
            continue
        if gain(base, score) <= 0.5 * need:
            break
        todo.append(i)
    # side by side: each anchor's simulations run one after the other
    with ThreadPoolExecutor(max_workers=max(1, min(run.workers, len(todo)))) as pool:
        done = list(pool.map(lambda i: run.confirm(evals[i], f"confirm {fitted[i][0]}"),
                             todo))
    for i, ev in zip(todo, done, strict=True):
        evals[i] = ev


def beam_top(run: Runner, tried: dict[str, dict[str, Any]]) -> list[str]:
    """The ``beam_width`` screened candidates of the lowest score."""
    singles = sorted((tried[n]["score"], n) for n in run.screened_pool
                     if tried.get(n, {}).get("score") is not None)
    return [n for _, n in singles[:run.cfg.beam_width]]


# effects that explain the same signature (a first-order low-pass of the photoreceptor
# delays events much as a late frame stamp does): when either is the best, the other is
# finished beside it whatever its screening says, and when both are finished the workflow
# compares them by the round after each (evcal.gap.workflow.lookahead)
SAME_SIGNATURE = {"exposure": "bandwidth"}


def signature_alternative(name: str) -> str | None:
    """The effect that explains the same signature as ``name`` (either way round)."""
    for a, b in SAME_SIGNATURE.items():
        if name in (a, b):
            return b if name == a else a
    return None


def same_signature(a: str, b: str) -> bool:
    """Whether effects ``a`` and ``b`` explain the same signature."""
    return signature_alternative(a) == b


def runner_up(run: Runner, best: tuple[float, Effect, Evaluation], current: Evaluation
              ) -> tuple[float, Effect, Evaluation] | None:
    """The confirmed candidate of another effect whose score is within ``close_margin``
    of ``best``'s (or ``close_relative`` of its gap above 1): moment estimates can be
    biased (a threshold that grows in the dark reads 0.8x its exponent, a bandwidth
    limit 0.5x its cutoff, and a frame lag then explains its delay better), so two
    effects that explain the data about as well are compared once both are
    bias-corrected. When ``best`` has an alternative of the same signature
    (:data:`SAME_SIGNATURE`, either way round) that was fitted this round, that one,
    confirmed on every seed, however far its moment estimate's screening fell behind, when
    it at least improved on ``current``."""
    margin = max(run.cfg.close_margin, run.cfg.close_relative * (best[0] - 1.0))
    for c in run.confirmed:
        if c[1].name != best[1].name and c[0] <= best[0] + margin:
            return c
    alt = signature_alternative(best[1].name)
    if alt is None:
        return None
    for c in run.confirmed:
        if c[1].name == alt:
            return c
    if alt not in run.screened_pool:
        return None
    eff, ev = run.screened_pool[alt]
    if ev.gap + run.cfg.penalty_per_parameter * eff.n_fitted >= \
            (run.screen_base if ev.on_band else current.gap):
        # it explains the data worse than the model without it: a cutoff that far off is
        # not what the lag stands for (and on a big sensor its simulations cost minutes)
        return None
    ev = run.confirm(ev, f"confirm {alt} (same signature as {best[1].name})")
    return ev.gap + run.cfg.penalty_per_parameter * eff.n_fitted, eff, ev


def best_pair(run: Runner, current: Evaluation, tried: dict[str, dict[str, Any]]
              ) -> tuple[float, list[tuple[Effect, Evaluation]]] | None:
    """When no single candidate qualifies: pairs of the ``beam_width`` best singles of
    the round, the second fitted on top of the first's simulations (two effects that
    explain the data only together: each hides the other's signature). The pair of the
    lowest score, confirmed on every seed, with the evaluation of its first effect
    alone."""
    top = beam_top(run, tried)
    jobs: list[tuple[Effect, Evaluation, Effect, Model]] = []
    for a in top:  # the pairs are fitted on the whole sensor's simulations
        eff_a, ev_a = run.screened_pool[a]
        if ev_a.on_band:
            run.screened_pool[a] = (eff_a, run.confirm(ev_a, f"confirm {a}"))
    for i, a in enumerate(top):
        eff_a, ev_a = run.screened_pool[a]
        for b in top[i + 1:]:
            eff_b = fit_candidate(b, run.meas, ev_a.sims, ev_a.model, run.rec)
            if eff_b is None:
                continue
            jobs.append((eff_a, ev_a, eff_b, run.candidate_model(ev_a.model, eff_b)))
        drop_derived(ev_a.sims)
    if not jobs:
        return None
    evals = run.evaluate_many([(j[2], j[3]) for j in jobs], current)
    pen = run.cfg.penalty_per_parameter
    scores = [ev.gap + pen * (j[0].n_fitted + j[2].n_fitted) for j, ev in zip(
        jobs, evals, strict=True)]
    k = int(np.argmin(scores))
    eff_a, ev_a, eff_b, _ = jobs[k]
    ev_pair = run.confirm(evals[k], f"confirm {eff_a.name} + {eff_b.name}")
    ev_a = run.confirm(ev_a, f"confirm {eff_a.name}")
    score = ev_pair.gap + pen * (eff_a.n_fitted + eff_b.n_fitted)
    tried[f"{eff_a.name} + {eff_b.name}"] = {
        "parameters": {eff_a.name: eff_a.parameters(), eff_b.name: eff_b.parameters()},
        "gap": ev_pair.gap, "score": score, "seeds": ev_pair.disc.n_sims,
        "pairs_screened": {f"{j[0].name} + {j[2].name}": float(ev.gap)
                           for j, ev in zip(jobs, evals, strict=True)}}
    return score, [(eff_a, ev_a), (eff_b, ev_pair)]
