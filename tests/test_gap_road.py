"""The gap workflow on the real DAVIS346 recording (../shared/data/davis346_road): slow (a
few minutes per seed on 2 cores), deselected in CI. What is asserted is that the recording
is explained and that the explanation does not depend on the seed of the simulations, not
which effects or values explain it (docs/GAP.md gives the figures of the last run)."""

from __future__ import annotations

from pathlib import Path

import pytest

from evcal.gap.workflow import GapConfig, run_gap
from evcal.io import open_recording


@pytest.mark.slow
@pytest.mark.extended
def test_road_is_explained_alike_on_two_seeds(shared_data: Path) -> None:
    road = shared_data / "davis346_road" / "road.aedat4"
    if not road.exists():
        pytest.skip(f"{road} is absent")
    rec = open_recording(road)
    runs = [run_gap(rec, GapConfig(seed=seed)) for seed in (0, 1)]
    for res in runs:
        assert res.final.gap <= 3.0, res.named_effects
        assert res.final.gap < 0.5 * res.initial.gap
    assert sorted(runs[0].named_effects) == sorted(runs[1].named_effects)
