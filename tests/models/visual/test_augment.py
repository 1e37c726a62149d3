import numpy as np
import pytest

from models.visual.augment import IDENTITY_VIEW, VIEW_KEYS, apply_view, augmented_views, view_params


def _view(**changes):
    params = dict(IDENTITY_VIEW)
    params.update(changes)
    return params


def test_view_zero_is_the_original(texture):
    views = augmented_views(texture, 4, seed=3)
    assert len(views) == 4
    np.testing.assert_array_equal(views[0], texture)
    assert view_params(4, 3)[0] == IDENTITY_VIEW


def test_params_are_deterministic_and_prefix_stable():
    assert view_params(5, 7) == view_params(5, 7)
    assert view_params(5, 7)[:3] == view_params(3, 7)
    assert view_params(3, 7)[1:] != view_params(3, 8)[1:]
    for params in view_params(20, 0):
        assert set(params) == set(VIEW_KEYS)
        assert params["rot90"] in (0, 1, 2, 3)
        assert abs(params["angle_deg"]) <= 15.0
        assert 0.0 <= params["noise_std"] <= 0.02


def test_views_are_reproducible(texture):
    first = augmented_views(texture, 3, seed=11)
    again = augmented_views(texture, 3, seed=11)
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a, b)
    assert all(v.dtype == np.float32 and v.min() >= 0 and v.max() <= 1 for v in first)


def test_quarter_turns_and_flips_are_exact():
    img = np.random.default_rng(0).random((30, 40)).astype(np.float32)
    turned = apply_view(img, _view(rot90=1))
    assert turned.shape == (40, 30)
    np.testing.assert_array_equal(turned, np.rot90(img))
    np.testing.assert_array_equal(apply_view(img, _view(flip=True)), img[:, ::-1])
    np.testing.assert_array_equal(apply_view(img, _view(rot90=2, flip=True)), np.rot90(img, 2)[:, ::-1])


def test_small_rotation_reflects_borders():
    constant = np.full((50, 60), 0.3, dtype=np.float32)
    rotated = apply_view(constant, _view(angle_deg=7.5))
    assert rotated.shape == (50, 60)
    np.testing.assert_allclose(rotated, 0.3, atol=1e-6)  # no black corners
    img = np.random.default_rng(1).random((50, 60)).astype(np.float32)
    assert not np.allclose(apply_view(img, _view(angle_deg=7.5)), img)


def test_noise_has_the_requested_std():
    grey = np.full((200, 200), 0.5, dtype=np.float32)
    noisy = apply_view(grey, _view(noise_std=0.02, noise_seed=5))
    assert abs(float(np.std(noisy - grey)) - 0.02) < 0.001
    np.testing.assert_array_equal(noisy, apply_view(grey, _view(noise_std=0.02, noise_seed=5)))


def test_invalid_arguments_raise(texture):
    with pytest.raises(ValueError, match="n_views"):
        view_params(0, 0)
    with pytest.raises(ValueError, match="keys"):
        apply_view(texture, {"rot90": 1})
    with pytest.raises(ValueError, match="2-D"):
        apply_view(np.zeros((4, 4, 3)), IDENTITY_VIEW)
