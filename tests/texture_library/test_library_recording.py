"""Sensor channels (units, shapes, rates) and the recording .npz file."""

from __future__ import annotations

import json

import numpy as np
import pytest

from texture_library.channels import check_channel
from texture_library.recording import Recording, load_recording, make_channel, recording_from_stroke, save_recording


@pytest.mark.parametrize(
    "kind, units, factor",
    [
        ("accel", "g", 9.80665),
        ("accel", "m/s^2", 1.0),
        ("speed", "m/s", 1000.0),
        ("speed", "mm/s", 1.0),
        ("position", "m", 1000.0),
        ("force", "N", 1.0),
    ],
)
def test_units_are_converted_to_canonical(kind, units, factor):
    # within every channel's physical bounds once converted (a speed of 3 m/s would be refused: at most 2000 mm/s)
    data = np.arange(12.0).reshape(4, 3) if kind == "accel" else np.arange(4.0) / 2
    ch = make_channel(kind, data, 500.0, units)
    np.testing.assert_allclose(ch.data, data * factor)
    assert ch.rate_hz == 500.0 and ch.duration_s == pytest.approx(4 / 500)


def test_units_default_to_canonical_and_columns_of_one_are_squeezed():
    ch = make_channel("force", np.ones((10, 1)), 100)
    assert ch.data.shape == (10,) and ch.data.dtype == np.float64
    assert make_channel("position", np.ones((10, 2)), 100).data.shape == (10, 2)
    assert make_channel("force", np.ones((10, 3), dtype=np.int16), 100).data.dtype == np.float64


@pytest.mark.parametrize(
    "kind, data, rate, units, message",
    [
        (
            "pressure",
            np.zeros(5),
            100,
            None,
            r"unknown channel 'pressure'; expected one of \['accel', 'force', 'speed', 'position'\]",
        ),
        ("accel", np.zeros((5, 3)), 100, "ft/s^2", r"accel: units must be one of \['m/s\^2', 'g'\], got 'ft/s\^2'"),
        ("speed", np.zeros(5), 100, "km/h", r"speed: units must be one of \['mm/s', 'm/s'\]"),
        ("force", np.zeros(5), "100", None, r"force: sample rate must be a finite number, got '100'"),
        ("force", np.zeros(5), None, None, r"force: sample rate must be a finite number, got None"),
        ("force", np.zeros(5), True, None, r"force: sample rate must be a finite number, got True"),
        ("force", np.zeros(5), float("nan"), None, r"force: sample rate must be a finite number"),
        ("force", np.zeros(5), 0, None, r"force: sample rate must lie in \[10, 100000\] Hz, got 0"),
        ("force", np.zeros(5), -5.0, None, r"force: sample rate must lie in \[10, 100000\] Hz, got -5"),
        ("force", np.zeros(5), 1e9, None, r"force: sample rate must lie in \[10, 100000\] Hz, got 1e\+09"),
        ("accel", np.array(["a", "b"]), 100, None, r"accel: samples must be numbers, got dtype <U1"),
        ("accel", np.ones((5, 3), dtype=bool), 100, None, r"accel: samples must be numbers, got dtype bool"),
        ("accel", np.zeros((5, 2)), 100, None, r"accel: shape must be \(n, 3\), got \(5, 2\)"),
        ("accel", np.zeros(5), 100, None, r"accel: shape must be \(n, 3\), got \(5,\)"),
        ("force", np.zeros((5, 2)), 100, None, r"force: shape must be \(n,\) or \(n, 3\), got \(5, 2\)"),
        ("speed", np.zeros((5, 3)), 100, None, r"speed: shape must be \(n,\), got \(5, 3\)"),
        ("position", np.zeros((5, 2, 1)), 100, None, r"position: shape must be \(n,\) or \(n, 2\), got \(5, 2, 1\)"),
        ("force", np.zeros(()), 100, None, r"force: shape must be"),
        ("force", np.zeros(0), 100, None, r"force: no samples"),
        ("accel", np.array([[0, 0, np.nan], [np.inf, 0, 0]]), 100, None, r"accel: 2 sample\(s\) are NaN or Inf"),
    ],
)
def test_check_channel_names_every_problem(kind, data, rate, units, message):
    with pytest.raises(ValueError, match=message):
        check_channel(kind, data, rate, units)


def _recording(n=2000, rate=1000.0, seed=0, **extra) -> Recording:
    rng = np.random.default_rng(seed)
    return Recording(
        accel=make_channel("accel", rng.standard_normal((n, 3)), rate),
        force=make_channel("force", 1 + rng.random((n // 2, 3)), rate / 2),
        **extra,
    )


def test_a_recording_needs_a_motion_channel():
    with pytest.raises(ValueError, match="recording needs a speed or a position channel"):
        _recording()


@pytest.mark.parametrize("motion", ["speed", "position"])
def test_save_load_round_trip_keeps_channels_rates_and_values(tmp_path, motion):
    channel = (
        make_channel("speed", np.linspace(0.0, 100.0, 250), 125.0)
        if motion == "speed"
        else make_channel("position", np.linspace(0.0, 0.1, 500).repeat(2).reshape(-1, 2), 250.0, "m")
    )
    rec = _recording(**{motion: channel})
    loaded = load_recording(save_recording(tmp_path / "r.npz", rec))
    assert set(loaded.channels()) == {"accel", "force", motion}
    for kind, ch in rec.channels().items():
        got = loaded.channels()[kind]
        assert got.rate_hz == ch.rate_hz and got.data.shape == ch.data.shape
        np.testing.assert_allclose(got.data, ch.data, rtol=1e-6)  # stored as float32
    assert loaded.duration_s == pytest.approx(2.0)
    with np.load(tmp_path / "r.npz") as z:
        header = json.loads(str(z["header"]))
    assert header["format"] == "hapticlink-recording" and header["version"] == 1
    assert header["channels"]["accel"] == {"rate_hz": 1000.0, "units": "m/s^2"}


def test_recording_from_stroke_and_crop():
    rec = recording_from_stroke(np.zeros((3000, 3)), np.ones((3000, 3)), np.full(3000, 50.0), 1000.0)
    assert rec.duration_s == pytest.approx(3.0)
    mixed = _recording(n=3000, speed=make_channel("speed", np.arange(300.0), 100.0))
    cut = mixed.crop(0.5, 2.5)
    assert cut.accel.data.shape[0] == 2000 and cut.force.data.shape[0] == 1000 and cut.speed.data.shape[0] == 200
    np.testing.assert_array_equal(cut.speed.data, np.arange(50.0, 250.0))
    with pytest.raises(ValueError, match="crop needs 0 ≤ start < stop"):
        mixed.crop(2.0, 1.0)


def _write(path, header, **arrays):
    np.savez(path, header=np.array(json.dumps(header) if not isinstance(header, str) else header), **arrays)
    return path


GOOD = {
    "format": "hapticlink-recording",
    "version": 1,
    "channels": {
        "accel": {"rate_hz": 1000.0, "units": "m/s^2"},
        "force": {"rate_hz": 1000.0, "units": "N"},
        "speed": {"rate_hz": 1000.0, "units": "mm/s"},
    },
}
ARRAYS = {"accel": np.zeros((600, 3)), "force": np.ones(600), "speed": np.ones(600)}


@pytest.mark.parametrize(
    "header, arrays, message",
    [
        ({**GOOD, "version": 2}, ARRAYS, r"unsupported hapticlink-recording version 2"),
        ({**GOOD, "format": "wav"}, ARRAYS, r"format is 'wav'"),
        ("{not json", ARRAYS, "header is not valid JSON"),
        ("[1, 2]", ARRAYS, "header must be a JSON object"),
        ({**GOOD, "channels": ["accel"]}, ARRAYS, "header 'channels' must map each channel"),
        (
            {**GOOD, "channels": {**GOOD["channels"], "temperature": {"rate_hz": 10}}},
            ARRAYS,
            "unknown channel 'temperature'",
        ),
        (
            GOOD,
            {k: v for k, v in ARRAYS.items() if k != "force"},
            "header lists channel 'force' but the array is missing",
        ),
        (
            {**GOOD, "channels": {k: v for k, v in GOOD["channels"].items() if k != "accel"}},
            ARRAYS,
            "missing channel 'accel'",
        ),
        (
            {**GOOD, "channels": {k: v for k, v in GOOD["channels"].items() if k != "speed"}},
            ARRAYS,
            "recording needs a speed or a position channel",
        ),
        (
            {**GOOD, "channels": {**GOOD["channels"], "speed": {"rate_hz": 0}}},
            ARRAYS,
            r"speed: sample rate must lie in",
        ),
        (
            {**GOOD, "channels": {**GOOD["channels"], "accel": {"rate_hz": 1000.0, "units": "g"}}},
            {**ARRAYS, "accel": np.zeros((600, 2))},
            r"accel: shape must be \(n, 3\), got \(600, 2\)",
        ),
        (GOOD, {**ARRAYS, "force": np.full(600, np.nan)}, r"force: 600 sample\(s\) are NaN or Inf"),
    ],
)
def test_load_recording_names_the_file_and_the_fault(tmp_path, header, arrays, message):
    path = _write(tmp_path / "r.npz", header, **arrays)
    with pytest.raises(ValueError, match=message) as err:
        load_recording(path)
    assert str(path) in str(err.value)


def test_load_recording_of_a_missing_or_foreign_file(tmp_path):
    with pytest.raises(ValueError, match="hapticlink-recording file not found"):
        load_recording(tmp_path / "absent.npz")
    (tmp_path / "text.npz").write_text("hello")
    with pytest.raises(ValueError, match="not a readable .npz file"):
        load_recording(tmp_path / "text.npz")
    np.savez(tmp_path / "plain.npz", accel=np.zeros((5, 3)))
    with pytest.raises(ValueError, match=r"no header \(not a hapticlink-recording file\)"):
        load_recording(tmp_path / "plain.npz")


def test_a_file_that_inflates_past_the_limit_is_refused_before_it_is_read(tmp_path, monkeypatch):
    """A 0.55 MB recording of zeros declared 480 MB a channel; loading it took 1.96 GB. The declared sizes are read
    first (here against a limit of 1 MiB, so the test writes little)."""
    import texture_library.npzfile as npzfile

    rec = Recording(
        accel=make_channel("accel", np.zeros((60_000, 3)), 1000.0),  # 1.4 MB of float64 once decompressed
        force=make_channel("force", np.zeros(60_000), 1000.0),
        speed=make_channel("speed", np.zeros(60_000), 1000.0),
    )
    path = save_recording(tmp_path / "zeros.npz", rec)  # saved as float32: 1.2 MB
    assert path.stat().st_size < 100_000
    monkeypatch.setattr(npzfile, "MAX_NPZ_BYTES", 1 << 20)  # after saving, which checks the same limit
    with pytest.raises(
        ValueError, match=r"zeros.npz: holds [\d,]+ bytes \(1\.1 MiB\) once decompressed; at most 1,048,576 bytes"
    ):
        load_recording(path)


def test_units_in_the_file_are_converted_on_load(tmp_path):
    header = {
        **GOOD,
        "channels": {
            **GOOD["channels"],
            "accel": {"rate_hz": 1000.0, "units": "g"},
            "speed": {"rate_hz": 1000.0, "units": "m/s"},
        },
    }
    rec = load_recording(_write(tmp_path / "r.npz", header, **{**ARRAYS, "accel": np.ones((600, 3))}))
    np.testing.assert_allclose(rec.accel.data, 9.80665)
    np.testing.assert_allclose(rec.speed.data, 1000.0)
