import numpy as np
import pytest
import torch

from models.offline.backbones.efficientnet import (
    EFFICIENTNET_LITE0_DIM,
    LITE_MEAN,
    LITE_STD,
    stem_implied_input_mean,
)
from models.offline.backbones.resnet import IMAGENET_MEAN


def test_pooled_features_shape(efficientnet_backbone):
    trunk = efficientnet_backbone.encoder.trunk
    with torch.no_grad():
        out = trunk(torch.zeros(2, 3, 224, 224))
    assert out.shape == (2, EFFICIENTNET_LITE0_DIM) == (2, 1280)
    assert torch.isfinite(out).all()


def test_shipped_weights_were_trained_on_tf_lite_normalisation(efficientnet_backbone):
    """The stem BatchNorm's running means reveal the input mean the weights saw in training."""
    implied = stem_implied_input_mean(efficientnet_backbone.encoder.trunk.net)
    tf_lite = (255.0 * np.array(IMAGENET_MEAN) - 127.0) / 128.0  # ImageNet pixels under (x − 127)/128
    torchvision_style = np.zeros(3)  # (x − mean)/std centres every channel
    assert np.all(np.abs(implied - tf_lite) < 0.07)
    assert np.linalg.norm(implied - tf_lite) < 0.5 * np.linalg.norm(implied - torchvision_style)


def test_encoder_applies_lite_normalisation(efficientnet_backbone):
    encoder = efficientnet_backbone.encoder
    assert LITE_MEAN == (127 / 255,) * 3 and LITE_STD == (128 / 255,) * 3
    # a uniform 127/255 grey patch is the all-zero network input
    grey = torch.full((1, 224, 224), 127.0 / 255.0)
    with torch.no_grad():
        torch.testing.assert_close(encoder(grey), encoder.trunk(torch.zeros(1, 3, 224, 224)), atol=1e-5, rtol=0)


def test_last_block_reads_the_block_the_head_convolves():
    """last_block = mean ⊕ std over space of what the last MBConv block hands the head (caught by a hook
    inside the package's own extract_features)."""
    from models.offline.backbones.efficientnet import EfficientNetLite0Trunk, load_efficientnet_lite0

    net = load_efficientnet_lite0()
    x = torch.randn(2, 3, 224, 224, generator=torch.Generator().manual_seed(0))
    seen = []
    hook = net._blocks[-1].register_forward_hook(lambda module, args, out: seen.append(out.detach()))
    with torch.no_grad():
        net.extract_features(x)
        hook.remove()
        out = EfficientNetLite0Trunk(net, "last_block")(x)
    block = seen[0].numpy().reshape(2, 320, -1)  # (n, 320, 7·7)
    assert seen[0].shape == (2, 320, 7, 7) and out.shape == (2, 640)
    np.testing.assert_allclose(out[:, :320].numpy(), block.mean(axis=2), atol=1e-5, rtol=1e-5)
    np.testing.assert_allclose(out[:, 320:].numpy(), block.std(axis=2), atol=1e-5, rtol=1e-5)


def test_trunk_refuses_an_unknown_layer():
    from models.offline.backbones.efficientnet import EfficientNetLite0Trunk, load_efficientnet_lite0

    with pytest.raises(ValueError, match="layer must be one of"):
        EfficientNetLite0Trunk(load_efficientnet_lite0(), "stem")
