"""Friction features: known answers for the tangential-to-normal force ratio."""

import numpy as np
import pytest

from models.tactile.friction import FRICTION_NAMES, MIN_NORMAL_N, friction_features


def test_coulomb_friction_reads_mu_whatever_the_pressure():
    rng = np.random.default_rng(0)
    normal = 0.3 + 3.5 * rng.random((4, 500))  # pressure wanders 0.3–3.8 N
    mu = np.array([0.15, 0.4, 0.8, 1.2])[:, None]
    f = friction_features(normal, mu * normal)
    assert f.shape == (4, len(FRICTION_NAMES))
    np.testing.assert_allclose(f[:, 0], mu[:, 0], rtol=1e-12)
    np.testing.assert_allclose(f[:, 1], 0.0, atol=1e-12)  # the ratio never wanders


def test_ratio_std_measures_a_wandering_ratio():
    normal = np.full((1, 1000), 2.0)
    ratio = 0.5 + 0.1 * np.sign(np.sin(np.linspace(0, 20 * np.pi, 1000)))  # stick–slip between 0.4 and 0.6
    f = friction_features(normal, ratio * normal)[0]
    assert f[0] == pytest.approx(ratio.mean())
    assert f[1] == pytest.approx(ratio.std(), rel=1e-9)


def test_light_touches_do_not_count_in_the_spread():
    normal = np.full((1, 100), 2.0)
    normal[0, :10] = MIN_NORMAL_N / 10  # nearly lifted: a 0.005 N ratio denominator would explode
    tangential = 0.5 * normal
    tangential[0, :10] = 0.01  # sensor noise, not friction
    f = friction_features(normal, tangential)[0]
    assert f[1] == pytest.approx(0.0, abs=1e-12)
    assert f[0] == pytest.approx(0.5, abs=1e-3)  # the least-squares slope weighs light samples little


def test_no_contact_gives_zeros_not_nan():
    f = friction_features(np.zeros((2, 50)), np.zeros((2, 50)))
    np.testing.assert_array_equal(f, 0.0)


@pytest.mark.parametrize(
    ("normal", "tangential", "match"),
    [
        (np.zeros((2, 50)), np.zeros((2, 40)), r"both be \(n, L\)"),
        (np.zeros(50), np.zeros(50), r"both be \(n, L\)"),
        (np.full((1, 5), np.nan), np.zeros((1, 5)), "finite"),
        (np.zeros((1, 0)), np.zeros((1, 0)), "at least one sample"),
    ],
)
def test_bad_inputs(normal, tangential, match):
    with pytest.raises(ValueError, match=match):
        friction_features(normal, tangential)
