import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models.tactile.config import TactileConfig
from models.tactile.preprocess import TactilePreprocessor
from texture_library.recording import Channel


def chunks_of(channel: Channel, sizes: list[int]):
    """Split a channel into consecutive blocks whose sizes cycle through ``sizes``."""
    out, i, k = [], 0, 0
    while i < channel.data.shape[0]:
        n = sizes[k % len(sizes)]
        out.append(Channel(channel.data[i : i + n], channel.rate_hz))
        i, k = i + n, k + 1
    return out


def stream(rec, sizes: dict[str, list[int]], config=None, skip_s=0.0):
    """Push a recording block by block, interleaving channels, collecting windows as they appear."""
    pre = TactilePreprocessor(config, skip_s=skip_s)
    blocks = {name: chunks_of(ch, sizes[name]) for name, ch in rec.channels().items()}
    windows = []
    for step in range(max(len(b) for b in blocks.values())):
        pre.push(**{name: b[step] for name, b in blocks.items() if step < len(b)})
        windows += list(pre.windows())
    pre.flush()
    return windows + list(pre.windows()), pre


def one_block(rec, config=None, skip_s=0.0):
    pre = TactilePreprocessor(config, skip_s=skip_s, max_buffer_s=None)
    pre.push(**rec.channels())
    pre.flush()
    return pre.take()


@settings(max_examples=20, deadline=None)
@given(
    rates=st.sampled_from([(1000.0, 1000.0, 1000.0), (3000.0, 500.0, 200.0), (2000.0, 1250.0, 1000.0)]),
    motion=st.sampled_from(["speed", "position"]),
    force_axes=st.sampled_from([1, 3]),
    sizes=st.fixed_dictionaries(
        {k: st.lists(st.integers(1, 900), min_size=1, max_size=5) for k in ("accel", "force", "speed", "position")}
    ),
)
def test_streaming_in_any_blocks_equals_one_block(rates, motion, force_axes, sizes, make_recording):
    rec = make_recording(2.2, *rates, force_axes=force_axes, motion=motion, seed=1)
    windows, _ = stream(rec, sizes)
    batch = one_block(rec)
    assert len(windows) == len(batch) == 4
    for w in windows:
        assert w.accel.shape == (500, 3) and w.speed.shape == w.force.shape == (500,)
        np.testing.assert_allclose(w.accel, batch.accel[w.index], rtol=0, atol=1e-9)
        np.testing.assert_allclose(w.speed, batch.speed[w.index], rtol=0, atol=1e-9)
        np.testing.assert_allclose(w.force, batch.force[w.index], rtol=0, atol=1e-9)
        assert w.t_start_s == batch.t_start_s[w.index] == w.index * 0.5


@pytest.mark.parametrize("duration", [3.0, 3.3, 3.49, 3.5])
@pytest.mark.parametrize("rates", [(1000.0, 1000.0, 1000.0), (10000.0, 500.0, 200.0), (2500.0, 3000.0, 333.0)])
def test_window_count_covers_the_duration(duration, rates, make_recording):
    rec = make_recording(duration, *rates)
    expected = math.floor((rec.duration_s - 0.5) / 0.5 + 1e-9) + 1
    assert len(one_block(rec)) == expected


def test_overlapping_windows_and_skip(make_recording):
    config = TactileConfig(hop_s=0.25)
    rec = make_recording(3.0)
    batch = one_block(rec, config, skip_s=1.0)
    assert len(batch) == math.floor((3.0 - 1.0 - 0.5) / 0.25) + 1
    np.testing.assert_allclose(batch.t_start_s, 1.0 + 0.25 * np.arange(len(batch)))
    full = one_block(rec, config)
    np.testing.assert_array_equal(batch.accel[0], full.accel[4])  # filters ran through the skipped part


def test_signal_conditioning(make_recording):
    rec = make_recording(3.0, force_axes=3, motion="position", seed=2)
    batch = one_block(rec)
    accel = batch.accel[1:]  # after the first window the filters are settled
    assert np.abs(accel[..., 2].mean()) < 0.05  # gravity removed by the high-pass
    tone_rms = np.sqrt(np.mean(accel[..., 0] ** 2))
    assert tone_rms == pytest.approx(np.sqrt(2.0**2 / 2 + 0.3**2), rel=0.05)  # 150 Hz tone + noise kept
    np.testing.assert_allclose(batch.speed[1:], 80.0, rtol=1e-6)  # |Δ(0.6, 0.8)·80 mm/s·t|·rate
    assert batch.force.mean() == pytest.approx(1.5, abs=0.05)  # normal = column 2, tangential ignored
    assert batch.force.std() < 0.2  # 25 Hz low-pass left the 1 Hz swing, dropped most noise


def test_buffers_stay_bounded(make_recording):
    rec = make_recording(12.0)
    pre = TactilePreprocessor()
    peak = 0
    for step in range(0, 12000, 100):
        pre.push(**{n: Channel(c.data[step : step + 100], c.rate_hz) for n, c in rec.channels().items()})
        for _ in pre.windows():
            pass
        peak = max(peak, pre.buffered_samples)
    assert peak <= 500 + 100


def test_missing_channel_hits_the_buffer_bound():
    pre = TactilePreprocessor(max_buffer_s=2.0)
    with pytest.raises(ValueError, match="speed, force lag"):
        for _ in range(30):
            pre.push(accel=Channel(np.zeros((100, 3)), 1000.0))


def test_speed_beats_position_and_position_then_speed_fails(make_recording):
    rec_s = make_recording(1.0)
    rec_p = make_recording(1.0, motion="position")
    pre = TactilePreprocessor()
    pre.push(accel=rec_s.accel, force=rec_s.force, speed=rec_s.speed, position=rec_p.position)
    assert pre.speed_source == "speed"
    pre = TactilePreprocessor()
    pre.push(position=rec_p.position)
    with pytest.raises(ValueError, match="speed"):
        pre.push(speed=rec_s.speed)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"accel": Channel(np.zeros((10, 2)), 1000.0)}, r"accel: shape must be \(n, 3\)"),
        ({"force": Channel(np.zeros((10, 2)), 1000.0)}, r"force: shape must be \(n,\) or \(n, 3\)"),
        ({"speed": Channel(np.array([1.0, np.nan]), 1000.0)}, "speed: 1 sample"),
        ({"position": Channel(np.array([1.0, np.inf]), 1000.0)}, "position: 1 sample"),
        ({"accel": Channel(np.zeros((10, 3)), 0.0)}, r"accel: sample rate must lie in \[10, 100000\] Hz, got 0"),
        ({"accel": Channel(np.zeros((10, 3)), -1000.0)}, r"accel: sample rate must lie in .* got -1000"),
        ({"accel": Channel(np.zeros((10, 3)), 1e12)}, r"accel: sample rate must lie in \[10, 100000\] Hz, got 1e\+12"),
        ({"accel": Channel(np.zeros((10, 3)), float("nan"))}, "accel: sample rate must be a finite number, got nan"),
        ({"accel": np.zeros((10, 3))}, "accel must be a texture_library.recording.Channel"),
        ({"force": Channel(np.array(["a", "b"]), 1000.0)}, "force: samples must be numbers"),
    ],
)
def test_bad_blocks(kwargs, message):
    with pytest.raises(ValueError, match=message):
        TactilePreprocessor().push(**kwargs)


def test_rate_and_columns_are_fixed_by_the_first_block():
    pre = TactilePreprocessor()
    pre.push(accel=Channel(np.zeros((10, 3)), 1000.0), force=Channel(np.zeros(10), 1000.0))
    with pytest.raises(ValueError, match="accel: rate changed from 1000 Hz to 2000 Hz"):
        pre.push(accel=Channel(np.zeros((10, 3)), 2000.0))
    with pytest.raises(ValueError, match="force: column count changed"):
        pre.push(force=Channel(np.zeros((10, 3)), 1000.0))
    pre.flush()
    with pytest.raises(ValueError, match="flushed"):
        pre.push(force=Channel(np.zeros(10), 1000.0))


def test_bad_constructor_arguments():
    with pytest.raises(ValueError, match="skip_s"):
        TactilePreprocessor(skip_s=-1.0)
    with pytest.raises(ValueError, match="max_buffer_s"):
        TactilePreprocessor(max_buffer_s=0.1)
    with pytest.raises(ValueError, match="no complete window"):
        TactilePreprocessor().take_one()
