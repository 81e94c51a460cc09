"""Readers and writers: round trips, the wire envelopes, real sample files, bad inputs."""

from __future__ import annotations

import json
from pathlib import Path

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from PIL import Image

from evcal.calibration import Calibration, Diagnostics, Special
from evcal.events import EVENTS_DTYPE, SensorSize, make_events, validate_events
from evcal.io import (
    CalibrationFileError,
    EmptyRecordingError,
    TruncatedRecordingError,
    TruncatedRecordingWarning,
    WireError,
    decode_events,
    decode_frame,
    encode_events,
    encode_frame,
    load_calibration,
    open_recording,
    read_aedat4,
    read_ecd,
    read_mcap,
    read_npz,
    save_calibration,
    write_csv,
    write_ecd,
    write_mcap,
    write_npz,
    write_recording,
)
from evcal.io.aedat4 import events_from_packets
from evcal.io.calibfile import CALIBRATION_KEYS
from evcal.io.ecd import format_events_txt, sensor_from_calib
from evcal.recording import Frames, Recording, RecordingError

SENSOR = SensorSize(height=30, width=40)
ECD_CALIB = [199.092366542, 198.82882047, 132.192071378, 110.712660011, -0.368436311798,
             0.150947243557, -0.000296130534385, -0.000759431726241, 0.0]
HYP = settings(max_examples=60, deadline=None,
               suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def _recording(seed: int = 0, n: int = 5000, n_frames: int = 4, *, float_frames: bool = False,
               t0_us: int = 1_000_000) -> Recording:
    """Random sorted events over 0.5 s and a few frames on SENSOR."""
    rng = np.random.default_rng(seed)
    h, w = SENSOR.shape
    t = np.sort(rng.integers(t0_us, t0_us + 500_000, n))
    ev = make_events(t, rng.integers(0, w, n), rng.integers(0, h, n), rng.integers(0, 2, n))
    dtype = np.float32 if float_frames else np.uint8
    images = rng.integers(0, 256, (n_frames, h, w)).astype(dtype)
    if float_frames:
        images += rng.random(images.shape, dtype=np.float32)
    frames = Frames(t_us=t0_us + 100_000 * np.arange(n_frames) + 17, images=images,
                    exposure_us=np.full(n_frames, 1234))
    return Recording(SENSOR, ev, frames, {"name": "synthetic", "seed": seed,
                                          "gain": np.float32(0.5)})


def _same(a: Recording, b: Recording, *, frames_exact: bool = True) -> None:
    assert a.sensor == b.sensor
    assert a.events.dtype == b.events.dtype == EVENTS_DTYPE
    np.testing.assert_array_equal(a.events, b.events)
    assert a.frames is not None
    assert b.frames is not None
    np.testing.assert_array_equal(a.frames.t_us, b.frames.t_us)
    if frames_exact:
        assert a.frames.images.dtype == b.frames.images.dtype
        np.testing.assert_array_equal(a.frames.images, b.frames.images)


def _user_metadata(rec: Recording) -> dict:
    return {k: v for k, v in rec.metadata.items() if k not in ("format", "source")}


# ----------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("float_frames", [False, True])
def test_mcap_round_trip(tmp_path: Path, float_frames: bool) -> None:
    rec = _recording(float_frames=float_frames)
    path = write_mcap(rec, tmp_path / "rec.mcap", chunk_events=777)
    back = read_mcap(path)
    _same(rec, back)
    np.testing.assert_array_equal(back.frames.exposure_us, rec.frames.exposure_us)
    assert _user_metadata(back) == {"name": "synthetic", "seed": 0, "gain": 0.5}
    assert back.metadata["format"] == "mcap"


def test_mcap_layout_is_plain_mcap(tmp_path: Path) -> None:
    """Channels, schemas, encodings, times and metadata as other MCAP tools see them."""
    from mcap.reader import make_reader

    rec = _recording()
    path = write_mcap(rec, tmp_path / "rec.mcap", chunk_events=1000)
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert {s.name: s.encoding for s in summary.schemas.values()} == {
            "evcal.EventChunk": "jsonschema", "evcal.Frame": "jsonschema"}
        for s in summary.schemas.values():
            json.loads(s.data)
        assert {c.topic: c.message_encoding for c in summary.channels.values()} == {
            "/events": "msgpack", "/frames": "msgpack"}
        assert all(c.compression == "zstd" for c in summary.chunk_indexes)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        assert meta["evcal"]["sensor"] == "40x30"
        n_ev, last_log = 0, 0
        for _, channel, msg in reader.iter_messages(log_time_order=False):
            assert msg.log_time >= last_log  # written in time order across channels
            last_log = msg.log_time
            if channel.topic == "/events":
                ev, header = decode_events(msg.data)
                assert msg.log_time == msg.publish_time == int(ev["t_us"][0]) * 1000
                assert header["seq"] == msg.sequence == n_ev
                n_ev += 1
            else:
                t_us, _, _, _ = decode_frame(msg.data)
                assert msg.log_time == t_us * 1000
    assert n_ev == 5


def test_mcap_empty_recording(tmp_path: Path) -> None:
    rec = Recording(SENSOR)
    back = read_mcap(write_mcap(rec, tmp_path / "empty.mcap"))
    assert back.sensor == SENSOR
    assert back.n_events == 0
    assert len(back.frames) == 0


def test_mcap_sensor_argument_must_agree(tmp_path: Path) -> None:
    path = write_mcap(_recording(), tmp_path / "rec.mcap")
    assert read_mcap(path, sensor=SENSOR).sensor == SENSOR
    with pytest.raises(RecordingError, match=r"declares a 40x30 sensor, but sensor=50x30"):
        read_mcap(path, sensor=SensorSize(height=30, width=50))


@pytest.mark.parametrize("float_frames", [False, True])
def test_npz_round_trip(tmp_path: Path, float_frames: bool) -> None:
    rec = _recording(float_frames=float_frames)
    path = write_npz(rec, tmp_path / "rec.npz")
    back = read_npz(path)
    _same(rec, back)
    np.testing.assert_array_equal(back.frames.exposure_us, rec.frames.exposure_us)
    assert _user_metadata(back) == {"name": "synthetic", "seed": 0, "gain": 0.5}


def test_npz_columns_and_no_suffix(tmp_path: Path) -> None:
    rec = _recording(n_frames=0)
    path = tmp_path / "columns.bin"  # not renamed to .bin.npz
    with open(path, "wb") as f:
        np.savez(f, t_us=rec.events["t_us"], x=rec.events["x"].astype(np.int32),
                 y=rec.events["y"], p=(rec.events["p"] > 0).astype(np.uint8),
                 sensor=np.array([30, 40]))
    back = read_npz(path)
    _same(rec, back)


def test_ecd_round_trip(tmp_path: Path) -> None:
    rec = _recording()
    rec = Recording(rec.sensor, rec.events, rec.frames, {"calib": ECD_CALIB})
    folder = write_ecd(rec, tmp_path / "ecd")
    assert (folder / "images.txt").read_text().splitlines()[0] == \
        "1.000017000 images/frame_00000000.png"
    back = read_ecd(folder)
    _same(rec, back)
    assert back.metadata["sensor_source"] == "the frames"
    assert back.metadata["calib"] == ECD_CALIB


def test_ecd_round_trip_events_only_needs_sensor(tmp_path: Path) -> None:
    rec = _recording(n_frames=0, t0_us=0)
    folder = write_ecd(rec, tmp_path / "ecd")
    with pytest.raises(RecordingError, match="--sensor-size WxH"):
        read_ecd(folder)
    _same(rec, read_ecd(folder, sensor=SENSOR))


def test_ecd_float_frames_are_written_as_8_bit(tmp_path: Path) -> None:
    rec = _recording(float_frames=True)
    back = read_ecd(write_ecd(rec, tmp_path / "ecd"))
    assert back.frames.images.dtype == np.uint8
    np.testing.assert_array_equal(back.frames.images,
                                  np.clip(np.rint(rec.frames.images), 0, 255))


def test_format_events_txt() -> None:
    ev = make_events([13_582_596, 5, 0, 1_589_163_147_368_868, -1_500_000],
                     [190, 0, 65535, 7, 3], [82, 7, 0, 100, 4], [1, -1, 1, -1, 1])
    assert format_events_txt(ev).decode().splitlines() == [
        "13.582596000 190 82 1", "0.000005000 0 7 0", "0.000000000 65535 0 1",
        "1589163147.368868000 7 100 0", "-1.500000000 3 4 1"]
    assert format_events_txt(ev[:0]) == b""


def test_write_recording_dispatch(tmp_path: Path) -> None:
    rec = _recording()
    for name in ("a.mcap", "a.npz", "a_folder"):
        path = write_recording(rec, tmp_path / name)
        _same(rec, open_recording(path))
    with pytest.raises(RecordingError, match="cannot write a recording of kind '.aedat4'"):
        write_recording(rec, tmp_path / "a.aedat4")


def test_open_recording_errors(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="no such file or directory"):
        open_recording(tmp_path / "nothing.mcap")
    (tmp_path / "x.h5").write_bytes(b"\x00")
    with pytest.raises(RecordingError, match=r"unknown recording format .* suffix '\.h5'.* "
                                             r"evcal reads .*AEDAT4"):
        open_recording(tmp_path / "x.h5")
    (tmp_path / "old.aedat").write_bytes(b"#!AER-DAT3.0\r\n")
    with pytest.raises(RecordingError, match="another version than 2.0, 3.1 or 4.0"):
        open_recording(tmp_path / "old.aedat")
    (tmp_path / "empty").mkdir()
    with pytest.raises(RecordingError, match="no events.txt or images.txt"):
        open_recording(tmp_path / "empty")


# ----------------------------------------------------------------------------- wire


@st.composite
def event_chunks(draw: st.DrawFn) -> tuple[np.ndarray, int, int, int]:
    h = draw(st.integers(1, 65535))
    w = draw(st.integers(1, 65535))
    n = draw(st.integers(0, 200))
    t = np.sort(draw(hnp.arrays(np.int64, n, elements=st.integers(-(2**62), 2**62))))
    x = draw(hnp.arrays(np.uint16, n, elements=st.integers(0, w - 1)))
    y = draw(hnp.arrays(np.uint16, n, elements=st.integers(0, h - 1)))
    p = draw(hnp.arrays(np.int8, n, elements=st.sampled_from([-1, 1])))
    seq = draw(st.integers(0, 2**64 - 1))
    return make_events(t, x, y, p), h, w, seq


@st.composite
def frames_(draw: st.DrawFn) -> tuple[int, np.ndarray, int, int]:
    h, w = draw(st.integers(1, 24)), draw(st.integers(1, 24))
    if draw(st.booleans()):
        image = draw(hnp.arrays(np.uint8, (h, w)))
    else:
        image = draw(hnp.arrays(np.float32, (h, w),
                                elements=st.floats(-1e6, 1e6, width=32)))
    t_us = draw(st.integers(-(2**63), 2**63 - 1))
    return t_us, image, draw(st.integers(0, 2**63 - 1)), draw(st.integers(0, 2**64 - 1))


@HYP
@given(event_chunks())
def test_wire_events_round_trip(chunk: tuple[np.ndarray, int, int, int]) -> None:
    ev, h, w, seq = chunk
    out, header = decode_events(encode_events(ev, height=h, width=w, seq=seq))
    assert out.dtype == EVENTS_DTYPE
    np.testing.assert_array_equal(out, ev)
    assert header == {"version": 1, "height": h, "width": w, "seq": seq, "n": ev.shape[0]}


@HYP
@given(frames_())
def test_wire_frame_round_trip(frame: tuple[int, np.ndarray, int, int]) -> None:
    t_us, image, exposure_us, seq = frame
    t, e, out, header = decode_frame(encode_frame(t_us, image, exposure_us=exposure_us, seq=seq))
    assert (t, e) == (t_us, exposure_us)
    assert out.dtype == image.dtype
    assert out.shape == image.shape
    np.testing.assert_array_equal(out, image)
    assert header["seq"] == seq
    assert header["dtype"] == str(image.dtype)


def _decode_any(buf: bytes) -> None:
    """Decoding either fails with WireError or gives data that keeps every invariant."""
    try:
        ev, header = decode_events(buf)
    except WireError:
        pass
    else:
        validate_events(ev, SensorSize(header["height"], header["width"]))
    try:
        _, _, image, _ = decode_frame(buf)
    except WireError:
        pass
    else:
        assert image.dtype != np.float32 or np.isfinite(image).all()


@HYP
@given(st.binary(max_size=300))
def test_wire_random_bytes_raise_wire_error(buf: bytes) -> None:
    _decode_any(buf)


_VALID_EVENTS = encode_events(_recording(n=20).events, height=30, width=40, seq=3)
_VALID_FRAME = encode_frame(5, np.arange(12, dtype=np.float32).reshape(3, 4), exposure_us=2,
                            seq=1)


@HYP
@given(st.sampled_from([_VALID_EVENTS, _VALID_FRAME]), st.data())
def test_wire_mutated_bytes_raise_wire_error(valid: bytes, data: st.DataObject) -> None:
    buf = bytearray(valid)
    for _ in range(data.draw(st.integers(1, 4))):
        kind = data.draw(st.sampled_from(["flip", "cut", "insert"]))
        i = data.draw(st.integers(0, max(len(buf) - 1, 0)))
        if kind == "flip" and buf:
            buf[i] = data.draw(st.integers(0, 255))
        elif kind == "cut":
            del buf[i:]
        else:
            buf[i:i] = data.draw(st.binary(min_size=1, max_size=8))
    _decode_any(bytes(buf))


_MSGPACK_INT = st.integers(-(2**63), 2**64 - 1)  # what msgpack can hold
_ANY_VALUE = st.one_of(st.none(), st.booleans(), _MSGPACK_INT, st.floats(), st.text(max_size=5),
                       st.binary(max_size=40), st.lists(_MSGPACK_INT, max_size=3),
                       st.dictionaries(st.text(max_size=3), _MSGPACK_INT, max_size=2))


@HYP
@given(st.sampled_from([_VALID_EVENTS, _VALID_FRAME]), st.data())
def test_wire_mutated_fields_raise_wire_error(valid: bytes, data: st.DataObject) -> None:
    obj = msgpack.unpackb(valid)
    key = data.draw(st.sampled_from([*sorted(obj), "extra"]))
    if data.draw(st.booleans()) and key in obj:
        del obj[key]
    else:
        obj[key] = data.draw(_ANY_VALUE)
    _decode_any(msgpack.packb(obj, use_bin_type=True))


def _events_obj(**changes: object) -> bytes:
    obj = msgpack.unpackb(_VALID_EVENTS)
    obj.update(changes)
    return msgpack.packb(obj, use_bin_type=True)


@pytest.mark.parametrize(("changes", "message"), [
    ({"version": 2}, "unsupported version 2"),
    ({"version": True}, "unsupported version True"),
    ({"height": 70000}, r"'height' = 70000 is outside 1\.\.65535"),
    ({"width": 0}, r"'width' = 0 is outside"),
    ({"n": 21}, r"'t_us' is truncated: 160 bytes, expected 168"),
    ({"n": 19}, r"'t_us' is too long"),
    ({"x": b"\x00" * 10}, r"'x' is truncated: 10 bytes, expected 40"),
    ({"p": b"\x00" * 20}, "polarity 0, expected"),
    ({"y": np.full(20, 30, "<u2").tobytes()}, "outside the 40x30 sensor"),
    ({"t_us": np.arange(20, 0, -1, dtype="<i8").tobytes()}, "timestamps are not sorted"),
    ({"t_us": [1, 2]}, r"'t_us' must be binary"),
    ({"seq": -1}, r"'seq' = -1 is outside"),
    ({"seq": "1"}, r"'seq' must be an integer, got str"),
    ({"extra": 1}, r"unknown field\(s\) \['extra'\]"),
])
def test_wire_event_errors_name_the_problem(changes: dict, message: str) -> None:
    with pytest.raises(WireError, match=message):
        decode_events(_events_obj(**changes))


def test_wire_errors_name_the_problem() -> None:
    with pytest.raises(WireError, match="empty message"):
        decode_events(b"")
    with pytest.raises(WireError, match="expected a msgpack map, got int"):
        decode_events(msgpack.packb(3))
    with pytest.raises(WireError, match="not a valid msgpack message"):
        decode_events(_VALID_EVENTS[:-5])
    obj = msgpack.unpackb(_VALID_EVENTS)
    del obj["n"]
    with pytest.raises(WireError, match=r"missing field\(s\) \['n'\]"):
        decode_events(msgpack.packb(obj))
    obj = msgpack.unpackb(_VALID_FRAME)
    obj["data"] = np.array([np.nan] * 12, "<f4").tobytes()
    with pytest.raises(WireError, match="12 NaN or infinite values"):
        decode_frame(msgpack.packb(obj))
    obj["data"] = b"\x00" * 47
    with pytest.raises(WireError, match=r"'data' is truncated: 47 bytes, expected 48"):
        decode_frame(msgpack.packb(obj))
    obj["dtype"] = "float64"
    with pytest.raises(WireError, match="dtype 'float64' is not one of"):
        decode_frame(msgpack.packb(obj))
    with pytest.raises(WireError, match="NaN"):
        encode_frame(0, np.full((2, 2), np.nan, np.float32), exposure_us=0, seq=0)
    with pytest.raises(WireError, match="float64 is not uint8 or float32"):
        encode_frame(0, np.zeros((2, 2)), exposure_us=0, seq=0)
    with pytest.raises(WireError, match="height=70000 is outside"):
        encode_events(_recording(n=3).events, height=70000, width=40, seq=0)
    with pytest.raises(WireError, match="outside the 10x10 sensor"):
        encode_events(_recording(n=300).events, height=10, width=10, seq=0)


# ----------------------------------------------------------------------------- calibration


def _calibration(seed: int = 0) -> Calibration:
    rng = np.random.default_rng(seed)
    shape = SENSOR.shape
    valid = rng.random(shape) > 0.2
    return Calibration.uniform(shape).replace(
        contrast=rng.uniform(0.05, 0.5, shape), bias=rng.uniform(-0.02, 0.02, shape),
        valid=valid, reason=np.where(valid, 0, 2), stderr_contrast=np.where(valid, 0.01, np.inf),
        stderr_bias=rng.random(shape), special=rng.integers(0, len(Special), shape),
        n_events=rng.integers(0, 1000, shape), log_offset=0.25, method="lsq",
        diagnostics=Diagnostics(extra={"min_events": 8, "window_us": np.int64(5000)}))


def test_calibration_round_trip(tmp_path: Path) -> None:
    cal = _calibration()
    path = save_calibration(cal, tmp_path / "cal.npz")
    with np.load(path, allow_pickle=False) as z:
        assert set(z.files) == CALIBRATION_KEYS
        assert z["contrast"].dtype == np.float32
        assert z["n_events"].dtype == np.int64
    back = load_calibration(path)
    for key in ("contrast", "bias", "valid", "reason", "stderr_contrast", "stderr_bias",
                "special", "n_events"):
        a, b = getattr(cal, key), getattr(back, key)
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    assert (back.log_offset, back.method) == (0.25, "lsq")
    assert back.diagnostics.to_dict() == {"min_events": 8, "window_us": 5000}


def test_calibration_file_errors(tmp_path: Path) -> None:
    cal = _calibration()
    path = save_calibration(cal, tmp_path / "cal.npz")
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}

    def broken(**changes: object) -> Path:
        bad = {**arrays, **changes}
        out = tmp_path / "bad.npz"
        with open(out, "wb") as f:
            np.savez(f, **{k: v for k, v in bad.items() if v is not None})
        return out

    with pytest.raises(CalibrationFileError, match=r"missing array\(s\) \['bias'\]"):
        load_calibration(broken(bias=None))
    with pytest.raises(CalibrationFileError, match=r"valid map has shape \(30, 41\), contrast has"):
        load_calibration(broken(valid=np.ones((30, 41), bool)))
    with pytest.raises(CalibrationFileError, match="reason map has dtype float64"):
        load_calibration(broken(reason=np.zeros((30, 40))))
    with pytest.raises(CalibrationFileError, match="NaN"):
        load_calibration(broken(contrast=np.full((30, 40), np.nan, np.float32)))
    with pytest.raises(CalibrationFileError, match="params_json is not valid JSON"):
        load_calibration(broken(params_json=np.array("{")))
    with pytest.raises(CalibrationFileError, match="looks like a recording"):
        load_calibration(write_npz(_recording(), tmp_path / "rec.npz"))
    (tmp_path / "cut.npz").write_bytes(path.read_bytes()[:200])
    with pytest.raises(CalibrationFileError, match="truncated zip archive: it ends at byte 200"):
        load_calibration(tmp_path / "cut.npz")


def test_write_csv(tmp_path: Path) -> None:
    cal = _calibration()
    scale, bias = write_csv(cal, tmp_path / "csv")
    assert (scale.name, bias.name) == ("scale.csv", "bias.csv")
    lines = scale.read_text().splitlines()
    assert len(lines) == 30
    assert len(lines[0].split(",")) == 40
    assert lines[0].split(",")[0] == f"{cal.contrast[0, 0]:.6f}"
    np.testing.assert_allclose(np.loadtxt(bias, delimiter=","), cal.bias, atol=5e-7)


# ----------------------------------------------------------------------------- real data


@pytest.mark.parametrize("name", ["boxes_rotation", "dynamic_rotation", "poster_rotation",
                                  "shapes_rotation"])
def test_real_ecd_slices(shared_data: Path, name: str) -> None:
    rec = open_recording(shared_data / "ecd_slices" / name)
    assert rec.sensor == SensorSize(height=180, width=240)
    assert "calib.txt" in rec.metadata["sensor_source"]
    assert rec.n_events == (20_000 if name == "shapes_rotation" else 30_000)
    assert set(np.unique(rec.events["p"]).tolist()) == {-1, 1}
    assert 10_000 < rec.t_range_us[1] - rec.t_range_us[0] < 110_000


def test_real_ecd_first_events(shared_data: Path) -> None:
    rec = read_ecd(shared_data / "ecd_slices" / "boxes_rotation")
    # "13.582595999 190 82 1" rounds to 13582596 µs
    assert rec.events[0].tolist() == (13_582_596, 190, 82, 1)


def test_real_slider_depth_frames(shared_data: Path) -> None:
    rec = open_recording(shared_data / "ecd_slider_depth_frames")
    assert rec.sensor == SensorSize(height=180, width=240)
    assert len(rec.frames) == 87
    assert rec.frames.images.dtype == np.uint8
    assert rec.n_events == 0
    assert rec.frames.t_us[1] == 38_766
    assert 3.3 < rec.duration_s < 3.4


def test_real_aedat4(shared_data: Path, tmp_path: Path) -> None:
    path = shared_data / "davis346_road" / "road.aedat4"
    rec = open_recording(path)
    assert rec.sensor == SensorSize(height=260, width=346)
    assert rec.n_events == 78_830
    assert len(rec.frames) == 59
    assert rec.frames.shape == (260, 346)
    assert (rec.frames.exposure_us == 500).all()
    assert rec.frames.t_us[0] == (1589163147364965 + 1589163147365465) // 2
    assert rec.metadata["reordered_events"] == 0
    assert 2.3 < (rec.events["t_us"][-1] - rec.events["t_us"][0]) * 1e-6 < 2.4
    # absolute µs times survive the text format, frames survive PNG
    _same(rec, read_ecd(write_ecd(rec, tmp_path / "road")))
    _same(rec, read_mcap(write_mcap(rec, tmp_path / "road.mcap")))


def test_real_aedat4_damaged(shared_data: Path, tmp_path: Path) -> None:
    data = (shared_data / "davis346_road" / "road.aedat4").read_bytes()
    (tmp_path / "cut.aedat4").write_bytes(data[: len(data) // 2])
    with pytest.raises(TruncatedRecordingError, match=r"cut\.aedat4: truncated file: .* inside "
                                                      r"packet 350 "):
        read_aedat4(tmp_path / "cut.aedat4", strict=True)
    (tmp_path / "head.aedat4").write_bytes(data[:100])
    with pytest.raises(EmptyRecordingError, match="head.aedat4: truncated inside its header"):
        read_aedat4(tmp_path / "head.aedat4")
    bad = bytearray(data)
    bad[3126:3130] = (99).to_bytes(4, "little")  # packet 0, whole, of a stream that is not
    (tmp_path / "bad.aedat4").write_bytes(bytes(bad))
    with pytest.raises(RecordingError, match=r"decoding failed after 0 packets \(corrupt "
                                             r"packet 0\?\): unknown stream id"):
        read_aedat4(tmp_path / "bad.aedat4")
    (tmp_path / "junk.aedat4").write_bytes(b"not an aedat file at all")
    with pytest.raises(RecordingError, match="wrong magic number"):
        read_aedat4(tmp_path / "junk.aedat4")
    with pytest.raises(RecordingError, match="declares a 346x260 sensor, but sensor=240x180"):
        read_aedat4(shared_data / "davis346_road" / "road.aedat4",
                    sensor=SensorSize(height=180, width=240))


def test_real_ros2_mcap_is_not_read_as_evcal_mcap(shared_data: Path) -> None:
    """open_recording reads it as a ROS 2 bag (tests/test_io_ros.py); evcal's own MCAP reader
    refuses it clearly."""
    path = shared_data / "ros2_event_packet_mcap" / "test_events_2_0.mcap"
    with pytest.raises(RecordingError, match="not an evcal recording"):
        read_mcap(path)


def test_aedat4_out_of_order_packets_are_sorted() -> None:
    dt = np.dtype([("t", "<u8"), ("x", "<u2"), ("y", "<u2"), (("p", "on"), "?")])
    a = np.array([(10, 1, 1, True), (20, 2, 2, False), (30, 3, 3, True)], dt)
    b = np.array([(25, 4, 4, True), (30, 5, 5, False), (40, 6, 6, True)], dt)
    events, reordered = events_from_packets([a, b])
    assert reordered == 1  # only t=25 is earlier than an event before it
    assert events["t_us"].tolist() == [10, 20, 25, 30, 30, 40]
    assert events["x"].tolist() == [1, 2, 4, 3, 5, 6]  # stable: equal times keep file order
    assert events["p"].tolist() == [1, -1, 1, 1, -1, 1]
    assert events_from_packets([a])[1] == 0
    assert events_from_packets([])[0].dtype == EVENTS_DTYPE


def test_sensor_from_calib() -> None:
    assert sensor_from_calib(ECD_CALIB) == SensorSize(height=180, width=240)
    assert sensor_from_calib([300, 300, 173.0, 130.0]) == SensorSize(height=260, width=346)
    assert sensor_from_calib([300, 300, 640.0, 360.0]) == SensorSize(height=720, width=1280)
    assert sensor_from_calib([300, 300, 20.0, 20.0]) is None


# ----------------------------------------------------------------------------- bad inputs


def _ecd(tmp_path: Path, lines: list[str], *, newline_at_end: bool = True,
         calib: bool = True) -> Path:
    folder = tmp_path / "ecd"
    folder.mkdir(exist_ok=True)
    text = "\n".join(lines) + ("\n" if newline_at_end else "")
    (folder / "events.txt").write_text(text)
    if calib:
        (folder / "calib.txt").write_text(" ".join(map(str, ECD_CALIB)) + "\n")
    return folder


_GOOD = ["0.000001000 1 2 1", "0.000002000 3 4 0", "0.000003000 5 6 1", "0.000004000 7 8 0"]


@pytest.mark.parametrize(("lines", "message"), [
    ([*_GOOD[:2], "0.000003000 5 6 1 9", _GOOD[3]],
     r"line 3: 5 columns, expected 4 \(t\[s\] x y p\)"),
    (["0.000003000 5 6", *_GOOD], r"line 1: 3 columns, expected 4"),
    ([*_GOOD[:2], "0.000003000 five 6 1"], r"line 3: column x is not a number: 'five'"),
    ([*_GOOD[:3], "0.000002500 7 8 0"], r"line 4: timestamps are not sorted: "
                                        r"t=0\.000002500 s comes after t=0\.000003000 s"),
    ([*_GOOD[:2], "0.000003000 240 6 1"], r"line 3: event at \(x=240, y=6\) is outside the "
                                          r"240x180 sensor"),
    ([*_GOOD[:2], "0.000003000 5 180 1"], r"line 3: event at \(x=5, y=180\) is outside"),
    ([*_GOOD[:2], "0.000003000 5 6 2"], r"line 3: polarity p=2, expected 0 or 1"),
    ([*_GOOD[:2], "0.000003000 5 6 -1"], r"line 3: polarity p=-1, expected 0 or 1"),
    ([*_GOOD[:2], "0.000003000 5.5 6 1"], r"line 3: x=5.5 is not a pixel coordinate"),
    (["", _GOOD[0], "", "0.000003000 -5 6 1"], r"line 4: x=-5 is not a pixel coordinate"),
    ([*_GOOD[:2], "0.000003000 nan 6 1"], r"line 3: non-finite value"),
])
def test_ecd_bad_events(tmp_path: Path, lines: list[str], message: str) -> None:
    with pytest.raises(RecordingError, match=message):
        read_ecd(_ecd(tmp_path, lines))


def test_ecd_truncated_file(tmp_path: Path) -> None:
    folder = _ecd(tmp_path, [*_GOOD, "0.000005000 1"], newline_at_end=False)
    with pytest.warns(TruncatedRecordingWarning, match=r"inside line 5 \('0.000005000 1'"):
        rec = read_ecd(folder)
    assert rec.n_events == 4
    with pytest.raises(TruncatedRecordingError, match="line 5"):
        read_ecd(folder, strict=True)
    # a malformed last line with all its columns is not a cut
    (tmp_path / "bad").mkdir()
    folder = _ecd(tmp_path / "bad", [*_GOOD, "0.000005000 1 x 1"], newline_at_end=False)
    with pytest.raises(RecordingError, match=r"line 5: column y is not a number"):
        read_ecd(folder)


def test_ecd_errors_in_later_blocks_name_the_right_line(tmp_path: Path) -> None:
    from evcal.io.ecd import read_events_txt

    n = 3000
    lines = [f"{k * 1e-6:.9f} {k % 240} {k % 180} {k % 2}" for k in range(n)]
    lines[2500] = "0.000000001 1 1 1"
    path = _ecd(tmp_path, lines) / "events.txt"
    with pytest.raises(RecordingError, match=r"line 2501: timestamps are not sorted"):
        read_events_txt(path, SensorSize(180, 240), block_bytes=4096)
    lines[2500] = "0.002500000 1 1 1"
    lines[1999] = "0.001999000 1 1"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(RecordingError, match=r"line 2000: 3 columns"):
        read_events_txt(path, SensorSize(180, 240), block_bytes=4096)
    lines[1999] = "0.001999000 1 1 1"
    path.write_text("\n".join(lines) + "\n")
    ev = read_events_txt(path, SensorSize(180, 240), block_bytes=4096)
    assert ev.shape == (n,)
    assert ev["t_us"].tolist() == list(range(n))


def test_ecd_sensor_unknown(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match=r"cannot tell the sensor size.*--sensor-size WxH"):
        read_ecd(_ecd(tmp_path, _GOOD, calib=False))


def _ecd_with_frames(tmp_path: Path, shapes: list[tuple[int, int]]) -> Path:
    folder = _ecd(tmp_path, _GOOD, calib=False)
    (folder / "images").mkdir()
    rows = []
    for k, shape in enumerate(shapes):
        Image.fromarray(np.full(shape, 9 * k, np.uint8)).save(folder / f"images/f{k}.png")
        rows.append(f"{k * 0.04:.9f} images/f{k}.png")
    (folder / "images.txt").write_text("\n".join(rows) + "\n")
    return folder


def test_ecd_frames(tmp_path: Path) -> None:
    rec = read_ecd(_ecd_with_frames(tmp_path, [(30, 40)] * 3))
    assert rec.sensor == SENSOR
    assert len(rec.frames) == 3
    assert rec.frames.t_us.tolist() == [0, 40_000, 80_000]


def test_ecd_frame_of_wrong_size(tmp_path: Path) -> None:
    folder = _ecd_with_frames(tmp_path, [(30, 40), (30, 40), (31, 40)])
    with pytest.raises(RecordingError, match=r"frame 2 \(images/f2\.png, images\.txt line 3\) "
                                             r"has shape \(31, 40\) \(a 40x31 image\), frame 0 "
                                             r"\(images/f0\.png\) is 40x30"):
        read_ecd(folder)
    with pytest.raises(RecordingError, match=r"frame 0 .* has shape \(30, 40\) .*the sensor is "
                                             r"50x30"):
        read_ecd(folder, sensor=SensorSize(height=30, width=50))


def test_ecd_missing_png(tmp_path: Path) -> None:
    folder = _ecd_with_frames(tmp_path, [(30, 40)] * 3)
    (folder / "images" / "f1.png").unlink()
    with pytest.raises(RecordingError, match=r"images\.txt line 2: frame file 'images/f1\.png' "
                                             r"is missing"):
        read_ecd(folder)


def test_mcap_truncated_and_corrupt(tmp_path: Path) -> None:
    path = write_mcap(_recording(), tmp_path / "rec.mcap", chunk_events=500)
    data = path.read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) // 2])
    # one zstd chunk (one block): nothing of it decompresses
    with pytest.raises(EmptyRecordingError, match=r"cut\.mcap: truncated before its first whole "
                                                  r"record: .* inside a chunk record"):
        read_mcap(tmp_path / "cut.mcap")
    bad = bytearray(data)
    bad[len(bad) // 3 : len(bad) // 3 + 64] = bytes(64)
    (tmp_path / "bad.mcap").write_bytes(bytes(bad))
    with pytest.raises(RecordingError, match=r"bad\.mcap: cannot read as MCAP"):
        read_mcap(tmp_path / "bad.mcap")
    (tmp_path / "junk.mcap").write_bytes(b"junk" * 10)
    with pytest.raises(RecordingError, match="not an MCAP file"):
        read_mcap(tmp_path / "junk.mcap")


def test_mcap_bad_message_is_named(tmp_path: Path) -> None:
    from mcap.writer import Writer

    path = tmp_path / "bad.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        ch = w.register_channel("/events", "msgpack", 0)
        w.add_message(ch, log_time=0, publish_time=0, data=_events_obj(p=b"\x02" * 20))
        w.finish()
    with pytest.raises(RecordingError, match=r"events message seq 3: event 0 has polarity 2"):
        read_mcap(path)


def test_npz_bad_inputs(tmp_path: Path) -> None:
    path = write_npz(_recording(), tmp_path / "rec.npz")
    (tmp_path / "cut.npz").write_bytes(path.read_bytes()[:500])
    with pytest.raises(RecordingError, match=r"cut\.npz: truncated zip archive"):
        read_npz(tmp_path / "cut.npz")
    rec = _recording()
    with open(tmp_path / "p2.npz", "wb") as f:
        np.savez(f, t_us=rec.events["t_us"], x=rec.events["x"], y=rec.events["y"],
                 p=np.full(rec.n_events, 2), sensor=np.array([30, 40]))
    with pytest.raises(RecordingError, match=r"polarity values \[2\]"):
        read_npz(tmp_path / "p2.npz")
    with open(tmp_path / "nosensor.npz", "wb") as f:
        np.savez(f, events=rec.events)
    with pytest.raises(RecordingError, match="no 'sensor' array"):
        read_npz(tmp_path / "nosensor.npz")
    with open(tmp_path / "outside.npz", "wb") as f:
        np.savez(f, events=rec.events, sensor=np.array([30, 20]))
    with pytest.raises(RecordingError, match="outside the 20x30 sensor"):
        read_npz(tmp_path / "outside.npz")


def test_recordings_are_recognised_by_content(tmp_path: Path) -> None:
    rec = _recording()
    for suffix in (".mcap", ".npz"):
        path = write_recording(rec, tmp_path / f"r{suffix}")
        misnamed = path.rename(tmp_path / f"r{suffix}.bin")  # a name that says nothing
        back = open_recording(misnamed)
        assert back.n_events == rec.n_events
        upper = misnamed.rename(tmp_path / f"R{suffix.upper()}")  # or shouts its suffix
        assert open_recording(upper).n_events == rec.n_events


def test_a_misnamed_real_aedat4_opens(shared_data: Path, tmp_path: Path) -> None:
    road = shared_data / "davis346_road" / "road.aedat4"
    (tmp_path / "road.AEDAT").write_bytes(road.read_bytes())
    assert open_recording(tmp_path / "road.AEDAT").sensor.width == 346
