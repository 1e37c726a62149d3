"""The synthetic world: documented ground truth, rater noise, images, and the physics → signal link."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.signal import welch

from texture_library.attributes import ATTRIBUTES, check_ratings
from texture_library.procedural import (
    PARAM_RANGES,
    make_world,
    rater_ratings,
    render_image,
    sample_params,
    true_ratings,
    vibration_model,
)
from texture_library.synthesis import render

RS, FB, SS, HS = range(4)  # rough_smooth, flat_bumpy, sticky_slippery, hard_soft


def test_neutral_points_rate_zero(params):
    """roughness 15 µm, bumps 0.5 mm, μ 0.6, stiffness 1 N/mm are the documented midpoints."""
    np.testing.assert_allclose(true_ratings(params), 0.0, atol=1e-12)


@pytest.mark.parametrize(
    "change, attribute, expected",
    [
        ({"roughness_um": 150.0}, RS, -100 * np.tanh(1.0)),  # log10(150/15) = 1
        ({"roughness_um": 1.5}, RS, 100 * np.tanh(1.0)),
        ({"bump_height_mm": 1.0}, FB, 100 * np.tanh(0.75)),
        ({"bump_height_mm": 0.0}, FB, -100 * np.tanh(0.75)),
        ({"mu": 1.0}, SS, -100 * np.tanh(0.8)),
        ({"mu": 0.2}, SS, 100 * np.tanh(0.8)),
        ({"stiffness_n_per_mm": 10.0}, HS, -100 * np.tanh(0.9)),
        ({"stiffness_n_per_mm": 0.1}, HS, 100 * np.tanh(0.9)),
    ],
)
def test_true_ratings_follow_the_documented_formulas(params, change, attribute, expected):
    truth = true_ratings(dataclasses.replace(params, **change))
    assert truth[attribute] == pytest.approx(expected)
    others = [a for a in range(4) if a != attribute]
    np.testing.assert_allclose(truth[others], 0.0, atol=1e-12)  # each parameter drives one attribute


@pytest.mark.parametrize(
    "name, attribute, sign",
    [("roughness_um", RS, -1), ("bump_height_mm", FB, +1), ("mu", SS, -1), ("stiffness_n_per_mm", HS, -1)],
)
def test_true_ratings_are_monotonic_in_their_parameter(params, name, attribute, sign):
    lo, hi, log = PARAM_RANGES[name]
    grid = np.geomspace(lo, hi, 40) if log else np.linspace(lo, hi, 40)
    values = np.array([true_ratings(dataclasses.replace(params, **{name: v}))[attribute] for v in grid])
    assert np.all(sign * np.diff(values) > 0)
    check_ratings(values[:, None].repeat(4, axis=1))  # always inside ±100


def test_grain_period_and_albedo_do_not_change_the_truth(params):
    """Albedo is perceptually irrelevant on purpose."""
    base = true_ratings(params)
    for change in ({"albedo": 0.7}, {"grain_mm": 2.5}, {"bump_period_mm": 14.0}):
        np.testing.assert_array_equal(true_ratings(dataclasses.replace(params, **change)), base)


def test_rater_ratings_are_integers_in_range_centred_on_the_truth():
    truth = np.array([-95.0, -20.0, 0.0, 60.0])
    ratings = rater_ratings(truth, 4000, np.random.default_rng(0))
    assert ratings.shape == (4000, 4)
    np.testing.assert_array_equal(ratings, np.round(ratings))
    assert ratings.min() >= -100 and ratings.max() <= 100
    # the mean approaches the truth (−95 is pulled in by clipping at −100, so allow more there)
    np.testing.assert_allclose(ratings.mean(axis=0)[1:], truth[1:], atol=1.0)
    assert ratings.mean(axis=0)[0] == pytest.approx(-95.0, abs=3.0)
    assert 8.0 < ratings[:, 2].std() < 16.0  # √(6² + 10²) ≈ 11.7


def test_rater_ratings_need_a_rater():
    with pytest.raises(ValueError, match="n_raters must be ≥ 1"):
        rater_ratings(np.zeros(4), 0, np.random.default_rng(0))


def test_sample_params_stay_inside_their_ranges():
    rng = np.random.default_rng(0)
    for _ in range(200):
        p = sample_params(rng).to_dict()
        for name, (lo, hi, _) in PARAM_RANGES.items():
            assert lo <= p[name] <= hi, name


@pytest.mark.parametrize("size", [32, 100, 224])
def test_images_are_uint8_of_the_requested_size(params, size):
    img = render_image(params, np.random.default_rng(0), size)
    assert img.dtype == np.uint8 and img.shape == (size, size)
    assert img.std() > 5  # it has texture, not a flat grey


def test_image_size_is_checked(params):
    with pytest.raises(ValueError, match="image size must be ≥ 32 px"):
        render_image(params, np.random.default_rng(0), 16)


def test_vibration_models_are_valid_and_carry_their_physics(params):
    model = vibration_model(params, "t", np.random.default_rng(0))
    assert model.speeds.size == 25 and model.triangles.shape == (32, 3)
    assert model.mu == params.mu
    assert model.extra["physical"] == params.to_dict()
    assert model.taps is not None and model.taps.accel.shape == (10, 100)
    np.testing.assert_array_equal(model.variance[model.speeds == 0], 0.0)  # no sliding, no vibration


def _render(params, n=8000, speed=150.0, force=2.0, seed=0):
    model = vibration_model(params, "t", np.random.default_rng(0))
    return render(model, np.full(n, speed), np.full(n, force), np.random.default_rng(seed))


def test_rougher_textures_vibrate_more_at_the_same_speed_and_force(params):
    rms = [_render(dataclasses.replace(params, roughness_um=r)).std() for r in (3.0, 15.0, 80.0)]
    assert rms[0] < rms[1] < rms[2]


def test_faster_and_harder_pressed_strokes_vibrate_more(params):
    assert _render(params, speed=60.0).std() < _render(params, speed=250.0).std()
    assert _render(params, force=0.5).std() < _render(params, force=4.0).std()


def _centroid_hz(x: np.ndarray) -> float:
    f, pxx = welch(x, fs=1000.0, nperseg=512)
    return float(np.sum(f * pxx) / np.sum(pxx))


def test_stiffer_textures_ring_at_higher_frequency(params):
    """The contact resonance rises with stiffness, and so does the spectral centroid."""
    soft, hard = (
        _render(dataclasses.replace(params, stiffness_n_per_mm=k, roughness_um=40.0, bump_height_mm=0.1))
        for k in (0.1, 30.0)
    )
    assert _centroid_hz(hard) > _centroid_hz(soft) + 50.0


def test_make_world_is_deterministic_for_a_seed():
    a, b = make_world(3, seed=4, n_raters=5, image_size=64), make_world(3, seed=4, n_raters=5, image_size=64)
    c = make_world(3, seed=5, n_raters=5, image_size=64)
    for x, y in zip(a, b):
        assert x.texture_id == y.texture_id and x.params == y.params and x.group == y.group
        np.testing.assert_array_equal(x.image, y.image)
        np.testing.assert_array_equal(x.ratings, y.ratings)
        np.testing.assert_array_equal(x.model.ar_lsf, y.model.ar_lsf)
    assert [t.texture_id for t in a] == ["synth_000", "synth_001", "synth_002"]
    assert a[0].params != c[0].params
    for tex in a:
        np.testing.assert_array_equal(tex.truth, true_ratings(tex.params))
        assert tex.ratings.shape == (5, len(ATTRIBUTES))


def test_make_world_needs_a_texture():
    with pytest.raises(ValueError, match="n_textures must be ≥ 1"):
        make_world(0)
