"""Tap features: known answers on damped sinusoids, robustness, HaTT's recorded taps."""

from pathlib import Path

import numpy as np
import pytest

from models.tactile.taps import MIN_TAP_SAMPLES, TAP_NAMES, local_mean_taps, tap_features

RATE = 1000.0
HATT_TAPS = Path(__file__).resolve().parents[3] / ".." / "shared" / "data" / "hatt-texnet" / "taps"


def damped_taps(
    speeds: np.ndarray,
    gain: float,
    freq_hz: float,
    tau_s: float,
    onset: int = 5,
    n: int = 100,
    noise: float = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """gain·speed·e^(−t/τ)·sin(2πft) from `onset` on: (k, n) m/s²."""
    t = (np.arange(n) - onset) / RATE
    shape = np.where(t >= 0, np.exp(-t / tau_s) * np.sin(2 * np.pi * freq_hz * t), 0.0)
    return gain * speeds[:, None] * shape[None] + noise * np.random.default_rng(seed).standard_normal((speeds.size, n))


def test_known_answers_of_a_damped_ring():
    speeds = np.array([10.0, 25.0, 40.0, 70.0])
    gain, f, tau = 0.3, 200.0, 0.008
    out = tap_features(speeds, damped_taps(speeds, gain, f, tau), RATE)
    assert out.shape == (len(TAP_NAMES),)
    # the first crest of e^(−t/τ)·sin(2πft) sits near t = 1/(4f), where the envelope is e^(−1/(4fτ))
    first_crest = np.exp(-1 / (4 * f * tau))
    assert 10 ** out[0] == pytest.approx(gain * first_crest, rel=0.05)
    # the envelope falls below peak/e about τ after the crest (crests are 1/(2f) apart: ±2.5 ms)
    assert 10 ** out[1] == pytest.approx(tau, abs=1 / (2 * f) + 1e-3)
    assert out[2] == pytest.approx(f, rel=0.15)


def test_harder_surfaces_score_harder():
    """Stiffer: larger peak per unit speed, higher ring, longer decay — each feature moves its way."""
    speeds = np.linspace(5.0, 80.0, 10)
    soft = tap_features(speeds, damped_taps(speeds, 0.05, 60.0, 0.003, noise=0.02), RATE)
    hard = tap_features(speeds, damped_taps(speeds, 1.0, 300.0, 0.015, noise=0.02), RATE)
    assert hard[0] > soft[0] + 1.0
    assert hard[1] > soft[1]
    assert hard[2] > soft[2] + 100.0


def test_medians_shrug_off_a_missed_tap():
    speeds = np.array([10.0, 20.0, 30.0, 40.0, 50.0])
    taps = damped_taps(speeds, 0.3, 200.0, 0.008)
    clean = tap_features(speeds, taps, RATE)
    taps[2] = 0.001 * np.random.default_rng(1).standard_normal(100)  # the tool missed the surface
    np.testing.assert_allclose(tap_features(speeds, taps, RATE), clean, rtol=0.05)


def test_an_offset_baseline_is_removed():
    speeds = np.array([20.0, 40.0])
    taps = damped_taps(speeds, 0.3, 200.0, 0.008)
    np.testing.assert_allclose(tap_features(speeds, taps + 9.81, RATE), tap_features(speeds, taps, RATE), rtol=1e-6)


@pytest.mark.parametrize(
    ("speeds", "accel", "match"),
    [
        (np.ones(3), np.ones((2, 100)), r"speeds \(k,\) and accel \(k, n\)"),
        (np.ones(0), np.ones((0, 100)), "k ≥ 1"),
        (np.ones(2), np.ones((2, MIN_TAP_SAMPLES - 1)), "at least"),
        (np.array([1.0, np.nan]), np.ones((2, 100)), "NaN or Inf"),
        (np.array([0.1, 0.2]), np.ones((2, 100)), "no tap is faster"),
    ],
)
def test_bad_taps(speeds, accel, match):
    with pytest.raises(ValueError, match=match):
        tap_features(speeds, accel, RATE)


@pytest.mark.shared
def test_hatt_taps_give_finite_features_that_separate_metal_from_foam():
    if not HATT_TAPS.is_dir():
        pytest.skip(f"HaTT taps not found at {HATT_TAPS} (needs ../shared)")
    from texture_library.hatt_xml import read_taps

    feats = {}
    for name in ("aluminum", "brick_1", "styrofoam", "epdm_foam", "blanket", "bubble_envelope"):
        path = HATT_TAPS / f"{name}.xml"
        if path.is_file():
            taps = read_taps(path)
            feats[name] = tap_features(taps.speeds, taps.accel, RATE)
            assert np.all(np.isfinite(feats[name])), name
    hard = [feats[n][0] for n in ("aluminum", "brick_1") if n in feats]
    soft = [feats[n][0] for n in ("styrofoam", "epdm_foam", "blanket", "bubble_envelope") if n in feats]
    assert hard and soft and min(hard) > max(soft)  # peak per unit tap speed


def test_local_mean_taps_lines_up_and_averages_the_neighbours_in_speed():
    t = np.arange(100) / 1000.0
    ring = np.where(t >= 0.005, np.exp(-(t - 0.005) / 0.01) * np.sin(2 * np.pi * 150 * (t - 0.005)), 0.0)
    speeds = np.array([10.0, 12.0, 14.0, 60.0, 70.0, 80.0])
    rng = np.random.default_rng(0)
    clean = speeds[:, None] * ring[None, :]
    # the third tap came 2 ms late: lined up before it counts
    clean[2] = speeds[2] * np.concatenate([np.zeros(2), ring[:-2]])
    noisy = clean + 0.5 * rng.standard_normal(clean.shape)
    got = local_mean_taps(speeds, noisy)
    assert got.shape == noisy.shape
    truth = speeds[:, None] * ring[None, :]
    # each tap averages three (itself and its two nearest in speed), so the noise falls by about √3
    for i in (0, 1, 3, 4, 5):
        err_in = np.sqrt(np.mean((noisy[i] - clean[i]) ** 2))
        err_out = np.sqrt(np.mean((got[i] - truth[i]) ** 2))
        assert err_out < 0.8 * err_in, (i, err_in, err_out)
    # one neighbour (itself): the recordings as they were
    np.testing.assert_allclose(local_mean_taps(speeds, noisy, neighbours=1), noisy)
    with pytest.raises(ValueError, match="speeds"):
        local_mean_taps(speeds[:3], noisy)
    with pytest.raises(ValueError, match="> 0"):
        local_mean_taps(np.where(speeds == 10.0, 0.0, speeds), noisy)
