import hashlib

import numpy as np
import pytest
import torch

from models.offline.backbones.cnn import Backbone, PatchEncoder, resolve_backbone
from models.offline.backbones.efficientnet import efficientnet_lite0_weights_path
from models.visual.config import VisualConfig


@pytest.fixture
def empty_hub(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))


def _patches(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).random((n, 224, 224)).astype(np.float32)


def test_auto_falls_back_to_efficientnet_without_resnet_weights(empty_hub):
    backbone = resolve_backbone(VisualConfig())
    assert (backbone.name, backbone.dim) == ("efficientnet_lite0", 1280)
    digest = hashlib.sha256(efficientnet_lite0_weights_path().read_bytes()).hexdigest()
    assert backbone.fingerprint == digest[:16]
    # torch-hub-style file names carry the first 8 hex digits of the file's sha256
    assert efficientnet_lite0_weights_path().name == f"efficientnet-lite0-{digest[:8]}.pth"


def test_explicit_choices(empty_hub, resnet_checkpoint):
    with pytest.raises(FileNotFoundError, match="backbone='resnet50' needs ImageNet weights"):
        resolve_backbone(VisualConfig(backbone="resnet50"))
    chosen = resolve_backbone(VisualConfig(backbone="efficientnet_lite0", resnet50_weights=str(resnet_checkpoint)))
    assert chosen.name == "efficientnet_lite0"


def test_embed_shapes_and_batching(efficientnet_backbone):
    patches = _patches(3)
    features = efficientnet_backbone.embed(patches)
    assert features.shape == (3, 1280) and features.dtype == np.float32
    assert np.all(np.isfinite(features))
    small_batches = Backbone(
        efficientnet_backbone.name,
        efficientnet_backbone.dim,
        efficientnet_backbone.fingerprint,
        efficientnet_backbone.weights,
        efficientnet_backbone.encoder,
        batch_size=2,
    )
    np.testing.assert_allclose(small_batches.embed(patches), features, rtol=0, atol=1e-5 * np.abs(features).max())
    assert efficientnet_backbone.embed(np.zeros((0, 224, 224), np.float32)).shape == (0, 1280)


def test_embed_rejects_bad_patches(efficientnet_backbone):
    with pytest.raises(ValueError, match="shape"):
        efficientnet_backbone.embed(np.zeros((2, 112, 112), np.float32))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        efficientnet_backbone.embed(np.full((1, 224, 224), 255.0, np.float32))


def test_grey_is_replicated_then_normalised_per_channel(resnet_random_backbone):
    encoder: PatchEncoder = resnet_random_backbone.encoder
    patches = torch.rand(2, 64, 64, generator=torch.Generator().manual_seed(1))  # the encoder takes any size
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    manual = (patches[:, None].repeat(1, 3, 1, 1) - mean) / std
    with torch.no_grad():
        torch.testing.assert_close(encoder(patches), encoder.trunk.net.features(manual))
    assert resnet_random_backbone.weights == "random(seed=0)"


def test_last_block_layer_is_efficientnet_only(empty_hub, resnet_checkpoint):
    chosen = resolve_backbone(VisualConfig(backbone="efficientnet_lite0", backbone_layer="last_block"))
    assert (chosen.name, chosen.dim) == ("efficientnet_lite0", 640)
    assert chosen.embed(_patches(2)).shape == (2, 640)
    with pytest.raises(ValueError, match="backbone_layer 'last_block' is read from EfficientNet-Lite0 only"):
        resolve_backbone(VisualConfig(backbone_layer="last_block", resnet50_weights=str(resnet_checkpoint)))
