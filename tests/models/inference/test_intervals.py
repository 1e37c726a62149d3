"""Conformal intervals: known quantiles, coverage on exchangeable data, the OOD fallback, JSON."""

import math

import numpy as np
import pytest

from models.inference.intervals import IntervalCalibration, conformal_quantile, ema


def test_conformal_quantile_is_the_finite_sample_order_statistic():
    scores = np.arange(1.0, 10.0)  # n = 9
    assert conformal_quantile(scores, 0.8) == 8.0  # ⌈0.8·10⌉ = 8th smallest
    assert conformal_quantile(scores, 0.9) == 9.0
    assert math.isinf(conformal_quantile(scores, 0.95))  # 0.95·10/9 > 1: no finite guarantee


def test_grouped_quantile_weighs_every_texture_once():
    # texture a has 100 windows with score 1, textures b…j one window each with scores 2…10
    scores = np.r_[np.ones(100), np.arange(2.0, 11.0)]
    groups = np.r_[np.zeros(100, int), np.arange(1, 10)]
    assert conformal_quantile(scores, 0.8, groups) == 9.0  # as if 10 textures with scores 1…10: ⌈0.8·11⌉
    assert conformal_quantile(scores, 0.8) == 1.0  # counting windows, a's 100 windows swamp the rest


@pytest.mark.parametrize("level", [0.8, 0.9])
def test_coverage_on_exchangeable_data_is_nominal(level):
    rng = np.random.default_rng(0)
    truth_cal = rng.normal(size=(3000, 4)) * 20
    pred_cal = truth_cal + rng.standard_t(4, size=(3000, 4)) * 5
    cal = IntervalCalibration.fit(pred_cal, truth_cal, prior_ratings=truth_cal[:50])
    truth = rng.normal(size=(20000, 4)) * 20
    pred = truth + rng.standard_t(4, size=(20000, 4)) * 5
    lo, hi = cal.interval(pred, level=level)
    covered = np.mean((truth >= lo) & (truth <= hi), axis=0)
    assert np.all(np.abs(covered - level) < 0.02), covered


def test_normalised_intervals_scale_with_the_scale_and_need_it():
    rng = np.random.default_rng(1)
    scale = rng.uniform(0.5, 3, size=300)
    truth = np.zeros((300, 4))
    pred = rng.normal(size=(300, 4)) * scale[:, None] * 4
    cal = IntervalCalibration.fit(
        pred, truth, scale=scale, scale_kind="distance", prior_ratings=rng.normal(size=(30, 4))
    )
    lo, hi = cal.interval(np.zeros((2, 4)), np.array([1.0, 2.0]), level=0.9)
    np.testing.assert_allclose(hi[1] - lo[1], 2 * (hi[0] - lo[0]))
    with pytest.raises(ValueError, match="normalised"):
        cal.interval(np.zeros((2, 4)), None)
    with pytest.raises(ValueError, match="positive"):
        cal.interval(np.zeros((2, 4)), np.array([1.0, 0.0]))


def test_flagged_windows_widen_to_the_population_band_and_everything_is_clipped():
    rng = np.random.default_rng(2)
    prior = rng.uniform(-60, 60, size=(79, 4))
    truth = rng.uniform(-60, 60, size=(79, 4))
    cal = IntervalCalibration.fit(truth + rng.normal(size=(79, 4)), truth, prior_ratings=prior)
    pred = np.array([[99.0, 0, 0, 0], [99.0, 0, 0, 0]])
    lo, hi = cal.interval(pred, level=0.9, ood=np.array([False, True]))
    assert hi[0, 0] == 100.0 and lo[0, 0] > 90  # narrow and clipped at the scale's end
    _, band = cal.quantile(0.9)
    center = prior.mean(axis=0)
    assert lo[1, 0] == pytest.approx(center[0] - band[0]) and hi[1, 0] == 100.0  # hull of both bands
    assert np.all(hi[1] - lo[1] >= hi[0] - lo[0])
    with pytest.raises(ValueError, match="outside"):
        cal.interval(pred, level=0.995)


def test_quantiles_grow_with_the_level_and_interpolate_between_levels():
    rng = np.random.default_rng(3)
    truth = rng.normal(size=(200, 4)) * 10
    cal = IntervalCalibration.fit(truth + rng.normal(size=(200, 4)) * 3, truth, prior_ratings=truth)
    q = cal.quantiles
    assert np.all(np.diff(q, axis=0) >= 0)
    mid, _ = cal.quantile(0.805)
    np.testing.assert_allclose(mid, (cal.quantile(0.80)[0] + cal.quantile(0.81)[0]) / 2)


def test_json_round_trip_is_exact():
    rng = np.random.default_rng(4)
    truth = rng.normal(size=(60, 4)) * 10
    cal = IntervalCalibration.fit(
        truth + rng.normal(size=(60, 4)),
        truth,
        groups=np.arange(60) // 3,
        prior_ratings=truth,
        target="ema",
        ema_alpha=0.5,
        method="test",
    )
    again = IntervalCalibration.from_json(cal.to_json())
    pred = rng.normal(size=(5, 4))
    for a, b in zip(cal.interval(pred, level=0.9), again.interval(pred, level=0.9)):
        np.testing.assert_allclose(a, b, rtol=1e-6)
    assert again.target == "ema" and again.ema_alpha == 0.5 and again.n_textures == 20
    with pytest.raises(ValueError, match="not an interval"):
        IntervalCalibration.from_dict({"format": "other"})
    with pytest.raises(ValueError, match="not JSON"):
        IntervalCalibration.from_json("{")
    with pytest.raises(ValueError, match="ema_alpha"):
        IntervalCalibration.fit(truth, truth, prior_ratings=truth, target="ema")


def test_ema_matches_the_service_smoother():
    from service.smoothing import ExponentialSmoother

    rng = np.random.default_rng(5)
    x = rng.normal(size=(12, 4))
    smoother = ExponentialSmoother(0.3)
    np.testing.assert_allclose(ema(x, 0.3), np.stack([smoother.update(v) for v in x]))
