import numpy as np
import pytest

from models.tactile.config import TactileConfig
from models.tactile.dwt import WAVELETS, dwt_features, dwt_step, wavedec, wavelet_filters

# pywt.Wavelet("db4").dec_lo, for cross-checking the spectral factorisation
PYWT_DB4_DEC_LO = [
    -0.010597401784997278,
    0.032883011666982945,
    0.030841381835986965,
    -0.18703481171888114,
    -0.02798376941698385,
    0.6308807679295904,
    0.7148465705525415,
    0.23037781330885523,
]


@pytest.mark.parametrize("wavelet", WAVELETS)
def test_filters_are_orthonormal_daubechies(wavelet):
    lo, hi = wavelet_filters(wavelet)
    n_moments = int(wavelet[2:])
    assert lo.size == hi.size == 2 * n_moments
    assert lo.sum() == pytest.approx(np.sqrt(2), abs=1e-12)
    assert np.dot(lo, lo) == pytest.approx(1.0, abs=1e-12)
    for m in range(1, n_moments):  # orthogonal to its even shifts
        assert np.dot(lo[2 * m :], lo[: lo.size - 2 * m]) == pytest.approx(0.0, abs=1e-12)
    k = np.arange(hi.size, dtype=float)
    for p in range(n_moments):  # vanishing moments of the high-pass
        assert np.dot(hi, k**p) == pytest.approx(0.0, abs=1e-9)


def test_db4_matches_pywt():
    np.testing.assert_allclose(wavelet_filters("db4")[0], PYWT_DB4_DEC_LO, atol=1e-11)


def test_haar_known_answer():
    a, d = dwt_step(np.array([1.0, 2.0, 3.0, 4.0]), "db1")  # pywt.dwt([1, 2, 3, 4], "db1")
    np.testing.assert_allclose(a, [3 / np.sqrt(2), 7 / np.sqrt(2)], atol=1e-12)
    np.testing.assert_allclose(d, [-1 / np.sqrt(2), -1 / np.sqrt(2)], atol=1e-12)


def test_coefficient_lengths():
    coeffs = wavedec(np.zeros((2, 500)), "db4", 5)
    assert [c.shape[-1] for c in coeffs] == [253, 130, 68, 37, 22, 22]  # floor((N + 7) / 2) per level


@pytest.mark.parametrize(("freq", "band"), [(400.0, 0), (200.0, 1), (90.0, 2), (45.0, 3), (22.0, 4)])
def test_sine_energy_lands_in_its_level(freq, band):
    t = np.arange(500) / 1000.0
    energies = [np.sum(c**2) for c in wavedec(np.sin(2 * np.pi * freq * t), "db4", 5)]
    assert int(np.argmax(energies)) == band  # d1 250–500, d2 125–250, d3 62–125, d4 31–62, d5 16–31 Hz


def test_features_layout():
    config = TactileConfig(feature_set="dwt")
    t = np.arange(500) / 1000.0
    f = dwt_features(np.stack([np.sin(2 * np.pi * 200.0 * t), np.zeros(500)]), config)
    assert f.shape == (2, 18)
    names = config.feature_names
    log_energy = f[0, 0::3]
    assert names[3 * int(np.argmax(log_energy))] == "dwt_d2_log_energy"
    assert np.all(f[0, 1::3] >= 0) and np.all(f[0, 2::3] >= 0)
    np.testing.assert_allclose(f[1, 0::3], -12.0)  # log10 floor for silence


def test_bad_input():
    with pytest.raises(ValueError, match="wavelet"):
        wavelet_filters("sym4")
    with pytest.raises(ValueError, match=r"\(n, 500\)"):
        dwt_features(np.zeros((2, 400)), TactileConfig(feature_set="dwt"))
    with pytest.raises(ValueError, match="levels"):
        wavedec(np.zeros(64), "db1", 0)
