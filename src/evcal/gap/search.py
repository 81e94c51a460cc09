"""One round's search over candidate effects: each fitted on the fit rows (or told why not),
held to the null calibration, screened on one seed, the best confirmed on every seed, all
judged on the held-out rows. What a round found is a :class:`Round` of :class:`Candidate`;
the run (:class:`.workflow.GapRun`) decides what to name from it."""

from __future__ import annotations

import math
import time
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

from ..jsonable import to_jsonable
from ..sim.effects import Effect
from . import effects as registry
from .effects import Fitted, NoEvidence
from .null import NullCalibration
from .runner import Evaluation, Evaluator, drop_derived, gain, longest_first, need


@dataclass
class Candidate:
    """One effect in one round: what its fitter said, and how it fared.

    ``status``: ``"no evidence"`` (the fitter saw none: ``reason``), ``"within the null"``
    (its strength no more than the null calibration's limit), ``"screened"`` (one seed),
    ``"confirmed"`` (every seed), ``"named"``."""

    name: str
    status: str
    reason: str = ""
    effect: Effect | None = None
    strength: float = 0.0
    null_limit: float = 0.0
    detail: dict[str, Any] = field(default_factory=dict)
    evaluation: Evaluation | None = None
    # the alternatives of a discrete parameter, screened beside it: (effect, evaluation)
    others: list[tuple[Effect, Evaluation]] = field(default_factory=list)
    # a confirmed candidate's share of its held-out gain on its own statistics, and whether
    # it was passed over for gaining elsewhere (Round.judge_signatures)
    signature: float | None = None
    passed_over: bool = False

    def score(self, pen: float) -> float:
        """Held-out gap plus the complexity penalty (inf without an evaluation)."""
        if self.evaluation is None or self.effect is None:
            return math.inf
        return self.evaluation.held_gap + pen * self.effect.n_fitted

    def signature_share(self, base: Evaluation) -> float:
        """The share of this candidate's held-out gain over ``base`` that falls on the
        statistics its effect moves (:attr:`.effects.EffectSpec.moves`), each statistic's
        gain counted down to a discrepancy of 1 (NaN without an evaluation or a gain)."""
        if self.evaluation is None:
            return math.nan
        return gain_share(base, self.evaluation, registry.spec(self.name).moves)

    def to_json(self, pen: float) -> dict[str, Any]:
        d: dict[str, Any] = {"status": self.status}
        if self.reason:
            d["reason"] = self.reason
        if self.effect is not None:
            d["parameters"] = to_jsonable(self.effect.parameters())
            d["strength"] = self.strength
            d["null_limit"] = self.null_limit
        if self.evaluation is not None:
            d["gap"] = float(self.evaluation.gap)
            d["held_out_gap"] = float(self.evaluation.held_gap)
            d["score"] = float(self.score(pen))
            d["seeds"] = int(self.evaluation.disc.n_sims)
            # each statistic's discrepancy on the held-out rows: where the gain came from
            d["held_out_statistics"] = {k: float(v) for k, v in
                                        self.evaluation.held.per_stat.items()}
        if self.signature is not None:
            d["signature_share"] = self.signature
        if self.others:
            d["variants"] = [{"parameters": to_jsonable(e.parameters()),
                              "held_out_gap": float(v.held_gap)} for e, v in self.others]
        if self.detail:
            d["detail"] = to_jsonable(self.detail)
        return d


@dataclass
class Round:
    """A round's candidates (by name, the registry's order) and against what they were
    judged: the held-out gap of the model they were added to (``base_gap``; the band's
    for screenings on a band, ``screen_base_gap``)."""

    candidates: dict[str, Candidate]
    base_gap: float
    screen_base_gap: float

    def ranked(self, pen: float) -> list[Candidate]:
        """The evaluated candidates, best (lowest held-out score) first."""
        out = [c for c in self.candidates.values() if c.evaluation is not None]
        return sorted(out, key=lambda c: c.score(pen))

    def best(self, pen: float) -> Candidate | None:
        """The confirmed candidate of the lowest held-out score that was not passed over
        (:meth:`judge_signatures`)."""
        conf = [c for c in self.ranked(pen) if c.status == "confirmed" and not c.passed_over]
        return conf[0] if conf else None

    def judge_signatures(self, base: Evaluation, min_share: float) -> None:
        """Each confirmed candidate's share of its gain over ``base`` on its own statistics;
        one below ``min_share`` times the even share (:func:`signature_ok`) is passed over,
        with the reason."""
        for c in self.candidates.values():
            if c.status != "confirmed":
                continue
            c.signature = c.signature_share(base)
            if not signature_ok(c, base, min_share):
                c.passed_over = True
                c.reason = (
                    f"{100 * c.signature:.0f} % of its held-out gain falls on the statistics "
                    f"its effect moves, where an even spread over all would put "
                    f"{100 * even_share(c.name, base):.0f} %: it absorbs a misfit its effect "
                    "does not describe")

    def to_json(self, pen: float) -> dict[str, Any]:
        return {name: c.to_json(pen) for name, c in self.candidates.items()}

    def let_go(self, *keep: Evaluation | None) -> None:
        """Every candidate's simulations let go but ``keep``'s."""
        kept = {id(e) for e in keep if e is not None}
        for c in self.candidates.values():
            for ev in [c.evaluation, *(v for _, v in c.others)]:
                if ev is not None and id(ev) not in kept:
                    ev.sims.clear()


def gain_share(base: Evaluation, after: Evaluation, moves: Iterable[str]) -> float:
    """The share of ``after``'s held-out gain over ``base`` that falls on the statistics
    ``moves``, each statistic's gain counted down to a discrepancy of 1 (NaN without a
    gain)."""
    before, now = base.held.per_stat, after.held.per_stat
    gains = {k: max(before[k], 1.0) - max(now.get(k, 1.0), 1.0) for k in before}
    total = sum(gains.values())
    if not total > 0:
        return math.nan
    return sum(gains[k] for k in set(moves) if k in gains) / total


def even_share_of(moves: Iterable[str], base: Evaluation) -> float:
    """The share of a gain the statistics ``moves`` would take were it spread evenly over
    every statistic compared."""
    stats = base.held.per_stat
    return len([k for k in set(moves) if k in stats]) / max(len(stats), 1)


def even_share(name: str, base: Evaluation) -> float:
    """:func:`even_share_of` the statistics effect ``name`` moves."""
    return even_share_of(registry.spec(name).moves, base)


def signature_ok(c: Candidate, base: Evaluation, min_share: float) -> bool:
    """Whether candidate ``c``'s gain over ``base`` shows in the statistics its effect
    moves: at least ``min_share`` times the even share (:func:`even_share`). An effect
    whose gain lies elsewhere does not explain the data by its own signature: it absorbs,
    through side effects of its parameters, a misfit of the model that it does not
    describe (a timestamp jitter smoothing a misfit of the event counts)."""
    if min_share <= 0.0:
        return True
    share = c.signature_share(base)
    return not math.isfinite(share) or share >= min_share * even_share(c.name, base)


def search(ev: Evaluator, null: NullCalibration, on: Evaluation, names: list[str],
           seconds: dict[str, float]) -> Round:
    """Every effect of ``names`` fitted on ``on``'s simulations (fit rows), held to the
    null calibration and screened on one seed; the ``confirm_top`` best confirmed on every
    seed. ``seconds`` (each candidate's time in the last round) is updated."""
    cfg = ev.cfg
    pen = cfg.penalty_per_parameter
    ctxs = {held: ev.fit_context(on.model, on.sims, held_out=held) for held in (True, False)}
    screen_base = ev.screen_gap(on) if cfg.screen else on.held_gap

    def fit_and_screen(name: str) -> Candidate:
        """A candidate fitted and, when it stands above the null, its alternatives
        screened at once: the fitters (numpy, holding the GIL in part) and the
        simulations of the candidates fitted first (numba, without it) share the cores."""
        t0 = time.perf_counter()
        spec = registry.spec(name)
        try:
            res = spec.fit(ctxs[spec.held_out])
            if isinstance(res, NoEvidence):
                return Candidate(name, "no evidence", res.reason)
            assert isinstance(res, Fitted)
            eff = res.effect
            strength = float(spec.strength(eff, ev.light_dn))
            limit = null.limit(name, cfg.null_factor)
            cand = Candidate(name, "screened", "", eff, strength, limit, dict(res.detail))
            if strength <= limit:
                cand.status = "within the null"
                cand.reason = (f"its strength {strength:.3g} is within {cfg.null_factor:g}x "
                               f"what the fitter reads on the model's own simulations "
                               f"({limit / cfg.null_factor:.3g})")
                return cand
            evals = [(e, ev.evaluate(ev.candidate_model(on.model, e), f"screen {name}",
                                     spread=on if cfg.screen else None))
                     for e in spec.alternatives(eff)]
            evals.sort(key=lambda t: t[1].held_gap)
            cand.effect, cand.evaluation = evals[0]
            cand.others = evals[1:]
            if not cfg.screen:
                cand.status = "confirmed"
            return cand
        finally:
            seconds[name] = time.perf_counter() - t0

    with ThreadPoolExecutor(max_workers=ev.workers) as pool:
        # longest first (each candidate's time in the last round, else the usual order of
        # costs): the round ends when its last task does, and a long one started last
        # leaves the other cores idle while it runs
        order = longest_first(names, seconds)
        done = dict(zip(order, pool.map(fit_and_screen, order), strict=True))
    drop_derived(on.sims)
    rnd = Round({n: done[n] for n in names}, on.held_gap, screen_base)
    if cfg.screen:
        _confirm(ev, rnd, pen)
    return rnd


def _confirm(ev: Evaluator, rnd: Round, pen: float) -> None:
    """The ``confirm_top`` best screened candidates confirmed on every seed, each only when
    its screened gain reaches half the gain that names (against the held-out gap of the
    model where it was screened: what falls that short does not qualify on every seed
    either)."""
    cfg = ev.cfg
    base = rnd.screen_base_gap
    todo = []
    for c in rnd.ranked(pen)[:cfg.confirm_top]:
        if gain(base, c.score(pen)) <= 0.5 * need(cfg, base):
            break
        todo.append(c)
    with ThreadPoolExecutor(max_workers=max(1, min(ev.workers, len(todo)))) as pool:
        confirmed = list(pool.map(lambda c: ev.confirm(c.evaluation, f"confirm {c.name}"),
                                  todo))
    for c, out in zip(todo, confirmed, strict=True):
        c.evaluation = out
        c.status = "confirmed"


@dataclass
class Pair:
    """Two effects tried together: ``first`` (a round's candidate, the better-ranked) and
    ``second`` (the other's effect, at the value its fitter read on the model alone), its
    evaluation the model with both (``second.evaluation``)."""

    first: Candidate
    second: Candidate
    # the second effect's own candidate of the round (alone on the current model), confirmed
    # with the first when the pair is the best: each of the two must add to the other
    alone: Candidate

    @property
    def names(self) -> tuple[str, str]:
        return self.first.name, self.second.name

    def score(self, pen: float) -> float:
        """Held-out gap with both plus both effects' complexity penalties."""
        if self.second.evaluation is None or self.first.effect is None or \
                self.second.effect is None:
            return math.inf
        return self.second.evaluation.held_gap + pen * (self.first.effect.n_fitted +
                                                        self.second.effect.n_fitted)

    @property
    def moves(self) -> set[str]:
        """The statistics either effect moves."""
        return set(registry.spec(self.first.name).moves) | \
            set(registry.spec(self.second.name).moves)

    def signature_share(self, base: Evaluation) -> float:
        """The share of the pair's held-out gain over ``base`` on the statistics either
        effect moves (NaN without a gain)."""
        assert self.second.evaluation is not None
        return gain_share(base, self.second.evaluation, self.moves)

    def even_share(self, base: Evaluation) -> float:
        return even_share_of(self.moves, base)

    def to_json(self, pen: float) -> dict[str, Any]:
        d = self.second.to_json(pen)
        d["pair"] = list(self.names)
        d["first_parameters"] = to_jsonable(self.first.effect.parameters()) \
            if self.first.effect is not None else None
        if math.isfinite(self.score(pen)):
            d["score"] = float(self.score(pen))
        return d


def search_pairs(ev: Evaluator, on: Evaluation, rnd: Round) -> list[Pair]:
    """Pairs of the round's ``pair_top`` best candidates (by held-out score, whatever their
    signature share: one effect's gain may lie on the other's statistics), each effect with
    the value its fitter read on the model alone (a candidate of the round: held to the
    null calibration there), screened together on one seed; the pair of the best score
    confirmed on every seed, and so are its two effects alone (what each adds to the other
    is judged on them). The better-ranked effect of a pair is its first.

    For effects that explain the data only together: each alone may gain little or even
    lose (a dark level alone changes every pixel's sensitivity to light, which a frame lag
    alone cannot follow), so a forward search of singles never reaches them. Screening the
    round's own fits together costs one simulation per pair (on the screening band): the
    value of the second effect is fitted again on the first's simulations when the pair is
    named (:meth:`.workflow.GapRun._pair`)."""
    cfg = ev.cfg
    pen = cfg.penalty_per_parameter
    top = [c for c in rnd.ranked(pen) if c.effect is not None][:cfg.pair_top]
    jobs = [(a, b) for i, a in enumerate(top) for b in top[i + 1:]]
    if not jobs:
        return []

    def screen(job: tuple[Candidate, Candidate]) -> Pair:
        a, b = job
        assert a.effect is not None
        assert b.effect is not None
        model = ev.candidate_model(ev.candidate_model(on.model, a.effect), b.effect)
        e = ev.evaluate(model, f"screen {a.name} + {b.name}",
                        spread=on if cfg.screen else None)
        second = Candidate(b.name, "screened" if cfg.screen else "confirmed", "", b.effect,
                           b.strength, b.null_limit, dict(b.detail), e)
        return Pair(a, second, b)

    with ThreadPoolExecutor(max_workers=max(1, min(ev.workers, len(jobs)))) as pool:
        pairs = list(pool.map(screen, jobs))
    pairs.sort(key=lambda p: p.score(pen))
    best = pairs[0]
    todo = [c for c in (best.second, best.first, best.alone)
            if c.status != "confirmed" and c.evaluation is not None]
    with ThreadPoolExecutor(max_workers=max(1, min(ev.workers, len(todo)))) as pool:
        done = list(pool.map(lambda c: ev.confirm(c.evaluation, f"confirm {c.name}"), todo))
    for c, out in zip(todo, done, strict=True):
        c.evaluation = out
        c.status = "confirmed"
    pairs.sort(key=lambda p: p.score(pen))
    return pairs


def let_go_pairs(pairs: list[Pair], *keep: Evaluation | None) -> None:
    """Every pair's simulations let go but ``keep``'s."""
    kept = {id(e) for e in keep if e is not None}
    for p in pairs:
        e = p.second.evaluation
        if e is not None and id(e) not in kept:
            e.sims.clear()
