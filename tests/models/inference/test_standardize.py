"""Standardisation with known answers."""

import numpy as np

from models.inference.standardize import Z_CLIP, Standardizer


def test_standardizer_centres_scales_and_bounds_unseen_values():
    X = np.array([[0.0, 1.0], [0.0, 3.0], [1e-6, 5.0]])  # column 0: nearly silent in training
    s = Standardizer().fit(X)
    np.testing.assert_allclose(s.transform(X)[:, 1], [-np.sqrt(1.5), 0.0, np.sqrt(1.5)])
    z = s.transform(np.array([[1.0, 3.0 + 1.0], [-1.0, 3.0]]))
    # a channel that fires only on a new texture stays at ±Z_CLIP instead of |z| ~ 2e6
    assert z[0, 0] == Z_CLIP and z[1, 0] == -Z_CLIP
    np.testing.assert_allclose(z[:, 1], [1.0 / np.sqrt(8 / 3), 0.0])


def test_constant_columns_pass_through_unscaled():
    s = Standardizer().fit(np.array([[2.0], [2.0]]))
    np.testing.assert_allclose(s.transform(np.array([[3.5]])), [[1.5]])
