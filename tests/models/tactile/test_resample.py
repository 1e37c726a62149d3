import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models.tactile.resample import Resampler, resample


def test_equal_rates_pass_through():
    x = np.random.default_rng(0).standard_normal((123, 3))
    np.testing.assert_array_equal(resample(x, 1000.0, 1000.0), x)


@pytest.mark.parametrize("rate_in", [200.0, 250.0, 333.0, 500.0, 800.0])
def test_upsampling_interpolates_a_ramp_exactly_at_t_k(rate_in):
    n = 97
    ramp = 3.0 + 2.5 * np.arange(n) / rate_in  # a line in time: linear interpolation is exact
    y = resample(ramp, rate_in, 1000.0)
    assert y.shape[0] == math.floor((n - 1) * 1000.0 / rate_in) + 1
    np.testing.assert_allclose(y, 3.0 + 2.5 * np.arange(y.shape[0]) / 1000.0, atol=1e-12)


@pytest.mark.parametrize(
    ("rate_in", "n"), [(200.0, 97), (500.0, 1000), (1000.0, 10), (3000.0, 3001), (5000.0, 12345), (44100.0, 441)]
)
def test_flush_makes_output_span_the_input_duration(rate_in, n):
    r = Resampler(rate_in, 1000.0)
    y = np.concatenate([r.process(np.arange(n, dtype=float)), r.flush()])
    assert y.shape[0] == math.ceil(n * 1000.0 / rate_in - 1e-9)
    with pytest.raises(ValueError, match="flushed"):
        r.process(np.zeros(3))


def test_downsampling_keeps_passband_and_rejects_aliases():
    fs = 5000.0
    t = np.arange(int(2 * fs)) / fs
    low = resample(np.sin(2 * np.pi * 50 * t), fs)[200:]
    alias = resample(np.sin(2 * np.pi * 2300 * t), fs)[200:]  # would fold to 300 Hz
    assert np.sqrt(np.mean(low**2)) == pytest.approx(np.sqrt(0.5), rel=0.01)
    assert np.max(np.abs(alias)) < 0.01  # > 40 dB down


def test_integer_ratio_downsampling_picks_input_samples_of_a_constant():
    y = resample(np.full((3000, 2), 4.2), 3000.0)
    assert y.shape == (1000, 2)
    np.testing.assert_allclose(y, 4.2, atol=1e-12)


@settings(max_examples=30, deadline=None)
@given(
    rate_in=st.sampled_from([200.0, 333.3, 1000.0, 2500.0, 3000.0, 10000.0]),
    cuts=st.lists(st.integers(0, 2000), max_size=8),
    cols=st.sampled_from([0, 3]),
)
def test_chunked_equals_whole(rate_in, cuts, cols):
    rng = np.random.default_rng(2)
    x = rng.standard_normal((2000,) if cols == 0 else (2000, cols))
    whole = resample(x, rate_in)
    r = Resampler(rate_in)
    chunked = np.concatenate([r.process(p) for p in np.split(x, sorted(cuts))])
    assert chunked.shape == whole.shape
    np.testing.assert_allclose(chunked, whole, rtol=0, atol=1e-12)


@pytest.mark.parametrize("rate", [0.0, -5.0, float("nan"), float("inf"), 5.0, 1e9, "fast", None])
def test_bad_rates(rate):
    with pytest.raises(ValueError, match="rate_in"):
        Resampler(rate)
    with pytest.raises(ValueError, match="rate_out"):
        Resampler(1000.0, rate)


def test_bad_samples():
    with pytest.raises(ValueError, match="NaN or Inf"):
        resample(np.array([0.0, np.nan, 1.0]), 2000.0)
    with pytest.raises(ValueError, match="shape"):
        resample(np.zeros((4, 2, 2)), 2000.0)
    r = Resampler(2000.0)
    r.process(np.zeros((10, 3)))
    with pytest.raises(ValueError, match="columns"):
        r.process(np.zeros((10, 2)))
