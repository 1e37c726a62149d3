import numpy as np
import pytest

from models.tactile.config import TactileConfig
from models.tactile.mfcc import librosa_mfcc, mfcc, mfcc_matrices

CONFIG = TactileConfig()


def assert_matches_librosa(windows, config):
    ours = mfcc(windows, config)
    ref = np.stack([librosa_mfcc(w, config) for w in windows])
    assert ours.shape == ref.shape == (len(windows), config.n_frames, config.n_mfcc)
    scale = np.max(np.abs(ref))
    np.testing.assert_allclose(ours, ref, rtol=1e-4, atol=1e-4 * scale)


def test_equals_librosa_on_random_windows():
    rng = np.random.default_rng(0)
    windows = rng.standard_normal((6, 500)) * np.array([[1e-3], [1.0], [30.0], [1.0], [5.0], [0.1]])
    assert_matches_librosa(windows, CONFIG)


def test_equals_librosa_on_sines_and_silence():
    t = np.arange(500) / 1000.0
    windows = np.stack([np.sin(2 * np.pi * f * t) for f in (37.0, 120.0, 250.0, 333.0, 480.0)] + [np.zeros(500)])
    assert_matches_librosa(windows, CONFIG)


@pytest.mark.parametrize(
    "config",
    [
        TactileConfig(top_db=40.0),
        TactileConfig(n_mels=20, n_mfcc=10, frame_hop=25),
        TactileConfig(window_s=0.25, hop_s=0.25, n_fft=128, n_mels=32),
    ],
)
def test_equals_librosa_for_other_configs(config):
    windows = np.random.default_rng(1).standard_normal((3, config.window_length))
    assert_matches_librosa(windows, config)


def test_top_db_floor_is_per_window():
    rng = np.random.default_rng(2)
    quiet = 1e-4 * rng.standard_normal(500)
    loud = 1e3 * rng.standard_normal(500)
    alone = mfcc(quiet[None], CONFIG)[0]
    batched = mfcc(np.stack([loud, quiet]), CONFIG)[1]
    np.testing.assert_allclose(batched, alone, rtol=1e-5, atol=1e-4)


def test_tone_energy_lands_in_its_mel_band():
    # invert the DCT (orthonormal, all coefficients) to get log-mel back and check the peak band
    import librosa

    config = TactileConfig(n_mfcc=26)
    t = np.arange(500) / 1000.0
    dct = mfcc_matrices(config)[2]  # (n_mels, n_mfcc), orthonormal and square here
    log_mel = mfcc(np.sin(2 * np.pi * 200.0 * t)[None], config)[0] @ dct.T
    peak = int(np.argmax(log_mel.mean(axis=0)))
    centres = librosa.mel_frequencies(config.n_mels + 2, fmin=config.fmin, fmax=config.fmax)[1:-1]
    assert abs(centres[peak] - 200.0) < 20.0


@pytest.mark.parametrize(
    ("windows", "message"),
    [
        (np.zeros((2, 499)), r"\(n, 500\)"),
        (np.zeros(500), r"\(n, 500\)"),
        (np.full((1, 500), np.inf), "NaN or Inf"),
        (np.zeros((1, 500), dtype=bool), "real"),
    ],
)
def test_bad_input(windows, message):
    with pytest.raises(ValueError, match=message):
        mfcc(windows, CONFIG)
