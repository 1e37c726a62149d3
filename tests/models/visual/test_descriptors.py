"""Known-answer tests of the texture descriptors, and their place in visual_features."""

from __future__ import annotations

import numpy as np
import pytest

from models.visual.config import VisualConfig
from models.visual.descriptors import (
    colour_statistics,
    descriptor_vector,
    grid_statistics,
    lbp_codes,
    lbp_histograms,
    radial_power_spectrum,
    scattering_dim,
    scattering_features,
    zoom_to,
)


def test_lbp_of_a_flat_image_is_all_neighbours_at_least_the_centre():
    hist = lbp_histograms(np.full((12, 12), 0.3), radii=(1, 2), points=8)
    expected = np.zeros(10)
    expected[8] = 1.0  # every neighbour ≥ centre: the uniform code P
    np.testing.assert_array_equal(hist, np.concatenate([expected, expected]))


def test_lbp_of_vertical_stripes():
    # period-2 stripes, 4 neighbours at radius 1: a bright pixel sees dark left/right and bright up/down
    # (1, 0, 1, 0: 4 transitions, non-uniform → P + 1); a dark one sees every neighbour ≥ it (code P)
    stripes = np.tile(np.array([[0.0, 1.0]]), (8, 4))
    codes = lbp_codes(stripes, radius=1, points=4)
    assert set(np.unique(codes)) == {4, 5}
    np.testing.assert_array_equal(lbp_histograms(stripes, (1,), 4), [0, 0, 0, 0, 0.5, 0.5])


def test_lbp_is_rotation_invariant_for_quarter_turns():
    img = np.random.default_rng(0).random((40, 40))
    np.testing.assert_allclose(lbp_histograms(img, (1, 2)), lbp_histograms(np.rot90(img), (1, 2)))


def test_spectrum_puts_a_sinusoid_in_its_octave():
    n = 256
    x = np.arange(n)
    f = 0.1  # cycles/px: in the octave [0.0625, 0.125), band 2 (finest first: [0.25, 0.5), [0.125, 0.25), …)
    img = 0.5 + 0.4 * np.sin(2 * np.pi * f * x)[None, :].repeat(n, axis=0)
    out = radial_power_spectrum(img, n_bands=6)
    fractions = out[2:]
    assert np.argmax(fractions) == 2 and fractions[2] > 0.95
    np.testing.assert_allclose(fractions.sum(), 1.0)


def test_spectrum_slope_of_brown_noise_is_minus_two():
    # power ∝ f^-2 (amplitude ∝ 1/f) → a log-log slope of −2
    n = 256
    rng = np.random.default_rng(0)
    fy, fx = np.fft.fftfreq(n)[:, None], np.fft.fftfreq(n)[None, :]
    r = np.sqrt(fx**2 + fy**2)
    r[0, 0] = 1.0
    spectrum = (rng.normal(size=(n, n)) + 1j * rng.normal(size=(n, n))) / r
    img = np.real(np.fft.ifft2(spectrum))
    img = (img - img.min()) / (img.max() - img.min())
    assert radial_power_spectrum(img, n_bands=5)[0] == pytest.approx(-2.0, abs=0.25)


def test_colour_of_a_uniform_patch():
    rgb = np.empty((8, 8, 3))
    rgb[...] = (0.2, 0.4, 0.6)
    out = colour_statistics(rgb)
    np.testing.assert_allclose(out[:3], [0.2, 0.4, 0.6])
    np.testing.assert_allclose(out[3:6], 0, atol=1e-12)
    np.testing.assert_allclose(out[6:10], [-0.2, 0, -0.3, 0], atol=1e-12)  # rg = R − G, yb = (R+G)/2 − B
    np.testing.assert_allclose(out[10:12], [2 / 3, 0], atol=1e-12)  # saturation (max − min) / max
    np.testing.assert_allclose(out[12], np.hypot(0.2, 0.3))


def test_colour_refuses_a_gray_array():
    with pytest.raises(ValueError, match=r"rgb must be an \(H, W, 3\) array"):
        colour_statistics(np.zeros((8, 8)))


def test_grids_of_four_quadrants():
    img = np.zeros((8, 8))
    img[:4, 4:] = 1.0
    img[4:, :4] = 1.0
    out = grid_statistics(img, scales=(1, 2))
    # one cell: no spread of means, within-cell std 0.5; four uniform quadrants: means 0,1,1,0 (std 0.5), stds 0
    np.testing.assert_allclose(out, [0.0, 0.5, 0.0, 0.5, 0.0, 0.0])


def test_scattering_of_a_flat_image_has_only_the_mean():
    out = scattering_features(np.full((64, 64), 0.5), J=3, L=8)
    assert out.shape == (scattering_dim(3, 8),) == (28,)
    # order 0: the low-passed mean 0.5; wavelets have zero mean, so orders 1 and 2 are ≈ 0 (log of the floor)
    assert out[0] == pytest.approx(np.log(0.5 + 1e-6), abs=1e-3)
    assert np.all(out[1:] < np.log(1e-4))


def test_scattering_reads_finer_texture_at_finer_scales():
    rng = np.random.default_rng(0)
    fine = rng.random((64, 64))
    coarse = zoom_to(rng.random((8, 8)).repeat(8, 0).repeat(8, 1), 64)
    f, c = scattering_features(fine, 3, 8), scattering_features(coarse, 3, 8)
    assert f[1] > c[1]  # j = 0: the finest order-1 band


def test_descriptor_vector_matches_the_configuration_and_refuses_missing_colour():
    cfg = VisualConfig(descriptors=("scattering", "lbp", "colour", "grids", "spectrum"), descriptor_size=128)
    assert cfg.descriptors == ("lbp", "spectrum", "colour", "grids", "scattering")
    gray = np.random.default_rng(1).random((160, 160)).astype(np.float32)
    colour = np.repeat(gray[..., None], 3, axis=2)
    out = descriptor_vector(gray, colour, cfg)
    assert out.shape == (cfg.descriptor_dim,) == (30 + 8 + 13 + 12 + 28,)
    with pytest.raises(ValueError, match="colour descriptor needs the frame in colour"):
        descriptor_vector(gray, None, cfg)


def test_default_hash_unchanged_by_the_descriptor_fields():
    assert VisualConfig().hash() == "db307d7f543e65cc"  # the hash every exported model and cache carries
    assert VisualConfig(descriptors=("lbp",)).hash() != VisualConfig().hash()


class FakeBackbone:
    name, dim, fingerprint = "fake", 3, "f" * 16

    def embed(self, patches: np.ndarray) -> np.ndarray:
        return np.stack([patches.mean(axis=(1, 2)), patches.std(axis=(1, 2)), patches.max(axis=(1, 2))], axis=1)


def test_visual_features_appends_the_descriptors_after_backbone_and_glcm(texture, tmp_path):
    from models.visual.cache import FeatureCache
    from models.visual.embedding import visual_features, visual_layout

    base = VisualConfig(patch_size=64, grid=2)
    cfg = VisualConfig(patch_size=64, grid=2, descriptors=("lbp", "spectrum", "colour"), descriptor_size=128)
    colour = np.repeat(texture[..., None], 3, axis=2)
    cache = FeatureCache(tmp_path / "c")
    plain = visual_features(texture, base, FakeBackbone(), cache)
    full = visual_features(texture, cfg, FakeBackbone(), cache, colour=colour)
    layout = visual_layout(3, cfg)
    assert full.shape == (3 + 256 + cfg.descriptor_dim,) and layout["colour"].stop == full.size
    np.testing.assert_array_equal(full[: plain.size], plain)  # the backbone and GLCM part is unchanged
    np.testing.assert_allclose(full[layout["lbp"]], lbp_histograms(zoom_to(texture, 128)), rtol=1e-6)
    again = visual_features(texture, cfg, FakeBackbone(), cache, colour=colour)  # from the cache
    np.testing.assert_array_equal(again, full)
    with pytest.raises(ValueError, match="needs the frame in colour"):
        visual_features(texture, cfg, FakeBackbone())


def test_two_frames_of_one_grey_in_different_colours_do_not_share_cached_descriptors(texture, tmp_path):
    from models.visual.cache import FeatureCache
    from models.visual.embedding import visual_features, visual_layout

    cfg = VisualConfig(patch_size=64, grid=2, descriptors=("colour",), descriptor_size=128)
    grey = np.repeat(texture[..., None], 3, axis=2)
    # the same luma (0.299 R + 0.587 G + 0.114 B) with a red–green tint
    tint = np.stack([texture + 0.05 * 0.587, texture - 0.05 * 0.299, texture], axis=2).clip(0, 1)
    cache = FeatureCache(tmp_path / "c")
    columns = visual_layout(3, cfg)["colour"]
    first = visual_features(texture, cfg, FakeBackbone(), cache, colour=grey)[columns]
    second = visual_features(texture, cfg, FakeBackbone(), cache, colour=tint)[columns]
    fresh = visual_features(texture, cfg, FakeBackbone(), None, colour=tint)[columns]
    assert not np.allclose(first, second)
    np.testing.assert_array_equal(second, fresh)
