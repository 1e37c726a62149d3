"""scene_change: a camera looking at one surface is one scene; another surface, a moved view or a change of light is not."""

from __future__ import annotations

import numpy as np
import pytest

from service.scene_change import frame_difference, scene_changed, thumbnail


def test_thumbnail_is_the_block_means():
    gray = np.zeros((32, 48), np.float32)
    gray[:16, :24] = 1.0  # top-left quarter white
    t = thumbnail(gray, size=2)
    assert t.shape == (2, 2) and np.allclose(t, [[1, 0], [0, 0]])
    with pytest.raises(ValueError, match="H, W ≥ 16"):
        thumbnail(np.zeros((8, 300)))
    with pytest.raises(ValueError, match="shape"):
        thumbnail(np.zeros((300, 300, 3)))


def test_noise_is_the_same_scene_another_surface_is_not():
    rng = np.random.default_rng(0)
    surface = np.kron(rng.uniform(0.2, 0.8, size=(14, 14)), np.ones((32, 32))).astype(np.float32)  # coarse texture
    noisy = np.clip(surface + rng.normal(0, 0.03, surface.shape), 0, 1).astype(np.float32)  # sensor noise
    other = np.kron(rng.uniform(0.2, 0.8, size=(14, 14)), np.ones((32, 32))).astype(np.float32)
    darker = surface * 0.7
    a, b = thumbnail(surface), thumbnail(noisy)
    assert frame_difference(a, b) < 0.01
    assert not scene_changed(a, b, 0.05)
    assert scene_changed(a, thumbnail(other), 0.05)
    assert scene_changed(a, thumbnail(darker), 0.05)  # the light changed
    assert scene_changed(None, a, 0.05)  # no scene yet
    assert scene_changed(a, b, 0.0) == (frame_difference(a, b) > 0)
    with pytest.raises(ValueError, match="threshold"):
        scene_changed(a, b, 2.0)
    with pytest.raises(ValueError, match="same shape"):
        frame_difference(a, thumbnail(surface, size=8))
