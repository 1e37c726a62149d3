"""Known-answer tests of the touch faults."""

import numpy as np
import pytest

from models.offline.faults import touch
from texture_library.trajectory import freehand

RATE = 1000.0


def tone(f_hz: float, seconds: float = 4.0, amp: float = 2.0) -> np.ndarray:
    t = np.arange(int(seconds * RATE)) / RATE
    return amp * np.sin(2 * np.pi * f_hz * t)


def peak_hz(x: np.ndarray) -> float:
    spec = np.abs(np.fft.rfft(x * np.hanning(len(x))))
    return float(np.fft.rfftfreq(len(x), 1 / RATE)[np.argmax(spec)])


@pytest.mark.parametrize("snr_db", [40.0, 20.0, 0.0])
def test_noise_has_the_power_the_snr_asks_for(snr_db):
    rng = np.random.default_rng(0)
    accel = np.stack([tone(80), tone(130, amp=1.0), np.full(4000, 9.81)], axis=1)  # gravity is not signal
    noisy = touch.add_noise(accel, snr_db, rng)
    noise_power = np.mean((noisy - accel) ** 2)
    signal_power = np.mean((accel - accel.mean(axis=0)) ** 2)
    assert 10 * np.log10(signal_power / noise_power) == pytest.approx(snr_db, abs=0.1)


@pytest.mark.parametrize("fraction", [0.5, 0.25, 0.1])
def test_clipping_keeps_exactly_that_fraction_of_the_range(fraction):
    x = np.stack([tone(50), 3 + tone(70, amp=0.5)], axis=1)
    out = touch.clip_range(x, fraction)
    np.testing.assert_allclose(np.ptp(out, axis=0), fraction * np.ptp(x, axis=0), rtol=1e-12)
    # samples inside the band are untouched, centred on the mid-range
    inside = np.abs(x - (x.max(0) + x.min(0)) / 2) <= fraction * np.ptp(x, axis=0) / 2
    np.testing.assert_array_equal(out[inside], x[inside])
    np.testing.assert_array_equal(touch.clip_range(x, 1.0), x)


def test_a_100_ms_gap_removes_100_ms():
    x = np.arange(3000.0)
    mask = touch.periodic_segments(3000, RATE, 0.1, 1.0)
    out = touch.remove_gaps(x, mask)
    assert len(x) - len(out) == 3 * 100  # one 100 ms gap per second of a 3 s signal
    # the first gap is samples 0–99; the stream closes up over each lost 100 samples
    assert out[0] == 100 and out[899] == 999 and out[900] == 1100


def test_dropout_holds_the_last_good_sample_for_its_duration():
    x = np.arange(2500.0)
    mask = touch.periodic_segments(2500, RATE, 0.05, 1.0, offset_s=0.2)
    out = touch.dropout_hold(x, mask)
    assert out.shape == x.shape
    assert np.all(out[200:250] == 199) and out[250] == 250 and np.all(out[1200:1250] == 1199)
    assert int(np.count_nonzero(out != x)) == 2 * 50 + 50  # 3 dropouts of 50 samples (the third starts at 2200)
    np.testing.assert_array_equal(touch.dropout_hold(x, np.r_[np.ones(5, bool), np.zeros(2495, bool)])[:5], 5.0)


@pytest.mark.parametrize("error", [0.05, -0.1, 0.2])
def test_rate_mismatch_moves_a_tone_by_the_clock_error(error):
    x = tone(100.0, seconds=8.0)
    out = touch.rate_mismatch(x, error)
    assert len(out) == pytest.approx(len(x) * (1 + error), abs=1)
    assert peak_hz(out) == pytest.approx(100.0 / (1 + error), abs=0.3)


def test_rotation_keeps_every_sample_s_magnitude_and_moves_the_axes():
    rng = np.random.default_rng(1)
    accel = rng.normal(size=(500, 3))
    out = touch.rotate_sensor(accel, 90.0, np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), np.linalg.norm(accel, axis=1))
    np.testing.assert_allclose(out[:, 0], -accel[:, 1], atol=1e-12)  # x ← −y for +90° about z
    np.testing.assert_allclose(touch.rotate_sensor(accel, 0.0, np.ones(3)), accel)


def test_bias_and_drift_add_what_they_say():
    x = np.zeros((2001, 3))
    np.testing.assert_allclose(touch.add_bias(x, 5.0), 5.0)
    drifted = touch.add_drift(x, RATE, 0.5)
    assert drifted[0, 0] == 0 and drifted[-1, 2] == pytest.approx(1.0)  # 0.5 m/s² per s over 2 s


def test_scaled_trajectory_is_the_same_pattern_faster_and_harder():
    traj = freehand(3.0, np.random.default_rng(0))
    fast = touch.scale_trajectory(traj, speed_factor=4.0)
    np.testing.assert_allclose(fast.speed, 4 * traj.speed)
    np.testing.assert_allclose(fast.position, 4 * traj.position)
    np.testing.assert_array_equal(fast.force, traj.force)
    hard = touch.scale_trajectory(traj, force_factor=0.25)
    np.testing.assert_allclose(hard.force, 0.25 * traj.force)


@pytest.mark.parametrize(
    "call",
    [
        lambda: touch.add_noise(np.zeros((10, 3)), float("nan"), np.random.default_rng()),
        lambda: touch.clip_range(np.zeros((10, 3)), 0.0),
        lambda: touch.clip_range(np.zeros((10, 3)), 1.5),
        lambda: touch.periodic_segments(100, RATE, 0.2, 0.1),
        lambda: touch.periodic_segments(100, RATE, 0.0001, 1.0),
        lambda: touch.rate_mismatch(np.zeros(100), -0.6),
        lambda: touch.rotate_sensor(np.zeros((10, 3)), 30.0, np.zeros(3)),
        lambda: touch.add_drift(np.zeros(10), 0.0, 1.0),
        lambda: touch.scale_trajectory(freehand(1.0, np.random.default_rng(0)), speed_factor=0.0),
        lambda: touch.dropout_hold(np.zeros(10), np.ones(10, bool)),
        lambda: touch.add_bias(np.array([1.0, np.nan]), 1.0),
    ],
)
def test_bad_strengths_and_signals_are_refused(call):
    with pytest.raises(ValueError):
        call()
