"""Pooling the feature vectors of several views (augmented views in training, camera frames in the service)."""

import numpy as np
import pytest

from models.visual.pooling import ViewPool, pool_texture_views, pool_views


def test_pool_is_the_mean_over_views():
    views = np.array([[1.0, 2.0, 3.0], [3.0, 2.0, -1.0]], np.float32)
    pooled = pool_views(views)
    assert pooled.dtype == np.float32 and pooled.shape == (3,)
    np.testing.assert_array_equal(pooled, [2.0, 2.0, 1.0])


def test_one_view_passes_through_and_order_does_not_matter():
    rng = np.random.default_rng(0)
    views = rng.normal(size=(8, 16)).astype(np.float32)
    np.testing.assert_array_equal(pool_views(views[:1]), views[0])
    np.testing.assert_allclose(pool_views(views[::-1]), pool_views(views), rtol=1e-6)


def test_texture_views_pool_the_first_k():
    rng = np.random.default_rng(1)
    visual = rng.normal(size=(3, 8, 5)).astype(np.float32)
    pooled = pool_texture_views(visual, 4)
    assert pooled.shape == (3, 5)
    np.testing.assert_allclose(pooled[2], visual[2, :4].mean(axis=0), rtol=1e-6)
    with pytest.raises(ValueError, match=r"views must lie in 1…8"):
        pool_texture_views(visual, 9)
    with pytest.raises(ValueError, match=r"\(textures, views, D\)"):
        pool_texture_views(visual[0], 1)


def test_running_pool_equals_pooling_the_latest_frames():
    rng = np.random.default_rng(2)
    frames = rng.normal(size=(7, 6)).astype(np.float32)
    pool = ViewPool(max_views=4)
    for i, f in enumerate(frames):
        pool.add(f)
        np.testing.assert_allclose(pool.value(), pool_views(frames[max(0, i - 3) : i + 1]), rtol=1e-6)
    assert len(pool) == 4
    pool.reset()
    with pytest.raises(ValueError, match="no view has been added"):
        pool.value()


@pytest.mark.parametrize(
    "bad, message",
    [
        (np.zeros(5, np.float32), r"must be \(k, D\)"),
        (np.zeros((0, 5), np.float32), "at least one view"),
        (np.zeros((2, 3), np.int64), "must be float"),
        (np.array([[1.0, np.nan]], np.float32), "NaN or Inf"),
    ],
)
def test_bad_input_is_refused_with_the_reason(bad, message):
    with pytest.raises(ValueError, match=message):
        pool_views(bad)


def test_running_pool_refuses_a_frame_of_another_width():
    pool = ViewPool(2)
    pool.add(np.zeros(4, np.float32))
    with pytest.raises(ValueError, match="width 5 does not match the pool's 4"):
        pool.add(np.zeros(5, np.float32))
    with pytest.raises(ValueError, match="max_views must be ≥ 1"):
        ViewPool(0)
