"""OffEI's batched window sums (solver.WindowRing, one compiled pass per batch) against the
definition: NormalEquations.add of each window's (P, E, Q, A, dL, w), window by window."""

from __future__ import annotations

import numpy as np
import pytest

from evcal.solver import RING_BLOCK, NormalEquations, WindowRing


@pytest.mark.parametrize(("d", "n_frames", "batch"), [(5, 40, 16), (1, 7, 3), (7, 30, 4)])
# pixel counts below, at and across the ring's block size (the last block partial or whole)
@pytest.mark.parametrize("n", [500, 2 * RING_BLOCK, RING_BLOCK // 2 + 1])
def test_batched_windows_equal_the_definition(d, n_frames, batch, n):
    rng = np.random.default_rng(d * 100 + n_frames)
    on = np.cumsum(rng.poisson(2, (n_frames, n)), axis=0).astype(np.int32)
    off = np.cumsum(rng.poisson(2, (n_frames, n)), axis=0).astype(np.int32)
    last_p = rng.choice(np.array([-1, 0, 1], np.int8), (n_frames, n))
    lg = rng.normal(4, 1, (n_frames, n))
    lg[rng.random((n_frames, n)) < 0.02] = -np.inf  # black pixels at offset 0
    ok = np.isfinite(lg) & (rng.random((n_frames, n)) > 0.05)

    ref = NormalEquations(n)
    for k in range(d, n_frames):
        j = k - d
        p_on, p_off = (on[k] - on[j]).astype(float), (off[k] - off[j]).astype(float)
        qk, qj = last_p[k].astype(float), last_p[j].astype(float)
        w = (ok[j] & ok[k]).astype(float)
        with np.errstate(invalid="ignore"):
            dl = np.where(w > 0, lg[k] - lg[j], 0.0)
        ref.add(p_on - p_off, p_on + p_off, qk - qj, np.abs(qk) - np.abs(qj), dl, w)

    got = NormalEquations(n)
    ring = WindowRing(n, d, batch=batch)
    for k in range(n_frames):
        if ring.push(on[k], off[k], last_p[k], lg[k], ok[k]):
            ring.flush(got)
    ring.flush(got)
    assert np.isfinite(got.m).all()
    np.testing.assert_allclose(got.m, ref.m, rtol=1e-12, atol=1e-9)
    assert got.n_eq.max() <= n_frames - d
    on_k, off_k = ring.counts(n_frames - 1)  # the counts read back as stored
    np.testing.assert_array_equal(on_k, on[-1])
    np.testing.assert_array_equal(off_k, off[-1])
    with pytest.raises(IndexError, match="not in the ring"):
        ring.counts(n_frames)
