import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from models.tactile.dft321 import dft321


@pytest.mark.parametrize("n", [500, 501, 64])
def test_parseval_energy_is_the_sum_over_axes(n):
    x = np.random.default_rng(n).standard_normal((4, n, 3)) * [1.0, 2.0, 0.5]
    y = dft321(x)
    assert y.shape == (4, n)
    np.testing.assert_allclose(np.sum(y**2, axis=-1), np.sum(x**2, axis=(-2, -1)), rtol=1e-10)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_single_axis_comes_back_unchanged(axis):
    s = np.random.default_rng(3).standard_normal(500)
    x = np.zeros((500, 3))
    x[:, axis] = s
    np.testing.assert_allclose(dft321(x), s, atol=1e-12)


def test_rotating_a_rank_one_signal_keeps_the_spectrum():
    rng = np.random.default_rng(4)
    s = rng.standard_normal(500)
    u = np.array([0.2, -0.5, 0.84])
    u /= np.linalg.norm(u)
    ref = np.abs(np.fft.rfft(s))
    for seed in range(5):
        R = Rotation.random(random_state=seed).as_matrix()
        y = dft321(np.outer(s, R @ u))
        np.testing.assert_allclose(np.abs(np.fft.rfft(y)), ref, rtol=1e-9, atol=1e-9)


def test_batched_equals_one_by_one():
    x = np.random.default_rng(5).standard_normal((2, 3, 100, 3))
    y = dft321(x)
    assert y.shape == (2, 3, 100)
    np.testing.assert_allclose(y[1, 2], dft321(x[1, 2]), atol=1e-13)


@pytest.mark.parametrize(
    ("x", "message"),
    [
        (np.zeros((10, 2)), r"\(\.\.\., n, 3\)"),
        (np.zeros(10), r"\(\.\.\., n, 3\)"),
        (np.zeros((1, 3)), "at least 2"),
        (np.full((10, 3), np.nan), "NaN"),
        (np.zeros((10, 3), dtype=complex), "real"),
    ],
)
def test_bad_input(x, message):
    with pytest.raises(ValueError, match=message):
        dft321(x)
