"""Labels of simulated events (``truth["labels"]``, uint8, one per event).

A module of its own so that the effect library (:mod:`evcal.sim.effects`, which re-exports
them) and the per-pixel kernel (:mod:`evcal.sim.kernel`) both use them without importing
each other.
"""

from __future__ import annotations

LABEL_SIGNAL = 0
LABEL_LEAK = 1
LABEL_SHOT_NOISE = 2
LABEL_HOT_PIXEL = 3
LABEL_ROW_NOISE = 4
LABEL_LEGEND = {LABEL_SIGNAL: "signal", LABEL_LEAK: "leak", LABEL_SHOT_NOISE: "shot_noise",
                LABEL_HOT_PIXEL: "hot_pixels", LABEL_ROW_NOISE: "row_noise"}
