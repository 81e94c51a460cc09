"""Readers of Prophesee RAW/DAT, HDF5 (MVSEC, DSEC, v2e) and jAER AEDAT 2.0 / 3.1 files.

The files in tests/data/formats/ and the figures asserted here (cross-checked with faery,
expelliarmus and v2e's own event list) are described in tests/data/formats/README.md.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from evcal.errors import ErrorReason
from evcal.events import EVENTS_DTYPE, SensorSize
from evcal.io import (
    EmptyRecordingError,
    TruncatedRecordingError,
    TruncatedRecordingWarning,
    open_recording,
    read_aedat2,
    read_hdf5,
    read_prophesee,
    sniff,
)
from evcal.recording import RecordingError

DATA = Path(__file__).parent / "data" / "formats"
VGA = SensorSize(height=480, width=640)
DAVIS240 = SensorSize(height=180, width=240)


def _key(events: np.ndarray) -> np.ndarray:
    """Events in a canonical order (time, then y, x, p), to compare as multisets."""
    return np.sort(events, order=["t_us", "y", "x", "p"])


def _truth() -> np.ndarray:
    """The events v2e returned for v2e_dvs.h5 / v2e_davis240.aedat (its float s to µs)."""
    z = np.load(DATA / "v2e_truth.npz")
    ev = np.empty(z["x"].size, EVENTS_DTYPE)
    ev["t_us"] = np.rint(z["t_s"] * 1e6)
    ev["x"], ev["y"], ev["p"] = z["x"], z["y"], z["p"]
    return ev


def _first(events: np.ndarray) -> tuple[int, int, int, int]:
    e = events[0]
    return (int(e["t_us"]), int(e["x"]), int(e["y"]), int(e["p"]))


def _cut(src: Path, dst: Path, n_bytes: int) -> Path:
    dst.write_bytes(src.read_bytes()[:n_bytes])
    return dst


# ------------------------------------------------------------------------- Prophesee


def test_evt2_real_file_needs_the_sensor_and_gives_the_reference_figures() -> None:
    path = DATA / "evt2_real.raw"
    assert sniff(path) == "prophesee"
    with pytest.raises(RecordingError, match=r"declares no sensor size.*pass sensor="):
        open_recording(path)
    rec = open_recording(path, sensor=VGA)
    ev = rec.events
    assert rec.sensor == VGA
    assert rec.n_events == 23938
    assert _first(ev) == (913716224, 35, 443, 1)
    assert int(ev["t_us"][-1]) == 913717207
    assert int(np.count_nonzero(ev["p"] > 0)) == 5743
    assert rec.metadata["format"] == "evt2"
    assert rec.metadata["reordered_events"] == 0
    assert rec.metadata["untimed_events"] == 0
    assert len(rec.frames) == 0


@pytest.mark.parametrize(("name", "fmt"), [("evt3_faery.raw", "evt3"), ("cd_faery.dat", "dat"),
                                           ("evt21.raw", "evt21"),
                                           ("evt21_legacy.raw", "evt21")])
def test_prophesee_encodings_give_the_same_events(name: str, fmt: str) -> None:
    rec = open_recording(DATA / name)
    assert rec.sensor == VGA  # from the header
    assert rec.metadata["format"] == fmt
    assert rec.n_events == 20000
    assert _first(rec.events) == (913716224, 35, 443, 1)
    assert int(rec.events["t_us"][-1]) == 913717043
    assert int(np.count_nonzero(rec.events["p"] > 0)) == 5146
    real = read_prophesee(DATA / "evt2_real.raw", sensor=VGA).events[:20000]
    assert np.array_equal(_key(rec.events), _key(real))


def test_prophesee_sensor_argument_is_checked() -> None:
    with pytest.raises(RecordingError, match="declares a 640x480 sensor"):
        read_prophesee(DATA / "evt3_faery.raw", sensor=SensorSize(height=260, width=346))


@pytest.mark.parametrize(("name", "cut", "match"), [
    ("evt2_real.raw", -2, r"inside a 4-byte EVT 2.0 word \(2 of its bytes present\)"),
    ("evt3_faery.raw", -1, r"inside a 2-byte EVT 3.0 word \(1 of its bytes present\)"),
    ("cd_faery.dat", -5, r"inside a 8-byte event \(3 of its bytes present\)"),
    ("evt21.raw", -4, r"inside a 8-byte EVT 2.1 word \(4 of its bytes present\)"),
])
def test_truncated_prophesee_files_read_their_whole_words(tmp_path: Path, name: str, cut: int,
                                                          match: str) -> None:
    src = DATA / name
    path = _cut(src, tmp_path / name, src.stat().st_size + cut)
    sensor = VGA if name == "evt2_real.raw" else None
    with pytest.warns(TruncatedRecordingWarning, match=match):
        rec = read_prophesee(path, sensor=sensor)
    full = read_prophesee(src, sensor=sensor)
    assert np.array_equal(rec.events, full.events[: rec.n_events])
    left = int(match.split(r"\(")[1].split()[0])  # the bytes of the partial word
    assert rec.metadata["truncated"]["cut_bytes"] == left
    with pytest.raises(TruncatedRecordingError, match=match) as info:
        read_prophesee(path, sensor=sensor, strict=True)
    assert info.value.reason == ErrorReason.TRUNCATED


def _raw(tmp_path: Path, header: str, words: np.ndarray, name: str = "x.raw") -> Path:
    path = tmp_path / name
    path.write_bytes(header.encode() + words.tobytes())
    return path


def test_prophesee_malformed_headers_and_words(tmp_path: Path) -> None:
    head = "% format EVT2;height=10;width=10\n"
    th = np.uint32(8 << 28)
    path = _raw(tmp_path, head, np.array([th, 5 << 28], "<u4"))
    with pytest.raises(RecordingError, match=r"EVT 2.0 word 1 has type 5") as info:
        read_prophesee(path)
    assert info.value.reason == ErrorReason.MALFORMED
    path = _raw(tmp_path, "% evt 4.0\n% geometry 10x10\n", np.zeros(2, "<u4"))
    with pytest.raises(RecordingError, match="gives the encoding as evt 4.0"):
        read_prophesee(path)
    path = tmp_path / "h.raw"
    path.write_bytes(b"% evt 3.0\n% geometry 10x")  # header cut before its newline
    with pytest.raises(EmptyRecordingError, match="truncated inside its header"):
        read_prophesee(path)
    dat = tmp_path / "trig.dat"
    dat.write_bytes(b"% Data file containing Trigger events\n% Version 2\n% Width 4\n"
                    b"% Height 4\n" + bytes([0x0E, 8]) + bytes(8))
    with pytest.raises(RecordingError, match="external trigger events"):
        read_prophesee(dat)
    dat.write_bytes(b"% Data file containing CD events\n% Version 2\n% Width 4\n% Height 4\n")
    with pytest.raises(EmptyRecordingError, match="header only"):
        read_prophesee(dat)


def test_evt2_time_high_wrap_and_untimed_events(tmp_path: Path) -> None:
    def cd(on: int, ts: int, x: int, y: int) -> int:
        return (on << 28) | (ts << 22) | (x << 11) | y

    words = np.array([cd(1, 1, 1, 1),  # before any TIME_HIGH: skipped, as OpenEB does
                      (8 << 28) | 0xFFFFFFF, cd(1, 63, 2, 3),
                      (8 << 28) | 0, cd(0, 5, 4, 5),  # TIME_HIGH back to 0: a wrap
                      (10 << 28), (14 << 28)], "<u4")
    rec = read_prophesee(_raw(tmp_path, "% format EVT2;height=10;width=10\n", words))
    assert rec.events.tolist() == [((0xFFFFFFF << 6) | 63, 2, 3, 1), ((1 << 34) | 5, 4, 5, -1)]
    assert rec.metadata["untimed_events"] == 1
    assert rec.metadata["trigger_events"] == 1


def test_evt3_wrap_and_events_outside_the_sensor(tmp_path: Path) -> None:
    words = np.array([(8 << 12) | 0xFFF, (6 << 12) | 7, (0 << 12) | 2, (2 << 12) | (1 << 11) | 3,
                      (8 << 12) | 0, (6 << 12) | 1, (2 << 12) | 9,
                      (2 << 12) | 50],  # x = 50 is outside the 10x10 sensor
                     "<u2")
    path = _raw(tmp_path, "% evt 3.0\n% format EVT3;height=10;width=10\n", words)
    with pytest.warns(RuntimeWarning, match="1 events outside the 10x10 sensor were dropped"):
        rec = read_prophesee(path)
    assert rec.events.tolist() == [((0xFFF << 12) | 7, 3, 2, 1), ((1 << 24) | 1, 9, 2, -1)]
    assert rec.metadata["dropped_events"] == 1


def test_dat_time_wrap_and_version_1_layout(tmp_path: Path) -> None:
    rows = np.zeros(3, [("t", "<u4"), ("d", "<u4")])
    rows["t"] = [4294967000, 4294967290, 100]
    rows["d"] = [(1 << 28) | (2 << 14) | 3, (0 << 28) | (1 << 14) | 1, (1 << 28) | 5]
    dat = tmp_path / "v2.dat"
    dat.write_bytes(b"% Data file containing CD events\n% Version 2\n% Width 8\n% Height 8\n"
                    + bytes([0x0C, 8]) + rows.tobytes())
    rec = read_prophesee(dat)
    assert rec.events.tolist() == [(4294967000, 3, 2, 1), (4294967290, 1, 1, -1),
                                   ((1 << 32) + 100, 5, 0, 1)]
    rows["d"] = [(1 << 17) | (2 << 9) | 3, (1 << 9) | 1, (1 << 17) | 5]
    dat.write_bytes(b"% Data file containing 2D events\n% Version 1\n% Width 8\n% Height 8\n"
                    + bytes([0x00, 8]) + rows.tobytes())
    rec = read_prophesee(dat)
    assert rec.events["x"].tolist() == [3, 1, 5]
    assert rec.events["p"].tolist() == [1, -1, 1]
    assert rec.metadata["event_type"] == "2d"


# ------------------------------------------------------------------------------ HDF5


def test_v2e_h5_from_v2e_itself() -> None:
    path = DATA / "v2e_dvs.h5"
    assert sniff(path) == "hdf5"
    rec = open_recording(path)
    assert rec.metadata["format"] == "hdf5-v2e"
    assert rec.sensor == DAVIS240  # the frames' size
    assert rec.n_events == 2674
    assert _first(rec.events) == (2000, 162, 71, -1)
    assert int(rec.events["t_us"][-1]) == 5000
    assert int(np.count_nonzero(rec.events["p"] > 0)) == 1811
    assert np.array_equal(rec.events, _truth())
    assert rec.frames.t_us.tolist() == [0, 1000, 2000, 3000, 4000, 5000]
    assert rec.frames.images.dtype == np.uint8


def test_mvsec_layout_and_camera_option() -> None:
    path = DATA / "mvsec_like.hdf5"
    rec = open_recording(path)
    assert rec.metadata["format"] == "hdf5-mvsec"
    assert rec.metadata["camera"] == "left"
    assert rec.sensor == SensorSize(height=260, width=346)
    assert rec.n_events == 2674
    assert _first(rec.events) == (1504645177002000, 162, 71, -1)
    assert int(rec.events["t_us"][-1]) == 1504645177005000
    assert np.array_equal(rec.events["t_us"] - 1504645177000000, _truth()["t_us"])
    assert rec.frames.t_us.tolist() == [1504645177000500, 1504645177005500]
    right = open_recording(path, camera="right")
    assert right.n_events == 100
    assert len(right.frames) == 0
    with pytest.raises(RecordingError, match=r"no camera 'middle'.*left, right"):
        open_recording(path, camera="middle")
    with pytest.raises(RecordingError, match="camera= chooses an MVSEC camera"):
        read_hdf5(DATA / "dsec_like.h5", camera="left")
    with pytest.raises(RecordingError, match="camera chooses the camera of an MVSEC"):
        open_recording(DATA / "evt3_faery.raw", camera="left")


def test_dsec_layout_blosc_and_t_offset() -> None:
    rec = open_recording(DATA / "dsec_like.h5")
    assert rec.metadata["format"] == "hdf5-dsec"
    assert rec.sensor == VGA
    assert rec.metadata["t_offset_us"] == 50_000_000
    assert rec.n_events == 2674
    assert _first(rec.events) == (50002000, 162, 71, -1)
    assert np.array_equal(rec.events["t_us"] - 50_000_000, _truth()["t_us"])


def test_hdf5_errors(tmp_path: Path) -> None:
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f.create_dataset("foo/bar", data=np.zeros(3))
    with pytest.raises(RecordingError, match=r"no layout evcal knows; it has foo/bar \(3,\)"):
        open_recording(other)
    src = DATA / "v2e_dvs.h5"
    cut = _cut(src, tmp_path / "cut.h5", src.stat().st_size // 2)
    with pytest.raises(RecordingError, match=r"truncated HDF5 file"):
        open_recording(cut)
    bare = tmp_path / "bare.h5"
    with h5py.File(bare, "w") as f:
        f.create_dataset("events", data=np.array([[10, 1, 2, 1], [20, 3, 4, 0]], np.uint32))
    with pytest.raises(RecordingError, match="declares no sensor size; pass sensor="):
        open_recording(bare)
    rec = open_recording(bare, sensor=SensorSize(height=8, width=8))
    assert rec.events.tolist() == [(10, 1, 2, 1), (20, 3, 4, -1)]
    with h5py.File(bare, "a") as f:
        f["events"][1, 3] = 2
    with pytest.raises(RecordingError, match="event 1 has polarity 2, expected 0 or 1"):
        open_recording(bare, sensor=SensorSize(height=8, width=8))


# ------------------------------------------------------------------------- AEDAT 2/3


def test_aedat2_from_v2e_writer_equals_v2e_events() -> None:
    path = DATA / "v2e_davis240.aedat"
    assert sniff(path) == "aedat2"
    with pytest.raises(RecordingError, match="names no chip evcal knows"):
        open_recording(path)
    rec = open_recording(path, sensor=DAVIS240)
    assert rec.metadata["address_layout"] == "davis"
    assert rec.n_events == 2674
    assert _first(rec.events) == (2000, 162, 71, -1)
    assert np.array_equal(rec.events, _truth())


def test_aedat2_chip_from_header_and_content_sniffing(tmp_path: Path) -> None:
    data = (DATA / "v2e_davis240.aedat").read_bytes()
    data = data.replace(b"# User name", b"# AEChip: eu.seebetter.ini.chips.davis.DAVIS240C\r\n"
                        b"# User name", 1)
    path = tmp_path / "renamed.BIN"
    path.write_bytes(data)
    assert sniff(path) == "aedat2"
    rec = open_recording(path)
    assert rec.sensor == DAVIS240
    assert rec.metadata["chip"].endswith("DAVIS240C")
    assert np.array_equal(rec.events, _truth())


def _aedat2(tmp_path: Path, chip: str, rows: list[tuple[int, int]]) -> Path:
    rec = np.array(rows, dtype=[("a", ">u4"), ("t", ">u4")])
    path = tmp_path / "x.aedat"
    path.write_bytes(b"#!AER-DAT2.0\r\n# AEChip: " + chip.encode() + b"\r\n"
                     b"#End Of ASCII Header\r\n" + rec.tobytes())
    return path


def test_aedat2_dvs128_layout(tmp_path: Path) -> None:
    # raw x 5, y 7: jAER x = 127 - 5; y counted from the bottom -> image row 127 - 7
    path = _aedat2(tmp_path, "ch.unizh.ini.jaer.chip.retina.DVS128",
                   [((7 << 8) | (5 << 1) | 0, 10), ((7 << 8) | (5 << 1) | 1, 11),
                    (1 << 15, 12)])
    rec = read_aedat2(path)
    assert rec.sensor == SensorSize(height=128, width=128)
    assert rec.events.tolist() == [(10, 122, 120, 1), (11, 122, 120, -1)]
    assert rec.metadata["special_events"] == 1


def test_aedat2_davis_samples_and_time_wrap(tmp_path: Path) -> None:
    dvs = (3 << 22) | (4 << 12) | (1 << 11)
    path = _aedat2(tmp_path, "eu.seebetter.ini.chips.davis.Davis346B", [
        (dvs, 0xFFFFFFF0),  # int32 -16 in jAER: just before the wrap
        ((1 << 31) | 7, 0xFFFFFFF1),  # an APS sample
        ((1 << 31) | (1 << 11), 0xFFFFFFF2),  # an IMU sample
        (1 << 10, 3),  # a special event
        (dvs ^ (1 << 11), 5),  # after the wrap
    ])
    rec = read_aedat2(path)
    assert rec.sensor == SensorSize(height=260, width=346)
    assert rec.events.tolist() == [(0xFFFFFFF0, 341, 256, 1), ((1 << 32) + 5, 341, 256, -1)]
    assert (rec.metadata["aps_samples"], rec.metadata["imu_samples"],
            rec.metadata["special_events"], rec.metadata["time_wraps"]) == (1, 1, 1, 1)


def test_aedat2_errors(tmp_path: Path) -> None:
    src = DATA / "v2e_davis240.aedat"
    cut = _cut(src, tmp_path / "cut.aedat", src.stat().st_size - 3)
    with pytest.raises(TruncatedRecordingError, match=r"inside a 8-byte record \(5 of its "
                                                      r"bytes present\)") as info:
        read_aedat2(cut, sensor=DAVIS240, strict=True)
    assert info.value.reason == ErrorReason.TRUNCATED
    with pytest.raises(RecordingError, match="outside the 100x100 sensor"):
        read_aedat2(src, sensor=SensorSize(height=100, width=100))
    old = tmp_path / "old.aedat"
    old.write_bytes(b"#!AER-DAT3.0\r\n#!END-HEADER\r\n")
    with pytest.raises(RecordingError, match="another version than 2.0, 3.1 or 4.0"):
        open_recording(old)


def test_aedat31_events_frames_and_overflow() -> None:
    path = DATA / "davis240_v31.aedat"
    assert sniff(path) == "aedat3"
    rec = open_recording(path)
    assert rec.sensor == DAVIS240  # '#Source 1: DAVIS240C'
    assert rec.n_events == 2674
    t0 = (1 << 31) - 3500
    assert _first(rec.events) == (t0 + 2000, 162, 71, -1)
    assert int(rec.events["t_us"][-1]) == t0 + 5000  # past the 31-bit overflow
    truth = _truth()
    assert np.array_equal(rec.events["t_us"] - t0, truth["t_us"])
    assert np.array_equal(rec.events[["x", "y", "p"]], truth[["x", "y", "p"]])
    assert rec.frames.t_us.tolist() == [t0 + 1000, t0 + 4000]
    assert rec.frames.exposure_us.tolist() == [1000, 1000]
    with h5py.File(DATA / "v2e_dvs.h5", "r") as f:
        v2e_frames = f["frame"][()]
    assert rec.frames.images.dtype == np.float32
    assert np.array_equal(rec.frames.images, v2e_frames[[1, 4]].astype(np.float32))
    assert rec.metadata["invalid_events"] == 1
    assert rec.metadata["skipped_packets"] == {"special": 1, "IMU6": 1}


def test_aedat31_truncated_and_corrupt(tmp_path: Path) -> None:
    src = DATA / "davis240_v31.aedat"
    data = src.read_bytes()
    start = data.index(b"#!END-HEADER\r\n") + 14
    cut = _cut(src, tmp_path / "cut.aedat", start + 28 + 8 + 10)  # into packet 1's header
    with pytest.raises(TruncatedRecordingError, match=r"inside the 28-byte header of packet "
                                                      r"1 \(10 bytes of it present\)") as info:
        read_aedat2(cut, strict=True)
    assert info.value.reason == ErrorReason.TRUNCATED
    cut = _cut(src, tmp_path / "cut2.aedat", len(data) - 12)  # into the last (IMU6) packet
    with pytest.warns(TruncatedRecordingWarning, match=r"inside packet 7 \(type 3; 64 bytes "
                                                       r"with its header, 52 present\)"):
        rec = read_aedat2(cut)
    assert rec.n_events == 2674  # the IMU6 packet held no polarity event
    bad = bytearray(data)
    bad[start + 4 : start + 8] = (0).to_bytes(4, "little")  # eventSize 0
    (tmp_path / "bad.aedat").write_bytes(bytes(bad))
    with pytest.raises(RecordingError, match="packet 0 .* impossible header") as info:
        read_aedat2(tmp_path / "bad.aedat")
    assert info.value.reason == ErrorReason.MALFORMED
    (tmp_path / "nohead.aedat").write_bytes(b"#!AER-DAT3.1\r\n#Format: RAW\r\n")
    with pytest.raises(EmptyRecordingError, match="no '#!END-HEADER' line"):
        read_aedat2(tmp_path / "nohead.aedat")


# -------------------------------------------------------------------- sniffing, CLI


def test_suffix_fallback_names_the_format_and_what_evcal_reads(tmp_path: Path) -> None:
    for name, kind in (("x.RAW", "prophesee"), ("x.dat", "prophesee"), ("x.H5", "hdf5"),
                       ("x.hdf5", "hdf5"), ("x.AEDAT", "aedat2")):
        path = tmp_path / name
        path.write_bytes(b"\x00" * 32)
        assert sniff(path) == kind
        with pytest.raises(RecordingError, match=rf"unknown recording format .* suffix "
                                                 rf"'{path.suffix}' it would be {kind}.*"
                                                 r"evcal reads .*Prophesee RAW"):
            open_recording(path)


def test_content_beats_suffix(tmp_path: Path) -> None:
    for src, name, kind in (("evt3_faery.raw", "a.h5", "prophesee"),
                            ("cd_faery.dat", "a.bin", "prophesee"),
                            ("v2e_dvs.h5", "a.dat", "hdf5"),
                            ("davis240_v31.aedat", "a.raw", "aedat3")):
        dst = tmp_path / name
        shutil.copy(DATA / src, dst)
        assert sniff(dst) == kind
        assert open_recording(dst).n_events in (20000, 2674)
    text = tmp_path / "notes.raw"
    text.write_text("% a comment, no Prophesee key\n")
    with pytest.raises(RecordingError, match="unknown recording format"):
        open_recording(text)


@pytest.mark.parametrize(("name", "extra", "n"), [
    ("evt2_real.raw", ["--sensor-size", "640x480"], 23938), ("evt21.raw", [], 20000),
    ("cd_faery.dat", [], 20000), ("dsec_like.h5", [], 2674), ("mvsec_like.hdf5", [], 2674),
    ("davis240_v31.aedat", [], 2674), ("v2e_davis240.aedat", ["--sensor-size", "240x180"], 2674),
])
def test_evcal_info(name: str, extra: list[str], n: int,
                    capsys: pytest.CaptureFixture[str]) -> None:
    from evcal.cli import main

    assert main(["info", str(DATA / name), "--json", "--quiet", *extra]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["n_events"] == n
