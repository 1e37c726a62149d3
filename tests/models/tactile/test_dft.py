import numpy as np
import pytest

from models.tactile.config import TactileConfig
from models.tactile.dft import band_edges, band_matrix, dft_features

CONFIG = TactileConfig(feature_set="dft")


def test_band_matrix_averages_disjoint_bins_inside_the_range():
    m = band_matrix(1000.0, 500, 20.0, 500.0, 32)
    assert m.shape == (251, 32)
    np.testing.assert_allclose(m.sum(axis=0), 1.0)
    assert np.all(np.count_nonzero(m, axis=1) <= 1)
    freqs = np.arange(251) * 2.0
    used = np.count_nonzero(m, axis=1) == 1
    assert freqs[used].min() >= 20.0 and freqs[used].max() == 500.0
    assert not used[freqs < 20.0].any()


@pytest.mark.parametrize("freq", [27.0, 207.0, 331.0, 478.0])
def test_sine_lands_in_its_band(freq):
    t = np.arange(500) / 1000.0
    f = dft_features(np.sin(2 * np.pi * freq * t)[None], CONFIG)
    assert f.shape == (1, 32)
    edges = band_edges(CONFIG)
    peak = int(np.argmax(f[0]))
    assert edges[peak] <= freq < edges[peak + 1]
    assert f[0, peak] - np.median(f[0]) > 2.0  # > 100× the typical band


def test_silence_is_the_floor_and_bad_shape_is_rejected():
    np.testing.assert_allclose(dft_features(np.zeros((1, 500)), CONFIG), -10.0)
    with pytest.raises(ValueError, match=r"\(n, 500\)"):
        dft_features(np.zeros((500,)), CONFIG)
