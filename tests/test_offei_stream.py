"""Streaming OffEI (offline.OffEIStream, offline.offei_file): a recording read message by
message gives the maps of the in-memory OffEI."""

from __future__ import annotations

import numpy as np
import pytest

from evcal.io import open_recording, write_recording
from evcal.offline import OffEIConfig, offei, offei_file
from evcal.recording import RecordingError
from evcal.sim.ideal import SimConfig, simulate_ideal


@pytest.fixture(scope="module")
def sim_mcap(tmp_path_factory):
    sim = simulate_ideal(SimConfig(height=36, width=48, duration_s=3.0, seed=4,
                                   internal_rate_hz=500))
    path = tmp_path_factory.mktemp("stream") / "sim.mcap"
    write_recording(sim.recording, path)
    return path


def _same(a, b):
    np.testing.assert_array_equal(a.valid, b.valid)
    np.testing.assert_array_equal(a.contrast, b.contrast)
    np.testing.assert_array_equal(a.bias, b.bias)
    assert a.log_offset == b.log_offset


@pytest.mark.parametrize("log_offset", [30.0, "auto"])
def test_streamed_equals_in_memory(sim_mcap, log_offset):
    """Given offset, or "auto" with a prefix holding the whole recording: identical maps."""
    cfg = OffEIConfig(log_offset=log_offset)
    ref = offei(open_recording(sim_mcap), cfg)
    seen = []
    got = offei_file(sim_mcap, cfg, progress=lambda done, total: seen.append((done, total)))
    _same(got, ref)
    assert seen[-1][0] == seen[-1][1] > 0


def test_auto_offset_from_a_prefix(sim_mcap):
    """With a prefix shorter than the recording, the offset comes from the prefix (said in
    the diagnostics) and the maps equal the in-memory OffEI at that offset."""
    got = offei_file(sim_mcap, OffEIConfig(log_offset="auto"), prefix_frames=30)
    info = got.diagnostics.log_offset_estimation
    assert info["prefix_frames"] == 30
    _same(got, offei(open_recording(sim_mcap), OffEIConfig(log_offset=got.log_offset)))
    assert abs(np.log1p(got.log_offset) - np.log1p(30.0)) < 0.5


def test_streaming_refuses_what_it_cannot_read(tmp_path, sim_mcap):
    bad = tmp_path / "cut.mcap"
    bad.write_bytes(sim_mcap.read_bytes()[: sim_mcap.stat().st_size // 2])
    with pytest.raises(RecordingError, match="truncated"):
        offei_file(bad, OffEIConfig(log_offset=30.0))


def test_calibrate_stream_cli(sim_mcap, tmp_path, capsys):
    from evcal.cli import main
    from evcal.io import load_calibration

    out = tmp_path / "s.npz"
    assert main(["calibrate", str(sim_mcap), "--stream", "--log-offset", "30", "--out",
                 str(out), "-q"]) == 0
    _same(load_calibration(out), offei(open_recording(sim_mcap), OffEIConfig(log_offset=30.0)))
    assert main(["calibrate", str(sim_mcap), "--stream", "--method", "onei", "--out",
                 str(out)]) == 2
    assert "--stream is OffEI alone" in capsys.readouterr().err
