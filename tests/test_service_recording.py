"""The Rerun recorder on its own: entities, bounded growth, a file `rerun rrd verify` accepts."""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest

pytest.importorskip("rerun")

from evcal.calibration import Calibration  # noqa: E402
from evcal.events import make_events  # noqa: E402
from evcal.service.recording import RrdLogger, read_entities  # noqa: E402


def test_image_budget_bounds_the_file(tmp_path):
    path = tmp_path / "run.rrd"
    cal = Calibration.uniform((48, 64), 0.2, 0.01, log_offset=30.0)
    # each map set is 2 * 12 KiB + 3 KiB: a 100 KiB budget holds 3 of them
    log = RrdLogger(path, map_period_s=0.0, recon_period_s=0.0, recon_frames=1,
                    scalar_period_s=0.0, max_image_bytes=100 << 10)
    rng = np.random.default_rng(0)
    for k in range(200):
        t = k * 40_000
        log.updated("cam0", cal, t, {"latency_ms": {"last": 5.0}, "event_rate_hz": 1e5,
                                     "errors_total": 0})
        log.frame("cam0", t + 1, rng.integers(0, 255, (48, 64)).astype(np.uint8))
        log.events("cam0", make_events([t + 2, t + 3], [1, 2], [3, 4], [1, -1]))
    log.close()
    ents = read_entities(path)
    assert 1 <= ents["/cameras/cam0/maps/contrast"] <= 4
    assert ents["/cameras/cam0/series/latency_ms"] == 200  # scalars continue
    assert path.stat().st_size < 400 << 10
    rerun = shutil.which("rerun")
    if rerun:
        res = subprocess.run([rerun, "rrd", "verify", str(path)], capture_output=True,
                             text=True, timeout=120)
        assert res.returncode == 0, res.stdout + res.stderr
