import numpy as np
import pytest

from models.visual.augment import view_params
from models.visual.cache import FeatureCache
from models.visual.config import VisualConfig
from models.visual.embedding import VisualFeatures, batch_visual_features, part_columns, visual_features, visual_layout
from models.visual.glcm import glcm_features
from models.visual.patches import extract_patches

from .conftest import synthetic_texture

SMALL = VisualConfig(grid=2)  # 4 patches keep real-backbone tests quick


class CountingEmbedder:
    """A deterministic stand-in backbone: per-patch [mean, std, min, max], counting calls."""

    name = "counting"
    dim = 4
    fingerprint = "0123456789abcdef"

    def __init__(self) -> None:
        self.calls = 0

    def embed(self, patches: np.ndarray) -> np.ndarray:
        self.calls += 1
        flat = patches.reshape(len(patches), -1)
        return np.stack([flat.mean(1), flat.std(1), flat.min(1), flat.max(1)], axis=1).astype(np.float32)


def test_vector_is_patch_mean_then_glcm(texture):
    embedder = CountingEmbedder()
    config = VisualConfig()
    values = visual_features(texture, config, embedder)
    assert values.shape == (4 + 256,) and values.dtype == np.float32
    expected_backbone = embedder.embed(extract_patches(texture, 224, 7)).mean(axis=0)
    np.testing.assert_allclose(values[:4], expected_backbone, rtol=1e-6)
    np.testing.assert_array_equal(values[4:], glcm_features(texture))


def test_cache_means_one_backbone_pass_per_image_and_view(tmp_path, texture):
    embedder = CountingEmbedder()
    cache = FeatureCache(tmp_path)
    first = visual_features(texture, SMALL, embedder, cache)
    again = visual_features(texture, SMALL, embedder, cache)
    assert embedder.calls == 1
    np.testing.assert_array_equal(first, again)
    turned = view_params(2, seed=0)[1]
    visual_features(texture, SMALL, embedder, cache, view=turned)
    visual_features(texture, SMALL, embedder, cache, view=turned)
    assert embedder.calls == 2
    visual_features(texture, VisualConfig(grid=3), embedder, cache)  # another config, another entry
    assert embedder.calls == 3


def test_batch_helper_shapes_metadata_and_consistency(tmp_path):
    images = [synthetic_texture(seed=s) for s in range(3)]
    embedder = CountingEmbedder()
    features = batch_visual_features(
        images, SMALL, embedder, n_views=2, seed=4, cache=FeatureCache(tmp_path), progress=False
    )
    assert isinstance(features, VisualFeatures)
    assert features.values.shape == (3, 2, 260)
    assert features.backbone_part.shape == (3, 2, 4) and features.glcm_part.shape == (3, 2, 256)
    assert features.views == tuple(view_params(2, 4))
    meta = features.metadata()
    assert meta["visual.backbone"] == "counting" and meta["visual.dim"] == "260"
    assert meta["visual.config_hash"] == SMALL.hash()
    assert meta["visual.weights_fingerprint"] == "0123456789abcdef"
    np.testing.assert_array_equal(features.values[1, 0], visual_features(images[1], SMALL, CountingEmbedder()))
    np.testing.assert_array_equal(
        features.values[2, 1], visual_features(images[2], SMALL, CountingEmbedder(), view=view_params(2, 4)[1])
    )
    assert embedder.calls == 6
    batch_visual_features(images, SMALL, embedder, n_views=2, seed=4, cache=FeatureCache(tmp_path), progress=False)
    assert embedder.calls == 6  # all cached


def test_bad_images_raise(texture):
    embedder = CountingEmbedder()
    with pytest.raises(ValueError, match="float array"):
        visual_features((texture * 255).astype(np.uint8), SMALL, embedder)
    with pytest.raises(ValueError, match=r"img must lie in \[0, 1\]"):
        visual_features(texture * 2, SMALL, embedder)
    with pytest.raises(ValueError, match="need at least 224×224"):
        visual_features(texture[:200], SMALL, embedder)
    assert embedder.calls == 0


def test_visual_features_metadata_validates_dims():
    with pytest.raises(ValueError, match="backbone_dim \\+ glcm_dim"):
        VisualFeatures(np.zeros((2, 10), np.float32), "resnet50", 2048, 256, "c" * 16, "f" * 16)


def test_real_backbone_end_to_end(efficientnet_backbone):
    image = synthetic_texture(256, 256, seed=9)
    values = visual_features(image, SMALL, efficientnet_backbone)
    assert values.shape == (1280 + 256,)
    assert np.all(np.isfinite(values))
    np.testing.assert_allclose(values[1280:].sum(), 1.0, rtol=1e-5)


def test_resize_scales_the_image_before_patches_and_glcm():
    from models.visual.image import resize_shorter

    img = synthetic_texture(height=520, width=480, seed=3)
    embedder = CountingEmbedder()
    resized = visual_features(img, VisualConfig(grid=2, resize=240), embedder)
    by_hand = visual_features(resize_shorter(img, 240), VisualConfig(grid=2), embedder)
    np.testing.assert_array_equal(resized, by_hand)
    assert not np.array_equal(resized, visual_features(img, VisualConfig(grid=2), embedder))


def test_glcm_off_gives_the_backbone_part_alone(texture):
    embedder = CountingEmbedder()
    on, off = VisualConfig(grid=2), VisualConfig(grid=2, glcm=False)
    with_glcm = visual_features(texture, on, embedder)
    without = visual_features(texture, off, embedder)
    assert off.glcm_dim == 0 and without.shape == (embedder.dim,)
    np.testing.assert_array_equal(without, with_glcm[: embedder.dim])
    assert list(visual_layout(embedder.dim, off)) == ["backbone"]
    assert list(visual_layout(embedder.dim, on)) == ["backbone", "glcm"]


def test_part_columns_cut_named_blocks_and_refuse_an_absent_one():
    layout = visual_layout(4, VisualConfig(descriptors=("spectrum",)))
    cols, blocks = part_columns(layout, "classic")
    assert cols.tolist() == list(range(4, 4 + 256 + 8)) and blocks == {"glcm": [0, 256], "spectrum": [256, 264]}
    assert part_columns(layout, "backbone")[0].tolist() == [0, 1, 2, 3]
    with pytest.raises(ValueError, match="'glcm' is empty"):
        part_columns(visual_layout(4, VisualConfig(glcm=False)), "glcm")
    with pytest.raises(ValueError, match="visual part must be one of"):
        part_columns(layout, "colours")
