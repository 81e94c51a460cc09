"""The Rerun recorder on its own: entities, bounded growth, a file `rerun rrd verify` accepts."""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest

pytest.importorskip("rerun")

from evcal.calibration import Calibration  # noqa: E402
from evcal.events import make_events  # noqa: E402
from evcal.service.rrdlog import RrdLogger, read_entities  # noqa: E402


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
        log.updated("cam0", cal, k * 40_000, status)
    assert log.stopped is None
    free["bytes"] = 10 << 20  # the disk fills up: the next call sees it (no once-a-second)
    for k in range(5, 10):
        log.updated("cam0", cal, k * 40_000, status)
    assert "MiB free" in (log.stopped or "")
    state = log.state()
    assert (state["recording"], state["reason"], state["complete"]) == (False, "disk_full",
                                                                         True)
    assert state["bytes"] == path.stat().st_size
    log.close()  # never raises, even after a stop
    ents = read_entities(path)  # what was written is complete and readable
    assert ents["/cameras/cam0/series/latency_ms"] == 5
    rerun = shutil.which("rerun")
    if rerun:
        res = subprocess.run([rerun, "rrd", "verify", str(path)], capture_output=True,
                             text=True, timeout=120)
        assert res.returncode == 0, res.stdout + res.stderr


def test_a_rerun_failure_stops_recording_never_the_caller(tmp_path):
    log = RrdLogger(tmp_path / "run.rrd", map_period_s=0.0)
    cal = Calibration.uniform((4, 5), 0.2, 0.01, log_offset=30.0)

    def broken(*_a, **_k):
        raise OSError(28, "No space left on device")

    log.rec.log = broken  # every write fails from now on
    log.updated("cam0", cal, 0, {})
    assert "No space left" in (log.stopped or "")
    assert log.state()["reason"] == "rerun_error"
    log.frame("cam0", 1, np.zeros((4, 5), np.uint8))  # ignored, no exception
    log.close()


def _mask_of(path, entity_suffix):
    """The last mask image logged at an entity ending in ``entity_suffix``, as [y, x]."""
    from rerun.chunk import RrdReader

    reader = RrdReader(str(path))
    found = None
    for store in reader.recordings():
        for chunk in reader.stream(store=store).collect().stream():
            if not str(chunk.entity_path).endswith(entity_suffix):
                continue
            rb = chunk.to_record_batch()
            if "SegmentationImage:buffer" not in rb.schema.names:
                continue
            buf = rb.column("SegmentationImage:buffer").to_pylist()[-1][0]
            fmt = rb.column("SegmentationImage:format").to_pylist()[-1][0]
            found = np.asarray(buf, np.uint8).reshape(fmt["height"], fmt["width"])
    return found


def test_histograms_are_bars_as_wide_as_their_bins(tmp_path):
    """The c and b histograms are read back with one bar per bin, centred on the bin, as
    wide as the bin (in the map's units): bars that do not overlap."""
    from rerun.chunk import RrdReader

    rng = np.random.default_rng(2)
    shape = (30, 40)
    cal = Calibration.uniform(shape, 0.2, 0.01, log_offset=30.0).replace(
        contrast=(0.2 + 0.02 * rng.standard_normal(shape)).astype(np.float32),
        bias=(0.01 * rng.standard_normal(shape)).astype(np.float32),
        valid=np.ones(shape, bool))
    path = tmp_path / "h.rrd"
    log = RrdLogger(path, map_period_s=0.0, scalar_period_s=0.0)
    log.updated("cam0", cal, 1_000_000, {})
    log.close()
    reader = RrdReader(str(path))
    seen = {}
    for store in reader.recordings():
        for chunk in reader.stream(store=store).collect().stream():
            name = str(chunk.entity_path)
            if not name.startswith("/cameras/cam0/hist/"):
                continue
            rb = chunk.to_record_batch()
            cols = {c.split(":")[-1]: rb.column(c).to_pylist()[-1]
                    for c in rb.schema.names if c.startswith("BarChart:")}
            seen[name.rsplit("/", 1)[-1]] = cols
    assert set(seen) == {"contrast", "bias"}
    for name, values in (("contrast", cal.contrast), ("bias", cal.bias)):
        cols = seen[name]
        x = np.asarray(cols["abscissa"][0]["buffer"], np.float64)
        w = np.asarray(cols["widths"], np.float64).ravel()
        counts = np.asarray(cols["values"][0]["buffer"], np.float64)
        assert x.size == w.size == counts.size == 50
        np.testing.assert_allclose(np.diff(x), w[:-1], rtol=1e-4)  # touching, not overlapping
        assert w.max() < 0.5 * (x[-1] - x[0]) / 10  # far narrower than a unit-wide bar
        assert counts.sum() == values.size
        assert x[0] - w[0] / 2 <= values.min()
        assert values.max() <= x[-1] + w[-1] / 2


def test_series_each_in_one_view_of_its_own_scale():
    """Every logged series is in exactly one view (valid_fraction used to be in none) and
    rates, latencies, fractions and dB do not share an axis."""
    from evcal.service.rrdlog import SERIES, SERIES_VIEWS

    placed = [n for _, names in SERIES_VIEWS for n in names]
    assert sorted(placed) == sorted(SERIES)
    for _, names in SERIES_VIEWS:
        units = {n.rsplit("_", 1)[-1] for n in names if n.endswith(("_hz", "_ms", "_db"))}
        assert len(units) <= 1, names


def test_invalid_pixels_masked_truth_errors_and_stderr(tmp_path):
    """Invalid pixels are drawn by a mask layer over each map, not as data; with the truth
    the error maps and the c/b MAE series are logged; standard-error maps beside."""
    rng = np.random.default_rng(1)
    shape = (30, 40)
    valid = rng.random(shape) > 0.2
    cal = Calibration.uniform(shape, 0.2, 0.01, log_offset=30.0).replace(
        contrast=(0.2 + 0.01 * rng.standard_normal(shape)).astype(np.float32), valid=valid,
        stderr_contrast=np.where(valid, 0.01, np.inf).astype(np.float32),
        stderr_bias=np.where(valid, 0.005, np.inf).astype(np.float32))
    truth = (np.full(shape, 0.2), np.full(shape, 0.01))
    path = tmp_path / "t.rrd"
    log = RrdLogger(path, map_period_s=0.0, scalar_period_s=0.0, truth={"cam0": truth})
    t_us = 1_744_227_144_732_712  # a ROS stamp: also on the absolute sensor_clock timeline
    log.updated("cam0", cal, t_us, {})
    log.close()
    from rerun.chunk import RrdReader

    reader = RrdReader(str(path))
    timelines = {name for store in reader.recordings()
                 for chunk in reader.stream(store=store).collect().stream()
                 if str(chunk.entity_path) == "/cameras/cam0/maps/contrast"
                 for name in chunk.to_record_batch().schema.names}
    assert {"sensor_time", "sensor_clock", "wall_time"} <= timelines
    ents = read_entities(path)
    for name in ("contrast", "bias", "stderr_contrast", "stderr_bias", "contrast_error",
                 "bias_error"):
        assert ents[f"/cameras/cam0/maps/{name}"] == 1, name
        np.testing.assert_array_equal(_mask_of(path, f"maps/{name}/invalid"), ~valid)
    assert ents["/cameras/cam0/series/c_mae"] == 1
    assert ents["/cameras/cam0/series/valid_fraction"] == 1


def test_offline_review_recordings(tmp_path, capsys):
    """calibrate --rrd and evaluate --rrd: the maps (with the truth evcal simulate wrote
    beside the recording), then the recording replayed through the reconstruction, with the
    ON/OFF events of every other interval."""
    from evcal.cli import main

    sim = tmp_path / "sim.npz"
    assert main(["simulate", "--out", str(sim), "--sensor-size", "48x36", "--duration-s",
                 "2", "--internal-rate-hz", "500", "-q"]) == 0
    cal = tmp_path / "cal.npz"
    assert main(["calibrate", str(sim), "--out", str(cal), "--rrd", str(tmp_path / "c.rrd"),
                 "-q"]) == 0
    ents = read_entities(tmp_path / "c.rrd")
    assert ents["/cameras/sim.npz/maps/contrast_error"] == 1
    assert ents["/cameras/sim.npz/series/c_mae"] == 1
    assert not any("/recon/" in e for e in ents)
    assert main(["evaluate", str(sim), "--calibration", str(cal), "--frames-per-image", "5",
                 "--rrd", str(tmp_path / "e.rrd"), "--truth", str(tmp_path / "nope.npz")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert main(["evaluate", str(sim), "--calibration", str(cal), "--frames-per-image", "5",
                 "--rrd", str(tmp_path / "e.rrd"), "-q"]) == 0
    ents = read_entities(tmp_path / "e.rrd")
    # 50 frame intervals: a window of 5 opens at the frame after the last one closed (every
    # 6th frame), so 8 reconstructions; the events of every other interval
    assert ents["/cameras/sim.npz/recon/calibrated"] == 50 // 6
    assert ents["/cameras/sim.npz/series/psnr_gain_db"] == 50 // 6
    assert ents["/cameras/sim.npz/events"] == 50 // 2


def test_live_viewer_sink_beside_the_file(tmp_path):
    """serve_port (serve --rerun-serve): a gRPC server a viewer connects to, listening while
    the file is written as before."""
    import socket

    from evcal.testing import free_port

    port = free_port()
    path = tmp_path / "live.rrd"
    log = RrdLogger(path, map_period_s=0.0, scalar_period_s=0.0, serve_port=port)
    try:
        cal = Calibration.uniform((24, 32), 0.2, 0.01, log_offset=30.0)
        log.updated("cam0", cal, 1_000, {})
        with socket.create_connection(("127.0.0.1", port), timeout=5):
            pass  # the viewer's endpoint is up
    finally:
        log.close()
    assert read_entities(path)["/cameras/cam0/maps/contrast"] == 1


def test_the_log_says_which_method_calibrated_an_events_only_camera(tmp_path):
    """An events-only camera is calibrated by OffE until frames come, then by OnEI: the log
    of the .rrd says so when the method changes (not for a camera on OnEI from the start)."""
    from rerun.chunk import RrdReader

    cal = Calibration.uniform((12, 16), 0.1, 0.0, log_offset=30.0)
    path = tmp_path / "m.rrd"
    log = RrdLogger(path, map_period_s=0.0, scalar_period_s=0.0)
    log.updated("cam0", cal, 1_000_000, {"method": "offe"})
    log.updated("cam0", cal, 2_000_000, {"method": "offe"})
    log.updated("cam0", cal, 3_000_000, {"method": "onei"})
    log.updated("cam1", cal, 3_000_000, {"method": "onei"})
    log.close()
    texts: dict[str, list[str]] = {}
    reader = RrdReader(str(path))
    for store in reader.recordings():
        for chunk in reader.stream(store=store).collect().stream():
            rb = chunk.to_record_batch()
            if "TextLog:text" in rb.schema.names:
                texts.setdefault(str(chunk.entity_path), []).extend(
                    t[0] for t in rb.column("TextLog:text").to_pylist() if t)
    cam0 = [t for t in texts.get("/cameras/cam0/log", []) if t.startswith("calibration by")]
    assert cam0 == ["calibration by offe (events only: c relative, median 0.1)",
                    "calibration by onei"]
    assert not [t for t in texts.get("/cameras/cam1/log", []) if t.startswith("calibration by")]
