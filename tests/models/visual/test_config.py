import hashlib

import pytest
from pydantic import ValidationError

from models.visual.config import VisualConfig


def test_defaults_follow_the_paper():
    config = VisualConfig()
    assert config.patch_size == 224
    assert config.grid == 7 and config.n_patches == 49
    assert config.glcm_levels == 16 and config.glcm_dim == 256
    assert config.glcm_distances == (1,)
    assert config.glcm_angles_deg == (0.0, 45.0, 90.0, 135.0)
    assert config.backbone == "auto" and config.resnet50_weights is None


def test_frozen_and_extra_forbidden():
    config = VisualConfig()
    with pytest.raises(ValidationError):
        config.grid = 5
    with pytest.raises(ValidationError):
        VisualConfig(patch_sz=224)


def test_hash_is_sha256_of_canonical_json():
    config = VisualConfig()
    expected = hashlib.sha256(config.canonical_json().encode()).hexdigest()[:16]
    assert config.hash() == expected
    assert len(config.hash()) == 16 and set(config.hash()) <= set("0123456789abcdef")


def test_hash_tracks_computation_not_location():
    base = VisualConfig()
    assert VisualConfig().hash() == base.hash()
    assert VisualConfig(glcm_levels=8).hash() != base.hash()
    assert VisualConfig(grid=5).hash() != base.hash()
    # How the backbone is picked differs per machine; the resolved backbone's name,
    # dim and weights fingerprint identify it beside the hash.
    assert VisualConfig(resnet50_weights="/somewhere/resnet50.pth").hash() == base.hash()
    assert VisualConfig(backbone="efficientnet_lite0").hash() == base.hash()
    # ints and floats for angles are one configuration
    assert VisualConfig(glcm_angles_deg=(0, 45, 90, 135)).hash() == base.hash()


def test_json_round_trip_keeps_value_and_hash():
    config = VisualConfig(grid=5, glcm_distances=(1, 2), resnet50_weights="w.pth")
    again = VisualConfig.model_validate_json(config.model_dump_json())
    assert again == config and again.hash() == config.hash()


@pytest.mark.parametrize(
    "kwargs",
    [
        {"glcm_distances": (0,)},
        {"glcm_distances": ()},
        {"glcm_angles_deg": ()},
        {"glcm_levels": 1},
        {"grid": 0},
        {"patch_size": 8},
        {"backbone": "vgg16"},
    ],
)
def test_invalid_values_raise(kwargs):
    with pytest.raises(ValueError):
        VisualConfig(**kwargs)


def test_resize_defaults_to_none_and_leaves_the_hash_as_before():
    # The hash existing models and caches were written under: the JSON without a resize key.
    legacy = '{"glcm_angles_deg":[0.0,45.0,90.0,135.0],"glcm_distances":[1],"glcm_levels":16,"grid":7,"patch_size":224}'
    assert VisualConfig().resize is None
    assert VisualConfig().canonical_json() == legacy
    assert VisualConfig().hash() == hashlib.sha256(legacy.encode()).hexdigest()[:16]
    assert VisualConfig(resize=512).hash() != VisualConfig().hash()
    assert VisualConfig(resize=512).hash() != VisualConfig(resize=448).hash()


def test_resize_must_hold_one_patch():
    with pytest.raises(ValidationError, match="resize"):
        VisualConfig(resize=200)
    assert VisualConfig(resize=224).resize == 224


def test_glcm_off_changes_the_hash_and_on_leaves_it_as_before():
    assert VisualConfig(glcm=True).hash() == VisualConfig().hash()
    off = VisualConfig(grid=2, glcm=False)
    assert off.hash() != VisualConfig(grid=2).hash() and '"glcm":false' in off.canonical_json()
    assert off.glcm_dim == 0 and VisualConfig().glcm_dim == 256


@pytest.mark.parametrize(
    "config", [VisualConfig(), VisualConfig(grid=2, glcm=False), VisualConfig(resize=448, descriptors=("lbp",))]
)
def test_computation_rebuilds_the_same_configuration(config):
    # what a model card carries, so the service computes the vector its model was trained on
    rebuilt = VisualConfig(**config.computation())
    assert rebuilt.hash() == config.hash() and rebuilt == config


def test_backbone_layer_head_leaves_the_hash_as_before():
    assert VisualConfig(backbone_layer="head").hash() == VisualConfig().hash()
    last = VisualConfig(grid=2, glcm=False, backbone_layer="last_block")
    assert last.hash() != VisualConfig(grid=2, glcm=False).hash()
    assert '"backbone_layer":"last_block"' in last.canonical_json()
    assert VisualConfig(**last.computation()) == last
    with pytest.raises(ValidationError, match="backbone_layer"):
        VisualConfig(backbone_layer="stem")
