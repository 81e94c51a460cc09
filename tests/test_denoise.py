"""The background-activity filter against a plain reference, on its own."""

from __future__ import annotations

import numpy as np
import pytest

from evcal.denoise import background_activity_filter, still_interval_mask
from evcal.events import SensorSize, make_events
from evcal.recording import Frames


def _reference(ev: np.ndarray, sensor: SensorSize, window_us: int, *,
               same_polarity: bool = False, two_sided: bool = False) -> np.ndarray:
    """The definition, one event at a time: kept when a pixel of its 3x3 neighbourhood (not
    itself) fired within ``window_us`` before it (an event earlier in the stream), or with
    ``two_sided`` after it (later in the stream); with ``same_polarity`` only an event of
    the same polarity counts."""
    t, x, y, p = (ev[k].tolist() for k in ("t_us", "x", "y", "p"))
    keep = []
    for i in range(len(t)):
        def supports(j: int, i: int = i) -> bool:
            return (j != i and abs(x[j] - x[i]) <= 1 and abs(y[j] - y[i]) <= 1
                    and (x[j], y[j]) != (x[i], y[i]) and abs(t[j] - t[i]) <= window_us
                    and (not same_polarity or p[j] == p[i]) and (two_sided or j < i))
        keep.append(any(supports(j) for j in range(len(t))))
    return np.array(keep, bool)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize(("same_polarity", "two_sided"),
                         [(False, False), (True, False), (False, True), (True, True)])
def test_matches_the_definition(seed, same_polarity, two_sided):
    rng = np.random.default_rng(seed)
    sensor = SensorSize(12, 16)
    n = 600
    # coarse times: many ties, which count on both sides of a two-sided filter
    t = np.sort(rng.integers(0, 100, n)) * 5000
    ev = make_events(t, rng.integers(0, 16, n), rng.integers(0, 12, n),
                     rng.choice([-1, 1], n))
    keep = background_activity_filter(ev, sensor, 20_000, same_polarity=same_polarity,
                                      two_sided=two_sided)
    np.testing.assert_array_equal(keep, _reference(ev, sensor, 20_000,
                                                   same_polarity=same_polarity,
                                                   two_sided=two_sided))
    assert 0.05 < keep.mean() < 0.95  # the case is not trivial


def test_still_intervals_drop_their_events():
    sensor = SensorSize(1, 2)
    # pixel 0 changes between frames 0 and 1 only, pixel 1 never
    images = np.array([[[100, 50]], [[130, 50]], [[130, 50]]], np.uint8)
    frames = Frames(t_us=np.array([0, 1000, 2000]), images=images,
                    exposure_us=np.zeros(3, np.int64))
    ev = make_events([-5, 500, 500, 1500, 2500], [0, 0, 1, 0, 0], [0] * 5, [1] * 5)
    keep = still_interval_mask(ev, frames, sensor, 0.05, 1.0)
    # outside the frames: kept; in (0, 1000]: pixel 0 moved, pixel 1 did not; then still
    assert keep.tolist() == [True, True, False, False, True]
    with pytest.raises(ValueError, match="max_dl"):
        still_interval_mask(ev, frames, sensor, 0.0, 1.0)


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
