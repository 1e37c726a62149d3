import numpy as np
import pytest

from models.evaluation.bootstrap import bootstrap_mean, paired_difference, per_texture_error


def test_interval_covers_the_mean_and_shrinks_with_more_textures():
    rng = np.random.default_rng(0)
    small = bootstrap_mean(rng.normal(5, 2, size=20))
    large = bootstrap_mean(rng.normal(5, 2, size=2000))
    assert small["lo"] < small["mean"] < small["hi"]
    # the standard error of a mean of n draws with sd 2: the 95 % width ≈ 3.92·2/√n
    assert large["hi"] - large["lo"] == pytest.approx(3.92 * 2 / np.sqrt(2000), rel=0.1)
    assert small["hi"] - small["lo"] > 5 * (large["hi"] - large["lo"])


def test_paired_difference_removes_what_both_share():
    rng = np.random.default_rng(1)
    shared = rng.normal(0, 10, size=80)  # texture difficulty, common to both models
    a, b = shared + 1.0 + rng.normal(0, 0.1, 80), shared
    diff = paired_difference(a, b)
    assert diff["lo"] > 0.9 and diff["hi"] < 1.1
    unpaired_width = bootstrap_mean(a)["hi"] - bootstrap_mean(a)["lo"]
    assert diff["hi"] - diff["lo"] < 0.1 * unpaired_width


def test_per_texture_error_is_on_the_report_scale_and_inputs_are_checked():
    pred = np.array([[10.0, 0, 0, 0], [0, 0, 0, 0]])
    np.testing.assert_allclose(per_texture_error(pred, np.zeros((2, 4))), [1.25, 0.0])  # 10/4 bipolar → ÷ 2
    with pytest.raises(ValueError):
        per_texture_error(pred, np.zeros((3, 4)))
    with pytest.raises(ValueError):
        bootstrap_mean(np.array([1.0]))
    with pytest.raises(ValueError):
        bootstrap_mean(np.array([1.0, np.nan]))
