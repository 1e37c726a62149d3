"""Rendering a vibration model: barycentric LSF interpolation and the time-varying ARMA filter."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter

from texture_library.lsf import lsf_to_poly
from texture_library.synthesis import barycentric, interpolate, render


def vertex_arma(model, k):
    """(AR, gain·MA, variance) of grid point k, straight from the model."""
    return lsf_to_poly(model.ar_lsf[k]), model.gain[k] * lsf_to_poly(model.ma_lsf[k]), model.variance[k]


def test_barycentric_weights_sum_to_one_and_reproduce_the_point(model):
    rng = np.random.default_rng(0)
    speed, force = rng.uniform(0, 200, 500), rng.uniform(0, 4, 500)
    idx, w = barycentric(model, speed, force)
    assert idx.shape == w.shape == (500, 3)
    np.testing.assert_allclose(w.sum(axis=1), 1.0)
    assert np.all(w >= 0)
    # linear precision: the weighted grid points are the query point itself
    np.testing.assert_allclose((w * model.speeds[idx]).sum(axis=1), speed, atol=1e-9)
    np.testing.assert_allclose((w * model.forces[idx]).sum(axis=1), force, atol=1e-9)


@pytest.mark.parametrize("k", range(9))
def test_barycentric_at_a_vertex_puts_all_weight_on_it(model, k):
    idx, w = barycentric(model, model.speeds[k : k + 1], model.forces[k : k + 1])
    np.testing.assert_allclose(w[0][idx[0] == k].sum(), 1.0, atol=1e-12)


def test_points_outside_the_grid_are_clamped_to_its_range(model):
    outside = barycentric(model, np.array([-50.0, 500.0, 150.0]), np.array([-1.0, 9.0, 7.0]))
    edge = barycentric(model, np.array([0.0, 200.0, 150.0]), np.array([0.0, 4.0, 4.0]))
    for a, b in zip(interpolate_at(model, *outside), interpolate_at(model, *edge)):
        np.testing.assert_allclose(a, b)


def interpolate_at(model, idx, w):
    return (w * model.speeds[idx]).sum(axis=1), (w * model.forces[idx]).sum(axis=1)


def test_interpolate_mixes_lsfs_not_coefficients(model):
    """Midway between two grid points the AR polynomial comes from the averaged LSFs."""
    params = interpolate(model, np.array([50.0]), np.array([0.0]))  # on the edge between points 0 and 3
    lsf_mid = 0.5 * (model.ar_lsf[0] + model.ar_lsf[3])
    np.testing.assert_allclose(params["ar"][0], lsf_to_poly(lsf_mid), atol=1e-12)
    np.testing.assert_allclose(params["variance"][0], 0.5 * (model.variance[0] + model.variance[3]))
    assert np.all(np.abs(np.roots(params["ar"][0])) < 1)  # still stable


@pytest.mark.parametrize("k", [4, 5, 8])  # interior, edge, corner
def test_render_at_a_grid_vertex_is_that_vertex_arma_filter(model, k):
    """Known answer: at a fixed (speed, force) on a vertex, render = lfilter(gain·ma, ar, √var·e)."""
    n = 3000
    e = np.random.default_rng(1).standard_normal(n)
    out = render(model, np.full(n, model.speeds[k]), np.full(n, model.forces[k]), excitation=e)
    ar, ma, var = vertex_arma(model, k)
    np.testing.assert_allclose(out, lfilter(ma, ar, np.sqrt(var) * e), rtol=1e-8, atol=1e-10)


def test_render_draws_its_excitation_from_the_rng(model):
    """rng-driven render is the same as passing rng.standard_normal(n) explicitly."""
    n = 1000
    speed, force = np.linspace(20, 180, n), np.linspace(0.5, 3.5, n)
    a = render(model, speed, force, np.random.default_rng(5))
    b = render(model, speed, force, excitation=np.random.default_rng(5).standard_normal(n))
    np.testing.assert_array_equal(a, b)


def test_zero_speed_renders_silence(model):
    out = render(model, np.zeros(500), np.full(500, 2.0), np.random.default_rng(0))
    np.testing.assert_array_equal(out, 0.0)


def test_output_variance_tracks_the_model_variance(model):
    """Over a long render the output variance is var·Σh² of the interpolated ARMA filter."""
    n, speed, force = 60_000, 150.0, 3.0
    out = render(model, np.full(n, speed), np.full(n, force), np.random.default_rng(2))
    p = interpolate(model, np.array([speed]), np.array([force]))
    impulse = np.zeros(4096)
    impulse[0] = 1.0
    h = lfilter(p["gain"][0] * p["ma"][0], p["ar"][0], impulse)
    expected = p["variance"][0] * np.sum(h**2)
    assert out[1000:].var() == pytest.approx(expected, rel=0.08)


def test_louder_where_the_model_is_louder(model):
    n = 20_000
    quiet = render(model, np.full(n, 50.0), np.full(n, 1.0), np.random.default_rng(3))
    loud = render(model, np.full(n, 200.0), np.full(n, 4.0), np.random.default_rng(3))
    assert loud.std() > 3 * quiet.std()


def test_render_is_deterministic_for_a_seed(model):
    speed, force = np.linspace(0, 200, 2000), np.linspace(0, 4, 2000)
    a = render(model, speed, force, np.random.default_rng(7))
    b = render(model, speed, force, np.random.default_rng(7))
    c = render(model, speed, force, np.random.default_rng(8))
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


@pytest.mark.parametrize(
    "speed, force, kwargs, message",
    [
        (np.zeros(5), np.zeros(4), {}, "1-D of equal length"),
        (np.zeros((5, 1)), np.zeros((5, 1)), {}, "1-D of equal length"),
        (np.array([1.0, np.nan]), np.zeros(2), {}, "finite"),
        (np.zeros(5), np.zeros(5), {"excitation": np.zeros(4)}, r"excitation must have shape \(5,\)"),
        (np.zeros(5), np.zeros(5), {"rng": None}, "needs an rng or an explicit excitation"),
    ],
)
def test_render_rejects_bad_input(model, speed, force, kwargs, message):
    kwargs = {"rng": np.random.default_rng(0), **kwargs}
    with pytest.raises(ValueError, match=message):
        render(model, speed, force, **kwargs)


def test_render_of_nothing_is_empty(model):
    assert render(model, np.zeros(0), np.zeros(0), np.random.default_rng(0)).shape == (0,)
