import numpy as np
import pytest

from models.visual.patches import check_patch_batch, extract_patches, patch_origins


def test_origins_span_the_axis_evenly():
    origins = patch_origins(1024, 224, 7)
    assert origins[0] == 0 and origins[-1] == 1024 - 224
    np.testing.assert_array_equal(origins, [0, 133, 267, 400, 533, 667, 800])
    # overlapping: the stride is smaller than the patch
    assert np.all(np.diff(origins) < 224)


def test_patches_are_the_grid_slices_row_major():
    img = np.random.default_rng(0).random((1024, 1024)).astype(np.float32)
    patches = extract_patches(img)
    assert patches.shape == (49, 224, 224) and patches.dtype == np.float32
    origins = patch_origins(1024, 224, 7)
    for k in (0, 6, 7, 24, 48):
        r, c = origins[k // 7], origins[k % 7]
        np.testing.assert_array_equal(patches[k], img[r : r + 224, c : c + 224])
    # the last patch is flush with the bottom-right corner
    np.testing.assert_array_equal(patches[-1], img[-224:, -224:])


def test_rectangular_image_and_small_grid():
    img = np.random.default_rng(1).random((300, 500)).astype(np.float32)
    patches = extract_patches(img, size=100, grid=3)
    assert patches.shape == (9, 100, 100)
    np.testing.assert_array_equal(patches[2], img[0:100, 400:500])
    np.testing.assert_array_equal(patches[4], img[100:200, 200:300])
    np.testing.assert_array_equal(patches[8], img[200:300, 400:500])


def test_image_exactly_one_patch_repeats_it():
    img = np.random.default_rng(2).random((224, 224)).astype(np.float32)
    patches = extract_patches(img)
    assert np.all(patches == img[None])


def test_grid_of_one_is_centred():
    img = np.arange(300 * 300, dtype=np.float32).reshape(300, 300)
    (patch,) = extract_patches(img, size=224, grid=1)
    np.testing.assert_array_equal(patch, img[38:262, 38:262])


def test_too_small_or_not_2d_raises():
    with pytest.raises(ValueError, match="smaller than one 224×224 patch"):
        extract_patches(np.zeros((223, 500), dtype=np.float32))
    with pytest.raises(ValueError, match="2-D"):
        extract_patches(np.zeros((300, 300, 3), dtype=np.float32))
    with pytest.raises(ValueError, match="grid"):
        patch_origins(300, 224, 0)


def test_check_patch_batch():
    ok = np.random.default_rng(3).random((2, 224, 224))
    out = check_patch_batch(ok, 224)
    assert out.dtype == np.float32 and out.flags.c_contiguous
    assert check_patch_batch(np.zeros((0, 224, 224), np.float32), 224).shape == (0, 224, 224)
    with pytest.raises(ValueError, match=r"shape \(n, 224, 224\)"):
        check_patch_batch(np.zeros((2, 200, 224), np.float32), 224)
    with pytest.raises(ValueError, match="dtype"):
        check_patch_batch(np.zeros((2, 224, 224), np.uint8), 224)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        check_patch_batch(np.full((1, 224, 224), -0.1, np.float32), 224)
    with pytest.raises(ValueError, match="numpy array"):
        check_patch_batch([[0.0]], 224)
