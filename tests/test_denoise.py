"""The background-activity filter against a plain reference, on its own."""

from __future__ import annotations

import numpy as np
import pytest

from evcal.denoise import background_activity_filter
from evcal.events import SensorSize, make_events


def _reference(ev: np.ndarray, sensor: SensorSize, window_us: int) -> np.ndarray:
    """The definition, one event at a time: kept when a pixel of its 3x3 neighbourhood (not
    itself) fired within ``window_us`` before it."""
    last: dict[tuple[int, int], int] = {}
    keep = []
    for t, x, y in zip(ev["t_us"].tolist(), ev["x"].tolist(), ev["y"].tolist(), strict=True):
        keep.append(any(t - last[(x + dx, y + dy)] <= window_us
                        for dx in (-1, 0, 1) for dy in (-1, 0, 1)
                        if (dx or dy) and (x + dx, y + dy) in last))
        last[(x, y)] = t
    return np.array(keep, bool)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_the_definition(seed):
    rng = np.random.default_rng(seed)
    sensor = SensorSize(12, 16)
    n = 3000
    t = np.sort(rng.integers(0, 2_000_000, n))
    ev = make_events(t, rng.integers(0, 16, n), rng.integers(0, 12, n),
                     rng.choice([-1, 1], n))
    keep = background_activity_filter(ev, sensor, 20_000)
    np.testing.assert_array_equal(keep, _reference(ev, sensor, 20_000))
    assert 0.05 < keep.mean() < 0.95  # the case is not trivial


def test_edges_kept_isolated_events_dropped():
    sensor = SensorSize(10, 10)
    # an edge sweeping along x at row 5 (one pixel per ms), and a lone event far away later
    xs = np.arange(10)
    ev = make_events(np.r_[xs * 1000, 50_000], np.r_[xs, 2], np.r_[np.full(10, 5), 0],
                     np.ones(11, int))
    keep = background_activity_filter(ev, sensor, 5000)
    assert keep.tolist() == [False] + [True] * 9 + [False]  # the first has no predecessor
    # the same event on its own pixel twice does not support itself
    ev2 = make_events([0, 100], [3, 3], [3, 3], [1, 1])
    assert not background_activity_filter(ev2, sensor, 5000).any()


def test_empty_and_bad_arguments():
    sensor = SensorSize(4, 4)
    assert background_activity_filter(make_events([], [], [], []), sensor, 1000).shape == (0,)
    ev = make_events([0], [0], [0], [1])
    with pytest.raises(ValueError, match="window_us=0 must be > 0"):
        background_activity_filter(ev, sensor, 0)
    with pytest.raises(ValueError, match="radius=0"):
        background_activity_filter(ev, sensor, 10, radius=0)
