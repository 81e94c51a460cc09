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


def test_a_restart_never_overwrites_the_previous_recording(tmp_path):
    path = tmp_path / "run.rrd"
    first = RrdLogger(path)
    first.close()
    size = path.stat().st_size
    second = RrdLogger(path)
    second.close()
    assert second.path == tmp_path / "run.1.rrd"
    assert path.stat().st_size == size
    assert read_entities(second.path)["/service"] >= 2


def test_a_full_disk_stops_recording_cleanly_and_keeps_the_file_readable(tmp_path):
    free = {"bytes": 1 << 30}
    path = tmp_path / "run.rrd"
    log = RrdLogger(path, map_period_s=0.0, scalar_period_s=0.0, min_free_bytes=100 << 20,
                    disk_free=lambda _p: free["bytes"])
    cal = Calibration.uniform((48, 64), 0.2, 0.01, log_offset=30.0)
    status = {"latency_ms": {"last": 5.0}, "event_rate_hz": 1e5, "errors_total": 0}
    for k in range(5):
        log._next_disk_check = 0.0  # check every call (normally once a second)
        log.updated("cam0", cal, k * 40_000, status)
    assert log.stopped is None
    free["bytes"] = 10 << 20  # the disk fills up
    for k in range(5, 10):
        log._next_disk_check = 0.0
        log.updated("cam0", cal, k * 40_000, status)
    assert log.stopped is not None and "MiB free" in log.stopped
    assert log.state()["recording"] is False
    log.close()  # never raises, even after a stop
    ents = read_entities(path)  # what was written is complete and readable
    assert ents["/cameras/cam0/series/latency_ms"] == 5


def test_a_rerun_failure_stops_recording_never_the_caller(tmp_path):
    log = RrdLogger(tmp_path / "run.rrd", map_period_s=0.0)
    cal = Calibration.uniform((4, 5), 0.2, 0.01, log_offset=30.0)

    def broken(*_a, **_k):
        raise OSError(28, "No space left on device")

    log.rec.log = broken  # every write fails from now on
    log.updated("cam0", cal, 0, {})
    assert log.stopped is not None and "No space left" in log.stopped
    log.frame("cam0", 1, np.zeros((4, 5), np.uint8))  # ignored, no exception
    log.close()
