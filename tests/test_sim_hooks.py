"""Each effect owns its simulation hooks: the simulator names no effect, every registered
effect acts through at least one hook, and an effect defined outside the library works through
:func:`~evcal.sim.nonideal.simulate` unchanged."""

from __future__ import annotations

import ast
import inspect
import textwrap
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np
import pytest

from evcal.sim import nonideal
from evcal.sim.effects import (
    EFFECTS,
    HOOKS,
    LABEL_ROW_NOISE,
    ApsConfig,
    Effect,
    HotPixels,
    KernelParams,
    Refractory,
    RowNoise,
    ShotNoise,
    SimContext,
    SimEvents,
    TimestampJitter,
    TimestampQuantisation,
    describe,
    simulation_order,
)
from evcal.sim.ideal import SimConfig
from evcal.sim.nonideal import simulate

CFG = SimConfig(height=20, width=24, duration_s=0.25, seed=3)
TOY_LABEL = 200


@dataclass(frozen=True, kw_only=True)
class ConstantEvents(Effect):
    """A toy: ``per_pixel`` ON events in every pixel at the middle of the run."""

    name: ClassVar[str] = "toy_constant_events"
    per_pixel: int = 2

    def after_kernel(self, events: SimEvents, ctx: SimContext) -> SimEvents:
        t_mid = (ctx.t_lo_us + ctx.t_hi_us) // 2
        pix = np.repeat(np.arange(ctx.n_pix, dtype=np.int32), self.per_pixel)
        added = (np.full(pix.size, t_mid, np.int64), pix, np.ones(pix.size, np.int8))
        return events.merged(added, TOY_LABEL)


@dataclass(frozen=True, kw_only=True)
class Shift(Effect):
    """A toy: every timestamp ``shift_us`` later."""

    name: ClassVar[str] = "toy_shift"
    shift_us: int = 7

    def on_timestamps(self, events: SimEvents, ctx: SimContext) -> SimEvents:
        return events._replace(t_us=events.t_us + self.shift_us)


@dataclass(frozen=True, kw_only=True)
class RandomEvents(Effect):
    """A toy drawing from a stream of its own: one event per pixel at a random time."""

    name: ClassVar[str] = "toy_random_events"

    def after_kernel(self, events: SimEvents, ctx: SimContext) -> SimEvents:
        rng = ctx.spawn_rng()
        t = np.sort(rng.integers(ctx.t_lo_us, ctx.t_hi_us + 1, ctx.n_pix))
        added = (t, np.arange(ctx.n_pix, dtype=np.int32), np.ones(ctx.n_pix, np.int8))
        return events.merged(added, TOY_LABEL)


@dataclass(frozen=True, kw_only=True)
class DeadTimeWitness(Effect):
    """A toy stepped scheme: it says its stamps apply the dead time, and records the dead
    time the context hands it (without applying it)."""

    name: ClassVar[str] = "toy_dead_time_witness"
    seen: list[object]

    def applies_dead_time(self) -> bool:
        return True

    def on_timestamps(self, events: SimEvents, ctx: SimContext) -> SimEvents:
        self.seen.append(ctx.stamp_dead_time)
        return events


@dataclass(frozen=True, kw_only=True)
class DarkerAndLonger(Effect):
    """A toy acting on the log offset, the kernel and the frames at once."""

    name: ClassVar[str] = "toy_darker_and_longer"

    def log_offset(self, nominal_dn: float) -> float:
        return nominal_dn + 5.0

    def kernel_setup(self, kp: KernelParams, ctx: SimContext) -> None:
        kp.refr_us = 400.0

    def on_aps(self, aps: ApsConfig) -> ApsConfig:
        return replace(aps, exposure_us=2000)


def _events(res: nonideal.SimResult) -> np.ndarray:
    return res.recording.events


def _names(tree: ast.AST) -> set[str]:
    """Every name the code uses: variables, attributes, imports (not docstrings, comments)."""
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Name):
            out.add(node.id)
        elif isinstance(node, ast.Attribute):
            out.add(node.attr)
        elif isinstance(node, ast.alias):
            out.add(node.asname or node.name)
    return out


def test_simulate_names_no_effect_class() -> None:
    """No ``isinstance`` and no effect class in the simulator's code, nor in the two helpers
    that ask the effects for the frame model and the log offset; the simulator's module
    imports none."""
    classes = {cls.__name__ for cls in EFFECTS.values()}
    for f in (nonideal.simulate, nonideal.effective_log_offset, ApsConfig.with_effects):
        src = textwrap.dedent(inspect.getsource(f))
        names = _names(ast.parse(src))
        assert "isinstance" not in names, f.__name__
        assert not names & classes, (f.__name__, names & classes)
    assert not _names(ast.parse(inspect.getsource(nonideal))) & classes


@pytest.mark.parametrize("name", list(EFFECTS))
def test_every_effect_overrides_a_hook(name: str) -> None:
    cls = EFFECTS[name]
    assert cls.hooks(), f"{name} overrides none of {HOOKS}"
    assert set(cls.hooks()) <= set(HOOKS)


def test_the_order_is_fixed_and_unique() -> None:
    orders = [cls.order for cls in EFFECTS.values()]
    assert len(set(orders)) == len(orders)
    assert all(o < Effect.order for o in orders)  # a new effect comes after the library's
    effects = [cls() for cls in EFFECTS.values()]
    forward = simulation_order(effects)
    assert simulation_order(reversed(effects)) == forward
    assert [e.name for e in forward][:2] == ["log_offset", "threshold_light"]
    # the base class does nothing and overrides nothing
    assert Effect.hooks() == ()


def test_order_given_does_not_matter() -> None:
    effects = [TimestampJitter(sigma_us=50.0), RowNoise(rate_hz=3.0), HotPixels(fraction=0.02),
               ShotNoise(rate_hz=10.0), TimestampQuantisation(step_us=500.0),
               Refractory(period_us=300.0)]
    a = simulate(CFG, effects)
    b = simulate(CFG, effects[::-1])
    np.testing.assert_array_equal(_events(a), _events(b))
    np.testing.assert_array_equal(a.truth["labels"], b.truth["labels"])


def test_a_toy_effect_adds_events_after_the_kernel() -> None:
    base_effects = [Refractory(period_us=300.0), HotPixels(fraction=0.02)]
    base = simulate(CFG, base_effects)
    toy = simulate(CFG, [*base_effects, ConstantEvents(per_pixel=3)])
    npix = CFG.height * CFG.width
    assert toy.recording.n_events == base.recording.n_events + 3 * npix
    mine = toy.truth["labels"] == TOY_LABEL
    assert mine.sum() == 3 * npix
    ev = _events(toy)[mine]
    counts = np.bincount(ev["y"].astype(np.int64) * CFG.width + ev["x"], minlength=npix)
    np.testing.assert_array_equal(counts, 3)
    # the other events, their labels and the truth are those of the run without it
    np.testing.assert_array_equal(_events(toy)[~mine], _events(base))
    np.testing.assert_array_equal(toy.truth["labels"][~mine], base.truth["labels"])
    np.testing.assert_array_equal(toy.truth["hot_pixels"], base.truth["hot_pixels"])
    assert np.all(np.diff(_events(toy)["t_us"]) >= 0)
    assert toy.truth["effects"]["toy_constant_events"] == {"per_pixel": 3}
    assert describe([ConstantEvents()]) == {"toy_constant_events": {"per_pixel": 2}}


def test_a_toy_effect_shifts_timestamps() -> None:
    base = simulate(CFG, [ShotNoise(rate_hz=10.0)], t_origin_us=1000)
    toy = simulate(CFG, [ShotNoise(rate_hz=10.0), Shift(shift_us=7)], t_origin_us=1000)
    a, b = _events(base), _events(toy)
    np.testing.assert_array_equal(b["t_us"], a["t_us"] + 7)
    for k in ("x", "y", "p"):
        np.testing.assert_array_equal(b[k], a[k])
    np.testing.assert_array_equal(toy.recording.frames.t_us, base.recording.frames.t_us)


def test_a_toy_effect_with_its_own_stream_moves_no_other_draw() -> None:
    effects = [HotPixels(fraction=0.02), RowNoise(rate_hz=3.0), ShotNoise(rate_hz=10.0)]
    base = simulate(CFG, effects)
    toy = simulate(CFG, [*effects, RandomEvents()])
    mine = toy.truth["labels"] == TOY_LABEL
    assert mine.sum() == CFG.height * CFG.width
    assert (base.truth["labels"] == LABEL_ROW_NOISE).any()  # it spawned a stream too
    np.testing.assert_array_equal(_events(toy)[~mine], _events(base))
    np.testing.assert_array_equal(toy.truth["labels"][~mine], base.truth["labels"])


def test_the_dead_time_reaches_stepped_stamps_through_the_context() -> None:
    seen: list[object] = []
    refr = Refractory(period_us=500.0)
    res = simulate(CFG, [refr, DeadTimeWitness(seen=seen)])
    assert seen == [refr]
    # the kernel left the dead time out (the witness did not apply it): the ideal events
    ideal = simulate(CFG, [])
    np.testing.assert_array_equal(_events(res), _events(ideal))
    # without a stepped scheme, the kernel applies it and nothing is left in the context
    seen_none: list[object] = []

    @dataclass(frozen=True, kw_only=True)
    class Witness(Effect):
        name: ClassVar[str] = "toy_witness"

        def on_timestamps(self, events: SimEvents, ctx: SimContext) -> SimEvents:
            seen_none.append(ctx.stamp_dead_time)
            return events

    res2 = simulate(CFG, [refr, Witness()])
    assert seen_none == [None]
    assert res2.recording.n_events < ideal.recording.n_events


def test_a_toy_effect_on_the_offset_the_kernel_and_the_frames() -> None:
    toy = simulate(CFG, [DarkerAndLonger()])
    assert toy.truth["log_offset"] == pytest.approx(CFG.log_offset + 5.0)
    assert set(DarkerAndLonger.hooks()) == {"log_offset", "kernel_setup", "on_aps"}
    np.testing.assert_array_equal(toy.recording.frames.exposure_us, 2000)
    ev = _events(toy)
    pix = ev["y"].astype(np.int64) * CFG.width + ev["x"]
    order = np.lexsort((ev["t_us"], pix))
    same = pix[order][1:] == pix[order][:-1]
    iei = np.diff(ev["t_us"][order])[same]
    assert iei.size > 100
    assert iei.min() >= 399  # the dead time the toy set in the kernel (stamps rounded)
