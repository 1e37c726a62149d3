import numpy as np
import pytest

from models.visual.glcm import glcm, glcm_features, offset, quantize

ALL_ANGLES = (0.0, 45.0, 90.0, 135.0)


def _naive_glcm(img, levels, distances, angles):
    """Reference: explicit loops over pixels, symmetric, normalised per offset, averaged."""
    q = np.minimum((img * levels).astype(int), levels - 1)
    h, w = q.shape
    mats = []
    for d in distances:
        for a in angles:
            dr, dc = int(round(d * np.sin(np.deg2rad(a)))), int(round(d * np.cos(np.deg2rad(a))))
            m = np.zeros((levels, levels))
            for r in range(h):
                for c in range(w):
                    rr, cc = r + dr, c + dc
                    if 0 <= rr < h and 0 <= cc < w:
                        m[q[r, c], q[rr, cc]] += 1
                        m[q[rr, cc], q[r, c]] += 1
            mats.append(m / m.sum())
    return np.mean(mats, axis=0)


def test_quantize_bins():
    values = np.array([[0.0, 0.0624, 0.0625, 0.5, 0.9999, 1.0]])
    np.testing.assert_array_equal(quantize(values, 16), [[0, 0, 1, 8, 15, 15]])


def test_offsets_follow_skimage_convention():
    assert offset(1, 0) == (0, 1)
    assert offset(1, 45) == (1, 1)
    assert offset(1, 90) == (1, 0)
    assert offset(1, 135) == (1, -1)
    assert offset(3, 90) == (3, 0)


def test_constant_image_puts_all_mass_in_one_cell():
    matrix = glcm(np.full((40, 30), 0.5))
    expected = np.zeros((16, 16))
    expected[8, 8] = 1.0
    np.testing.assert_allclose(matrix, expected)


def test_vertical_stripes_by_direction():
    # columns alternate level 0 and level 15, an even number of each
    img = np.tile(np.array([0.0, 1.0]), (20, 16))
    across = np.zeros((16, 16))
    across[0, 15] = across[15, 0] = 0.5
    along = np.zeros((16, 16))
    along[0, 0] = along[15, 15] = 0.5
    np.testing.assert_allclose(glcm(img, angles=(0.0,)), across)  # horizontal neighbours differ
    np.testing.assert_allclose(glcm(img, angles=(90.0,)), along)  # vertical neighbours match
    np.testing.assert_allclose(glcm(img, angles=(45.0,)), across)  # diagonal neighbours differ
    # averaged over the four directions: 3 of 4 offsets cross the stripes
    np.testing.assert_allclose(glcm(img), 0.75 * across + 0.25 * along)


def test_random_image_matrix_is_a_symmetric_distribution():
    img = np.random.default_rng(0).random((64, 48))
    matrix = glcm(img, distances=(1, 2))
    assert matrix.shape == (16, 16)
    assert np.all(matrix >= 0)
    np.testing.assert_allclose(matrix.sum(), 1.0, atol=1e-12)
    np.testing.assert_allclose(matrix, matrix.T, atol=1e-15)


def test_matches_naive_reference():
    img = np.random.default_rng(1).random((23, 17))
    for levels, distances in ((16, (1,)), (8, (2, 3))):
        np.testing.assert_allclose(
            glcm(img, levels, distances, ALL_ANGLES), _naive_glcm(img, levels, distances, ALL_ANGLES), atol=1e-12
        )


def test_features_are_the_flat_matrix():
    img = np.random.default_rng(2).random((50, 50))
    features = glcm_features(img)
    assert features.shape == (256,) and features.dtype == np.float32
    np.testing.assert_allclose(features.reshape(16, 16), glcm(img), atol=1e-7)


def test_invalid_inputs_raise():
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        glcm(np.full((10, 10), 2.0))
    with pytest.raises(ValueError, match="non-finite"):
        glcm(np.full((10, 10), np.nan))
    with pytest.raises(ValueError, match="no pixel pairs"):
        glcm(np.zeros((4, 4)), distances=(5,))
    with pytest.raises(ValueError, match="distances must be ≥ 1"):
        glcm(np.zeros((4, 4)), distances=(0,))
    with pytest.raises(ValueError, match="non-empty"):
        glcm(np.zeros((4, 4)), angles=())
    with pytest.raises(ValueError, match="2-D"):
        glcm(np.zeros((4, 4, 3)))
