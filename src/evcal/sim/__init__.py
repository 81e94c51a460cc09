"""Simulators: the ideal DVS (:mod:`.ideal`) and the one with real-sensor effects
(:mod:`.nonideal`, effects in :mod:`.effects`)."""

from .bench import bench_simulator
from .effects import EFFECT_NAMES, EFFECTS, ApsConfig, Effect, EffectError, make_effect
from .nonideal import simulate

__all__ = ["EFFECTS", "EFFECT_NAMES", "ApsConfig", "Effect", "EffectError", "bench_simulator",
           "make_effect", "simulate"]
