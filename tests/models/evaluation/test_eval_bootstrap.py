"""Texture-level bootstrap intervals: known answers, pairing, coverage."""

import numpy as np
import pytest

from models.evaluation.metrics import bootstrap_mae_samples, error_table, percentile_interval


def test_constant_errors_have_a_zero_width_interval():
    truth = np.zeros((30, 4))
    pred = np.tile([10.0, -20.0, 4.0, 0.0], (30, 1))
    s = bootstrap_mae_samples(pred, truth, n_boot=200)
    assert s.shape == (200, 5)
    np.testing.assert_allclose(percentile_interval(s), [[5, 10, 2, 0, 4.25]] * 2)


def test_interval_brackets_the_point_and_covers_the_population_mae():
    """With errors drawn from a known distribution, the 95 % interval covers the population MAE ~95 % of the time."""
    rng = np.random.default_rng(5)
    population = 10.0 * np.sqrt(2 / np.pi) / 2  # |N(0, 10)| bipolar errors, on the 0–100 scale
    hits = 0
    for trial in range(300):
        err = np.abs(rng.normal(0.0, 10.0, size=(40, 4)))
        ci = percentile_interval(bootstrap_mae_samples(err, np.zeros_like(err), n_boot=1000, seed=trial))
        point = error_table(err, np.zeros_like(err))["mae"]["rough_smooth"]
        assert ci[0, 0] <= point <= ci[1, 0]
        hits += ci[0, 0] <= population <= ci[1, 0]
    assert 0.91 <= hits / 300 <= 0.99


def test_same_seed_pairs_the_resamples():
    """A prediction better by exactly 2 bipolar points on every texture: the paired difference is exactly 1."""
    rng = np.random.default_rng(1)
    truth = rng.uniform(-50, 50, (25, 4))
    worse = truth + 10.0 + rng.uniform(0, 5, (25, 4))
    better = worse - 2.0
    d = bootstrap_mae_samples(worse, truth, n_boot=300) - bootstrap_mae_samples(better, truth, n_boot=300)
    np.testing.assert_allclose(d, 1.0)
    d_unpaired = bootstrap_mae_samples(worse, truth, n_boot=300, seed=1) - bootstrap_mae_samples(better, truth, n_boot=300, seed=2)
    assert d_unpaired.std() > 0.1


@pytest.mark.parametrize(("pred", "truth", "kw", "match"), [
    (np.zeros((5, 4)), np.zeros((4, 4)), {}, "must both be"),
    (np.zeros((1, 4)), np.zeros((1, 4)), {}, "T ≥ 2"),
    (np.zeros((5, 4)), np.zeros((5, 4)), {"n_boot": 10}, "n_boot"),
])
def test_bad_arguments(pred, truth, kw, match):
    with pytest.raises(ValueError, match=match):
        bootstrap_mae_samples(pred, truth, **kw)
    with pytest.raises(ValueError, match="level"):
        percentile_interval(np.zeros((10, 2)), level=1.5)
