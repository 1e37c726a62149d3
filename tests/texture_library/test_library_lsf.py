"""Line spectral frequencies ⇄ polynomial coefficients."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from texture_library.lsf import lsf_to_poly, poles_to_poly, poly_to_lsf


@st.composite
def stable_polys(draw, max_order: int = 20, max_radius: float = 0.97) -> np.ndarray:
    """A monic real polynomial of order 1…max_order with every root strictly inside |z| ≤ max_radius."""
    order = draw(st.integers(1, max_order))
    radius = st.floats(0.0, max_radius)
    roots: list[complex] = []
    for _ in range(order // 2):
        r, theta = draw(radius), draw(st.floats(0.0, np.pi))
        roots += [r * np.exp(1j * theta), r * np.exp(-1j * theta)]
    if order % 2:
        roots.append(draw(st.floats(-max_radius, max_radius)))
    return np.real(np.poly(roots))


@settings(max_examples=300, deadline=None)
@given(stable_polys())
def test_lsf_round_trip_recovers_the_polynomial(a):
    lsf = poly_to_lsf(a)
    assert lsf.shape == (a.size - 1,)
    # clustered roots give coefficients in the hundreds; the round trip is accurate relative to them
    np.testing.assert_allclose(lsf_to_poly(lsf), a, atol=1e-7 * max(1.0, float(np.abs(a).max())))


@settings(max_examples=150, deadline=None)
@given(stable_polys())
def test_lsfs_interlace_inside_zero_pi(a):
    """Sorted, strictly inside (0, π), P's roots at positions 0, 2, 4…, Q's at 1, 3, 5…"""
    lsf = poly_to_lsf(a)
    assert np.all(lsf > 0) and np.all(lsf < np.pi)
    assert np.all(np.diff(lsf) > 0)
    ext = np.concatenate([a, [0.0]])
    p_angles = np.angle(np.roots(ext + ext[::-1]))
    p_angles = np.sort(p_angles[(p_angles > 1e-9) & (p_angles < np.pi - 1e-9)])
    np.testing.assert_allclose(p_angles, lsf[0::2], atol=1e-6)


@pytest.mark.parametrize("order", [1, 2, 5, 10, 17, 20])
def test_lsf_round_trip_even_and_odd_order_at_both_extremes(order):
    """All poles at the origin (LSFs evenly spaced kπ/(p+1)) and all poles near the unit circle."""
    flat = np.zeros(order + 1)
    flat[0] = 1.0
    np.testing.assert_allclose(poly_to_lsf(flat), np.pi * np.arange(1, order + 1) / (order + 1), atol=1e-9)
    rng = np.random.default_rng(order)
    roots = [0.995 * np.exp(s * 1j * t) for t in rng.uniform(0.05, 3.0, order // 2) for s in (1, -1)]
    if order % 2:
        roots.append(-0.99)
    sharp = np.real(np.poly(roots))
    np.testing.assert_allclose(lsf_to_poly(poly_to_lsf(sharp)), sharp, atol=1e-7)


def test_known_small_cases_by_hand():
    # p = 1: P = 1 + 2a₁z⁻¹ + z⁻², so cos ω = −a₁.  a₁ = −½ → ω = π/3.
    np.testing.assert_allclose(poly_to_lsf(np.array([1.0, -0.5])), [np.pi / 3])
    np.testing.assert_allclose(lsf_to_poly(np.array([np.pi / 3])), [1.0, -0.5], atol=1e-12)
    # p = 2: P = (1 + z⁻¹)(1 + (a₁+a₂−1)z⁻¹ + z⁻²), Q = (1 − z⁻¹)(1 + (a₁−a₂+1)z⁻¹ + z⁻²)
    # a = (1, −0.5, 0.25): cos ω₁ = (1 − a₁ − a₂)/2 = 0.625, cos ω₂ = −(1 + a₁ − a₂)/2 = −0.125
    expected = np.arccos([0.625, -0.125])
    np.testing.assert_allclose(poly_to_lsf(np.array([1.0, -0.5, 0.25])), expected, atol=1e-12)
    np.testing.assert_allclose(lsf_to_poly(expected), [1.0, -0.5, 0.25], atol=1e-12)


def test_lsf_to_poly_is_batched_over_leading_axes():
    rng = np.random.default_rng(0)
    lsf = np.sort(rng.uniform(0.1, 3.0, (2, 3, 6)), axis=-1)
    batch = lsf_to_poly(lsf)
    assert batch.shape == (2, 3, 7)
    np.testing.assert_allclose(batch[1, 2], lsf_to_poly(lsf[1, 2]))
    np.testing.assert_array_equal(lsf_to_poly(np.zeros((4, 0))), np.ones((4, 1)))


@pytest.mark.parametrize(
    "lsf, message",
    [
        ([0.0, 1.0], r"strictly inside \(0, π\)"),
        ([1.0, np.pi], r"strictly inside \(0, π\)"),
        ([-0.5, 1.0], r"strictly inside \(0, π\)"),
        ([np.nan, 1.0], "NaN or Inf"),
        ([1.0, np.inf], "NaN or Inf"),
        ([2.0, 1.0], "increase strictly"),
        ([1.0, 1.0], "increase strictly"),
        (1.0, "at least one axis"),
    ],
)
def test_lsf_to_poly_rejects_bad_lsfs(lsf, message):
    with pytest.raises(ValueError, match=message):
        lsf_to_poly(np.array(lsf))


@pytest.mark.parametrize(
    "a, message",
    [
        ([2.0, 0.5], "monic"),
        ([1.0, -2.0], "not minimum phase"),  # root at z = 2
        ([1.0, 0.0, 1.0], "not minimum phase"),  # roots on the unit circle
        ([[1.0, 0.5]], "1-D"),
    ],
)
def test_poly_to_lsf_rejects_bad_polynomials(a, message):
    with pytest.raises(ValueError, match=message):
        poly_to_lsf(np.array(a))


def test_poles_to_poly_places_conjugate_poles():
    a = poles_to_poly(np.array([100.0, 250.0]), np.array([0.9, 0.5]), 1000.0)
    roots = np.roots(a)
    angles = np.sort(np.abs(np.angle(roots)))
    np.testing.assert_allclose(angles, np.repeat(2 * np.pi * np.array([100.0, 250.0]) / 1000.0, 2), atol=1e-9)
    np.testing.assert_allclose(np.sort(np.abs(roots)), [0.5, 0.5, 0.9, 0.9], atol=1e-9)


@pytest.mark.parametrize(
    "freqs, radii, message",
    [
        ([0.0], [0.5], "frequencies"),
        ([500.0], [0.5], "frequencies"),
        ([100.0], [1.0], "radii"),
        ([100.0, 200.0], [0.5], "equal length"),
    ],
)
def test_poles_to_poly_rejects_bad_poles(freqs, radii, message):
    with pytest.raises(ValueError, match=message):
        poles_to_poly(np.array(freqs), np.array(radii), 1000.0)
