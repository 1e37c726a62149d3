"""scene_change: a camera looking at one surface is one scene; another surface (even of the same brightness), a moved
view or a change of light is not."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.scene_change import (
    THUMBNAIL_BYTES,
    frame_difference,
    scene_changed,
    thumbnail,
    thumbnail_bytes,
    thumbnail_from_bytes,
)


def test_thumbnail_is_the_block_means_and_standard_deviations():
    gray = np.zeros((32, 48), np.float32)
    gray[:16, :24] = 1.0  # top-left quarter white
    gray[16:, 24:][::2] = 1.0  # bottom-right quarter: white and black rows, mean 0.5, sd 0.5
    t = thumbnail(gray, size=2)
    assert t.shape == (2, 2, 2)
    assert np.allclose(t[0], [[1, 0], [0, 0.5]]) and np.allclose(t[1], [[0, 0], [0, 0.5]])
    rng = np.random.default_rng(0)
    for shape, size in (((448, 448), 16), ((481, 307), 16), ((64, 64), 4)):  # the rows and columns that do not fill
        image = rng.uniform(0, 1, shape).astype(np.float32)  # a block are left out
        h, w = shape[0] // size * size, shape[1] // size * size
        blocks = image[:h, :w].reshape(size, h // size, size, w // size)
        expected = np.stack([blocks.mean(axis=(1, 3)), blocks.std(axis=(1, 3))])
        np.testing.assert_allclose(thumbnail(image, size), expected, rtol=0, atol=1e-6)
    assert thumbnail(gray.astype(np.float64), size=2).dtype == np.float32
    with pytest.raises(ValueError, match="H, W ≥ 16"):
        thumbnail(np.zeros((8, 300)))
    with pytest.raises(ValueError, match="shape"):
        thumbnail(np.zeros((300, 300, 3)))


def test_noise_is_the_same_scene_another_surface_is_not():
    rng = np.random.default_rng(0)
    camera = lambda img: np.clip(img + rng.normal(0, 0.03, img.shape), 0, 1).astype(np.float32)  # noqa: E731
    surface = np.kron(rng.uniform(0.2, 0.8, size=(14, 14)), np.ones((32, 32))).astype(np.float32)  # coarse texture
    other = np.kron(rng.uniform(0.2, 0.8, size=(14, 14)), np.ones((32, 32))).astype(np.float32)
    # the same mean brightness everywhere, another grain: block means cannot tell, block deviations can
    fine = np.tile(np.array([[0.3, 0.7], [0.7, 0.3]], np.float32), (224, 224))
    flat = np.full((448, 448), 0.5, np.float32)
    a, b = thumbnail(camera(surface)), thumbnail(camera(surface))  # two frames of one surface, one camera
    assert frame_difference(a, b) < 0.005
    assert not scene_changed(a, b, 0.015)
    assert scene_changed(a, thumbnail(camera(other)), 0.015)
    assert scene_changed(a, thumbnail(camera(surface * 0.7)), 0.015)  # the light changed
    assert np.allclose(thumbnail(fine)[0], thumbnail(flat)[0])
    assert scene_changed(thumbnail(camera(fine)), thumbnail(camera(flat)), 0.015)
    assert scene_changed(None, a, 0.015)  # no scene yet
    assert scene_changed(a, b, 0.0) == (frame_difference(a, b) > 0)
    with pytest.raises(ValueError, match="threshold"):
        scene_changed(a, b, 3.0)
    with pytest.raises(ValueError, match="same shape"):
        frame_difference(a, thumbnail(surface, size=8))


def test_a_thumbnail_round_trips_through_its_wire_bytes():
    thumb = thumbnail(np.random.default_rng(0).uniform(0, 1, (64, 48)))
    payload = thumbnail_bytes(thumb)
    assert len(payload) == THUMBNAIL_BYTES == 2048
    assert payload[:4] == np.float32(thumb[0, 0, 0]).astype("<f4").tobytes(), "little-endian float32, means first"
    np.testing.assert_array_equal(thumbnail_from_bytes(payload), thumb)


@pytest.mark.parametrize(
    ("payload", "message"),
    [
        (b"\x00" * 2047, "2048 bytes"),
        (b"", "got 0"),
        (np.full((2, 16, 16), np.inf, "<f4").tobytes(), "finite grey levels"),
        (np.full((2, 16, 16), -0.5, "<f4").tobytes(), "in \\[0, 1\\]"),
    ],
)
def test_thumbnail_bytes_that_are_no_thumbnail_are_refused_with_the_reason(payload, message):
    with pytest.raises(ValueError, match=message):
        thumbnail_from_bytes(payload)
    with pytest.raises(ValueError, match="shape"):
        thumbnail_bytes(np.zeros((16, 16), np.float32))
