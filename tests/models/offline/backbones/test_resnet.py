import hashlib

import numpy as np
import pytest
import torch

from models.offline.backbones.cnn import resnet50_backbone, resolve_backbone
from models.offline.backbones.resnet import (
    RESNET50_STATE_DICT_LEN,
    ResNet50,
    find_resnet50_weights,
    load_resnet50,
    random_resnet50,
)
from models.visual.config import VisualConfig

# (name, shape) samples of torchvision's resnet50().state_dict()
TORCHVISION_SAMPLES = {
    "conv1.weight": (64, 3, 7, 7),
    "bn1.running_mean": (64,),
    "bn1.num_batches_tracked": (),
    "layer1.0.conv1.weight": (64, 64, 1, 1),
    "layer1.0.downsample.0.weight": (256, 64, 1, 1),
    "layer1.0.downsample.1.running_var": (256,),
    "layer2.0.conv2.weight": (128, 128, 3, 3),
    "layer3.5.conv3.weight": (1024, 256, 1, 1),
    "layer4.0.downsample.0.weight": (2048, 1024, 1, 1),
    "layer4.2.bn3.weight": (2048,),
    "fc.weight": (1000, 2048),
    "fc.bias": (1000,),
}


@pytest.fixture(scope="module")
def net(resnet_random_backbone) -> ResNet50:
    return resnet_random_backbone.encoder.trunk.net


def test_state_dict_has_torchvision_layout(net):
    state = net.state_dict()
    assert len(state) == RESNET50_STATE_DICT_LEN == 320
    for name, shape in TORCHVISION_SAMPLES.items():
        assert tuple(state[name].shape) == shape, name
    # blocks per stage [3, 4, 6, 3]; only each stage's first block has a shortcut projection
    for stage, blocks in enumerate((3, 4, 6, 3), start=1):
        assert f"layer{stage}.{blocks - 1}.conv3.weight" in state
        assert f"layer{stage}.{blocks}.conv1.weight" not in state
        assert f"layer{stage}.1.downsample.0.weight" not in state
    # torchvision's ResNet-50 has 25,557,032 parameters
    assert sum(p.numel() for p in net.parameters()) == 25_557_032


def test_features_shape_and_logits(net):
    x = torch.randn(2, 3, 64, 64, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        features = net.features(x)
        logits = net(x)
    assert features.shape == (2, 2048) and logits.shape == (2, 1000)
    torch.testing.assert_close(logits, net.fc(features))


def test_random_weights_are_seeded(net):
    state = net.state_dict()  # seed 0
    assert torch.equal(random_resnet50(0).state_dict()["layer2.1.conv2.weight"], state["layer2.1.conv2.weight"])
    assert not torch.equal(random_resnet50(1).state_dict()["conv1.weight"], state["conv1.weight"])


def test_checkpoint_round_trip_via_configured_path(resnet_checkpoint, resnet_random_backbone, tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "empty-hub"))
    loaded = resolve_backbone(VisualConfig(resnet50_weights=str(resnet_checkpoint)))
    assert (loaded.name, loaded.dim) == ("resnet50", 2048)
    assert loaded.fingerprint == hashlib.sha256(resnet_checkpoint.read_bytes()).hexdigest()[:16]
    patches = np.random.default_rng(0).random((1, 224, 224)).astype(np.float32)
    features = loaded.embed(patches)
    assert features.shape == (1, 2048)
    np.testing.assert_array_equal(features, resnet_random_backbone.embed(patches))


def test_checkpoint_found_in_torch_hub_cache(resnet_checkpoint, tmp_path, monkeypatch):
    hub = tmp_path / "hub"
    (hub / "checkpoints").mkdir(parents=True)
    cached = hub / "checkpoints" / "resnet50-0676ba61.pth"
    cached.symlink_to(resnet_checkpoint)
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(hub))
    assert find_resnet50_weights(None) == cached
    assert resolve_backbone(VisualConfig()).name == "resnet50"


def test_strict_loading_and_missing_paths(net, tmp_path):
    partial = {k: v for k, v in net.state_dict().items() if not k.startswith("fc.")}
    path = tmp_path / "partial.pth"
    torch.save(partial, path)
    with pytest.raises(RuntimeError, match="Missing key"):
        load_resnet50(path)
    with pytest.raises(FileNotFoundError, match="resnet50_weights"):
        find_resnet50_weights(tmp_path / "nope.pth")
    with pytest.raises(FileNotFoundError):
        resnet50_backbone(tmp_path / "nope.pth")
