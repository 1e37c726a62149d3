import numpy as np
import pytest

from models.offline.evaluation.metrics import error_table, group_errors, split_half_ceiling
from texture_library.attributes import ATTRIBUTES


def test_errors_are_on_the_0_100_scale():
    truth = np.zeros((2, 4))
    pred = np.array([[10, -10, 20, 0], [10, 10, -20, 0]], float)  # bipolar errors
    e = error_table(pred, truth)
    assert e["mae"]["rough_smooth"] == pytest.approx(5.0)
    assert e["mae"]["sticky_slippery"] == pytest.approx(10.0)
    assert e["mae"]["hard_soft"] == 0.0
    assert e["mae"]["mean"] == pytest.approx((5 + 5 + 10 + 0) / 4)
    assert e["rmse"]["flat_bumpy"] == pytest.approx(5.0)


def test_error_table_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="must both be"):
        error_table(np.zeros((3, 4)), np.zeros((2, 4)))


def test_split_half_of_identical_raters_is_zero_and_of_noisy_raters_matches_theory():
    truth = np.random.default_rng(0).uniform(-80, 80, size=(40, 1, 4))
    assert split_half_ceiling(np.repeat(truth, 10, axis=1))["mae"]["mean"] == pytest.approx(0.0, abs=1e-9)
    sd, raters = 20.0, 40
    noisy = truth + np.random.default_rng(1).normal(0, sd, size=(40, raters, 4))
    # difference of two half-means: sd·sqrt(4/raters) bipolar → MAE = that·sqrt(2/π), ÷2 for the report scale
    expected = sd * np.sqrt(4 / raters) * np.sqrt(2 / np.pi) / 2
    assert split_half_ceiling(noisy, n_splits=100)["mae"]["mean"] == pytest.approx(expected, rel=0.1)


def test_group_errors_count_textures_per_group():
    truth = np.zeros((3, 4))
    pred = np.array([[2, 0, 0, 0], [4, 0, 0, 0], [0, 0, 0, 8]], float)
    g = group_errors(pred, truth, ["x", "x", "y"])
    assert g["x"]["n"] == 2 and g["y"]["n"] == 1
    assert g["x"]["rough_smooth"] == pytest.approx(1.5)
    assert g["y"]["hard_soft"] == pytest.approx(4.0)
    assert set(ATTRIBUTES) <= set(g["x"])
