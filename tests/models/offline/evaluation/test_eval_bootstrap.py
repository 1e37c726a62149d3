"""Texture-level bootstrap intervals: known answers, pairing, and that the intervals cover what they claim."""

import numpy as np
import pytest

from models.offline.evaluation.bootstrap import (
    bootstrap_errors,
    bootstrap_mean,
    paired_difference,
    paired_ratio,
    per_texture_error,
    resample_indices,
    texture_errors,
)


def test_texture_errors_are_on_the_report_scale_and_averaged_over_seeds():
    truth = np.zeros((2, 4))
    pred = np.stack([np.full((2, 4), 10.0), np.full((2, 4), -30.0)])  # two seeds: |err| 5 and 15 on 0–100
    abs_err, sq_err = texture_errors(pred, truth)
    np.testing.assert_allclose(abs_err, 10.0)
    np.testing.assert_allclose(sq_err, (25.0 + 225.0) / 2)
    np.testing.assert_allclose(texture_errors(pred[0], truth)[0], 5.0)
    with pytest.raises(ValueError, match="matching truth"):
        texture_errors(pred, np.zeros((3, 4)))


def test_constant_errors_give_a_zero_width_interval():
    out = bootstrap_errors(np.full((20, 4), 3.0), np.full((20, 4), 9.0))
    for metric in ("mae", "rmse"):
        assert out[metric]["lo"]["mean"] == out[metric]["value"]["mean"] == out[metric]["hi"]["mean"] == 3.0


def test_interval_is_the_percentile_of_resampled_means():
    rng = np.random.default_rng(3)
    abs_err = rng.gamma(2.0, 2.5, size=(40, 4))
    out = bootstrap_errors(abs_err, n_boot=500, seed=7)["mae"]
    means = abs_err[resample_indices(40, 500, 7)].mean(axis=1).mean(axis=1)
    assert out["lo"]["mean"] == pytest.approx(np.percentile(means, 2.5))
    assert out["hi"]["mean"] == pytest.approx(np.percentile(means, 97.5))
    assert out["value"]["hard_soft"] == pytest.approx(abs_err[:, 3].mean())


def test_95_percent_intervals_cover_the_true_mae_about_95_percent_of_the_time():
    rng = np.random.default_rng(0)
    true_mae = 5.0  # errors ~ exponential with mean 5
    hits = 0
    for trial in range(200):
        abs_err = rng.exponential(true_mae, size=(79, 4))
        out = bootstrap_errors(abs_err, n_boot=400, seed=trial)["mae"]
        hits += out["lo"]["rough_smooth"] <= true_mae <= out["hi"]["rough_smooth"]
    assert 0.88 <= hits / 200 <= 0.99, hits


def test_paired_difference_resamples_the_same_textures_for_both_models():
    rng = np.random.default_rng(1)
    hard = rng.exponential(8.0, size=(60, 4))  # texture difficulty shared by both models
    a, b = hard + 1.0, hard + rng.normal(0, 0.05, size=hard.shape)
    d = paired_difference(a, b)
    assert d["value"]["mean"] == pytest.approx(1.0, abs=0.02)
    assert 0.9 < d["lo"]["mean"] < d["hi"]["mean"] < 1.1  # tight: the shared difficulty cancels
    # unpaired, the same data gives an interval far wider than the paired one
    unpaired = bootstrap_errors(a)["mae"]
    assert unpaired["hi"]["mean"] - unpaired["lo"]["mean"] > 10 * (d["hi"]["mean"] - d["lo"]["mean"])
    same = paired_difference(a, a)
    assert same["lo"]["mean"] == same["hi"]["mean"] == 0.0


def test_bad_input():
    with pytest.raises(ValueError, match="same textures"):
        paired_difference(np.zeros((5, 4)), np.zeros((6, 4)))
    with pytest.raises(ValueError, match="at least 2 textures"):
        bootstrap_errors(np.zeros((1, 4)))
    with pytest.raises(ValueError, match="n_boot must be ≥ 100"):
        bootstrap_errors(np.zeros((5, 4)), n_boot=10)


def test_paired_ratio_known_answers():
    rng = np.random.default_rng(2)
    ref = rng.exponential(10.0, size=(40, 4)) + 0.1
    half = paired_ratio(0.5 * ref, ref)  # half the error on every texture: exactly 0.5 on every resample
    for part in ("value", "lo", "hi"):
        assert half[part]["mean"] == pytest.approx(0.5) and half[part]["hard_soft"] == pytest.approx(0.5)
    noisy = paired_ratio(ref * rng.uniform(0.2, 0.6, size=ref.shape), ref)
    assert noisy["lo"]["mean"] < noisy["value"]["mean"] < noisy["hi"]["mean"] < 0.6
    with pytest.raises(ValueError, match="zero error"):
        paired_ratio(ref, np.zeros_like(ref))
    with pytest.raises(ValueError, match="same textures"):
        paired_ratio(ref, ref[:-1])


def test_bootstrap_mean_interval_covers_the_mean_and_shrinks_with_more_textures():
    rng = np.random.default_rng(0)
    small = bootstrap_mean(rng.normal(5, 2, size=20))
    large = bootstrap_mean(rng.normal(5, 2, size=2000))
    assert small["lo"] < small["mean"] < small["hi"]
    # the standard error of a mean of n draws with sd 2: the 95 % width ≈ 3.92·2/√n
    assert large["hi"] - large["lo"] == pytest.approx(3.92 * 2 / np.sqrt(2000), rel=0.1)
    assert small["hi"] - small["lo"] > 5 * (large["hi"] - large["lo"])


def test_bootstrap_mean_of_a_paired_difference_removes_what_both_share():
    rng = np.random.default_rng(1)
    shared = rng.normal(0, 10, size=80)  # texture difficulty, common to both models
    a, b = shared + 1.0 + rng.normal(0, 0.1, 80), shared
    diff = bootstrap_mean(a - b)
    assert diff["lo"] > 0.9 and diff["hi"] < 1.1
    unpaired_width = bootstrap_mean(a)["hi"] - bootstrap_mean(a)["lo"]
    assert diff["hi"] - diff["lo"] < 0.1 * unpaired_width


def test_bootstrap_mean_agrees_with_bootstrap_errors_on_the_mean_attribute():
    abs_err = np.random.default_rng(4).gamma(2.0, 2.5, size=(30, 4))
    one = bootstrap_mean(abs_err.mean(axis=1))
    table = bootstrap_errors(abs_err)["mae"]
    assert (one["mean"], one["lo"], one["hi"]) == pytest.approx(
        (table["value"]["mean"], table["lo"]["mean"], table["hi"]["mean"])
    )


def test_per_texture_error_is_on_the_report_scale_and_inputs_are_checked():
    pred = np.array([[10.0, 0, 0, 0], [0, 0, 0, 0]])
    np.testing.assert_allclose(per_texture_error(pred, np.zeros((2, 4))), [1.25, 0.0])  # 10/4 bipolar → ÷ 2
    with pytest.raises(ValueError):
        per_texture_error(pred, np.zeros((3, 4)))
    with pytest.raises(ValueError):
        bootstrap_mean(np.array([1.0]))
    with pytest.raises(ValueError):
        bootstrap_mean(np.array([1.0, np.nan]))
