"""``evcal demo`` runs end to end (small size here) and prints its table; ``evcal query``
fails clearly when no service answers."""

from __future__ import annotations

import pytest

pytest.importorskip("zenoh")
pytest.importorskip("rerun")

from evcal.service.rrdlog import read_entities  # noqa: E402
from evcal.testing import endpoint, free_port, run_client  # noqa: E402

pytestmark = pytest.mark.timeout(180)


def test_demo_prints_table_and_writes_rrd(tmp_path):
    out = tmp_path / "demo.rrd"
    res = run_client("demo", ["--out", str(out), "--size", "64x48", "--duration", "3",
                              "--n-small", "5000"])
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert any(line.startswith("calibration") and "PSNR dB" in line for line in lines)
    rows = {line.split("  ")[0]: line for line in lines}
    assert "DI (c=0.1, b=0)" in rows
    assert "live OnEI (service)" in rows
    live = rows["live OnEI (service)"].split()
    gain_db = float(live[-1])
    assert gain_db > 1.0, res.stdout  # the live calibration beats DI
    # the true maps: nothing wrong in them, and the ceiling of what the events allow
    truth = rows["true maps (perfect c, b)"].split()
    assert truth[-6:-3] == ["100.0", "0.0000", "0.0%"], rows["true maps (perfect c, b)"]
    assert float(truth[-1]) >= gain_db - 0.5
    # every column is explained
    for col in ("valid %", "c MAE", "c med rel", "b MAE", "PSNR dB", "gain dB", "true maps"):
        assert any(line.startswith(col) for line in lines), col
    assert "replayed in real time" in res.stderr
    ents = read_entities(out)
    assert ents.get("/cameras/demo/cam0/maps/contrast", 0) >= 3
    # the truth is known: error maps and the c MAE curve beside the maps
    assert ents["/cameras/demo/cam0/maps/contrast_error"] == ents[
        "/cameras/demo/cam0/maps/contrast"]
    assert ents["/cameras/demo/cam0/series/c_mae"] >= 3
    assert ents.get("/cameras/demo/cam0/events", 0) >= 1
    assert "frame received -> calibration published" in res.stderr


def test_query_without_a_service_fails_clearly(tmp_path):
    res = run_client("query", ["--camera", "nobody", "--out", str(tmp_path / "c.npz"),
                               "--connect", endpoint(free_port()), "--no-multicast-scouting",
                               "--timeout", "1"])
    assert res.returncode == 1
    assert "no service answered" in res.stderr
    assert not (tmp_path / "c.npz").exists()


def test_the_camera_table_has_a_row_per_camera_and_one_per_empty_instance():
    from evcal.clients.query import format_instances

    infos = [
        {"instance": "w1", "pid": 12, "shard": "1/2", "cameras": [
            {"id": "lab/a", "sensor": "346x260", "updates": 4, "events": 1234567,
             "last_update_t_us": 99}]},
        {"instance": "sup", "pid": 10, "supervisor": True, "cameras": []},
        {"instance": "w0", "pid": 11, "shard": "0/2", "cameras": [
            {"id": "lab/b", "sensor": None, "updates": 0, "events": 0,
             "last_update_t_us": None}]},
    ]
    lines = format_instances(infos).splitlines()
    assert lines[0].startswith("instance")
    assert lines[1].split()[:3] == ["sup", "(supervisor)", "10"]
    assert "1,234,567" in lines[3]
    assert lines[3].split()[-1] == "99"
    assert lines[2].split()[-1] == "-"  # no calibration yet
    assert len(lines) == 4
