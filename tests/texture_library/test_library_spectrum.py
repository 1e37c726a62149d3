"""Known answers for the exact ARMA spectra and the log-spectral distance."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from texture_library.lsf import poly_to_lsf
from texture_library.spectrum import (
    arma_psd,
    band_frequencies,
    log_spectral_distance_db,
    model_spectra,
    pooled_distance_db,
    pooled_spectral_distance_db,
    spectral_distance_db,
)
from texture_library.synthesis import render

from .conftest import square_model


def white_model(variance: float = 4.0):
    """The square grid with no poles and no zeros: white noise of the given variance everywhere."""
    m = square_model()
    n = m.speeds.size
    return dataclasses.replace(
        m, ar_lsf=np.zeros((n, 0)), ma_lsf=np.zeros((n, 0)), variance=np.full(n, variance), gain=np.ones(n)
    )


def test_white_noise_has_the_flat_spectrum_two_sigma_squared_over_the_rate():
    psd = arma_psd(white_model(4.0), [100.0], [2.0], band_frequencies(50))
    np.testing.assert_allclose(psd, 2 * 4.0 / 1000.0, rtol=1e-12)


def test_the_spectrum_peaks_at_the_ar_pole_and_integrates_to_the_rendered_power():
    m = square_model()
    freqs = np.linspace(0.0, 500.0, 5001)
    psd = arma_psd(m, [100.0], [2.0], freqs)[0]  # grid point: poles at 110 Hz and 300 Hz
    peaks = freqs[1:-1][(psd[1:-1] > psd[:-2]) & (psd[1:-1] > psd[2:])]
    np.testing.assert_allclose(sorted(peaks), [110.0, 300.0], atol=3.0)
    rendered = render(m, np.full(200_000, 100.0), np.full(200_000, 2.0), np.random.default_rng(0))[1000:]
    power = np.sum(psd) * (freqs[1] - freqs[0])  # one-sided PSD integrates to the variance
    assert power == pytest.approx(np.var(rendered), rel=0.03)


def test_distance_is_zero_to_itself_and_ten_db_for_ten_times_the_power():
    m = square_model()
    assert spectral_distance_db(m, m) == 0.0
    louder = dataclasses.replace(m, variance=m.variance * 10.0)
    # speed 0 is outside the operating points, so every point has positive variance
    assert spectral_distance_db(m, louder) == pytest.approx(10.0, abs=1e-9)


def test_the_band_leaves_the_nyquist_bin_out():
    f = band_frequencies()
    assert f.size == 240 and f[0] == 20.0 and f[-1] == pytest.approx(498.0) and np.all(f < 500.0)
    np.testing.assert_allclose(np.diff(f), 2.0)


def zero_near_nyquist(r: float = 0.999):
    """The white model with one MA zero at z = −r: |B|² = 1 + 2r·cos ω + r², 60 dB down at 500 Hz for r = 0.999."""
    m = white_model(4.0)
    return dataclasses.replace(m, ma_lsf=np.tile(poly_to_lsf(np.array([1.0, r])), (m.speeds.size, 1)))


def test_a_zero_at_nyquist_counts_only_through_the_band_below_it():
    # every operating point has the same spectra, so the distance is the RMS of 10·log10|B|² over the grid
    f = band_frequencies()
    w = 2 * np.pi * f / 1000.0
    expected = np.sqrt(np.mean((10 * np.log10(1 + 2 * 0.999 * np.cos(w) + 0.999**2)) ** 2))
    assert spectral_distance_db(zero_near_nyquist(), white_model(4.0)) == pytest.approx(expected, rel=1e-9)
    # the old grid (97 bins, 500 Hz included) holds the −60 dB bin, and it alone moves the figure
    old = np.linspace(20.0, 500.0, 97)
    with_nyquist = spectral_distance_db(zero_near_nyquist(), white_model(4.0), old)
    without = spectral_distance_db(zero_near_nyquist(), white_model(4.0), old[:-1])
    assert 10 * np.log10((1 - 0.999) ** 2) == pytest.approx(-60.0)
    assert with_nyquist - without > 1.0


def test_the_pooled_variant_is_one_rms_over_points_and_frequencies():
    m = square_model()
    # 10× the power at speed 100 and 100× at speed 200: 10 dB at one point, 20 dB at the other
    louder = dataclasses.replace(m, variance=m.variance * np.where(m.speeds == 200.0, 100.0, 10.0))
    points = ((100.0, 2.0), (200.0, 2.0))
    assert spectral_distance_db(m, louder, points=points) == pytest.approx(15.0, abs=1e-9)
    assert pooled_spectral_distance_db(m, louder, points=points) == pytest.approx(np.sqrt(250.0), abs=1e-9)
    assert pooled_spectral_distance_db(m, m) == 0.0
    # equally far everywhere: the two definitions agree
    ten = dataclasses.replace(m, variance=m.variance * 10.0)
    assert pooled_spectral_distance_db(m, ten) == pytest.approx(spectral_distance_db(m, ten), abs=1e-9)


def test_weights_pick_the_part_of_the_band_that_counts():
    a = np.ones((2, 4))
    b = np.array([[1.0, 1.0, 10.0, 10.0], [1.0, 1.0, 1.0, 1.0]])
    np.testing.assert_allclose(log_spectral_distance_db(a, b), [np.sqrt(50.0), 0.0])
    np.testing.assert_allclose(log_spectral_distance_db(a, b, weights=np.array([1.0, 1.0, 0.0, 0.0])), [0.0, 0.0])
    assert model_spectra(square_model()).shape == (9, 240)


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda m: arma_psd(m, [1.0, 2.0], [1.0], band_frequencies()), "equal length"),
        (lambda m: arma_psd(m, [1.0], [1.0], np.array([10.0, 600.0])), "freqs_hz must lie in"),
        (lambda m: log_spectral_distance_db(np.ones(3), np.ones(4)), "same shape"),
        (lambda m: log_spectral_distance_db(np.ones(3), -np.ones(3)), "≥ 0"),
        (lambda m: band_frequencies(1), "n must be"),
        (lambda m: pooled_distance_db(np.ones(3), np.ones(3)), "points, frequencies"),
    ],
)
def test_bad_input_is_named(call, message):
    with pytest.raises(ValueError, match=message):
        call(square_model())
