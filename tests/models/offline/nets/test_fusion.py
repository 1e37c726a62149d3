"""VisuoTactileNet: modalities, concat sizes, head, argument checks; the faithful forward."""

from __future__ import annotations

import pytest
import torch

from models.offline.nets.fusion import FusionHead, MLPBranch, VisuoTactileNet, pairwise_max_pool

SMALL = {"width": 1 / 16, "visual_fc": (16, 8), "tactile_filters": (4, 4), "tactile_out": 8, "head": (8, 8, 4)}


def test_faithful_forward_shapes() -> None:
    net = VisuoTactileNet(1536, 526)
    out = net(torch.randn(2, 526), torch.randn(2, 1536))
    assert out["ratings"].shape == (2, 4)
    assert out["reconstruction"] is not None and out["reconstruction"].shape == (2, 1536)
    assert net.head.fc1.in_features == 256  # 128 visual + 128 tactile
    assert (net.head.fc1.out_features, net.head.fc2.out_features) == (128, 128)
    assert (net.head.fc3.in_features, net.head.fc3.out_features, net.head.out.out_features) == (64, 32, 4)


@pytest.mark.parametrize("modality", ["both", "tactile", "visual"])
def test_modalities_have_only_their_branches(modality: str) -> None:
    net = VisuoTactileNet(64, 526, modality=modality, **SMALL)  # type: ignore[arg-type]
    assert net.modality == modality
    assert (net.visual is not None) == (modality != "tactile")
    assert (net.tactile is not None) == (modality != "visual")
    assert net.head.fc1.in_features == (16 if modality == "both" else 8)
    out = net(torch.randn(3, 526), torch.randn(3, 64))
    assert out["ratings"].shape == (3, 4)
    assert (out["reconstruction"] is None) == (modality == "tactile")


def test_single_modality_ignores_the_other_input() -> None:
    torch.manual_seed(0)
    tactile_net = VisuoTactileNet(64, 526, modality="tactile", **SMALL)
    visual_net = VisuoTactileNet(64, 526, modality="visual", **SMALL)
    t, v = torch.randn(2, 526), torch.randn(2, 64)
    torch.testing.assert_close(tactile_net(t, v)["ratings"], tactile_net(t, torch.randn(2, 64))["ratings"])
    torch.testing.assert_close(visual_net(t, v)["ratings"], visual_net(torch.randn(2, 526), v)["ratings"])


def test_mlp_tactile_branch_accepts_any_length() -> None:
    net = VisuoTactileNet(64, 300, tactile_branch="mlp", tactile_hidden=(16,), **SMALL)
    assert isinstance(net.tactile, MLPBranch)
    assert net(torch.randn(2, 300), torch.randn(2, 64))["ratings"].shape == (2, 4)


def test_pairwise_max_pool_known_answer() -> None:
    x = torch.tensor([[1.0, 4.0, -2.0, -3.0, 7.0, 7.5]])
    assert pairwise_max_pool(x).tolist() == [[4.0, -2.0, 7.5]]


def test_head_output_is_linear() -> None:
    """The last layer has no ReLU: negative standardized ratings must be reachable."""
    head = FusionHead(4, (8, 8, 4))
    with torch.no_grad():
        head.out.bias.fill_(-5.0)
        head.out.weight.zero_()
    assert (head(torch.randn(3, 4)) == -5.0).all()


def test_gradients_reach_both_branches() -> None:
    net = VisuoTactileNet(64, 526, **SMALL)
    out = net(torch.randn(4, 526), torch.randn(4, 64))
    (out["ratings"].sum() + out["reconstruction"].pow(2).mean()).backward()  # type: ignore[union-attr]
    for name, p in net.named_parameters():
        assert p.grad is not None, name


def test_bad_arguments_raise() -> None:
    with pytest.raises(ValueError, match=r"tactile_dim 500 does not match .* 40·13 \+ 6 = 526"):
        VisuoTactileNet(64, 500)
    with pytest.raises(ValueError, match="modality"):
        VisuoTactileNet(64, 526, modality="audio")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="tactile_branch"):
        VisuoTactileNet(64, 526, tactile_branch="gru")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="even second"):
        FusionHead(8, (8, 7, 4))
    # a visual-only model does not care about the tactile layout
    VisuoTactileNet(64, 500, modality="visual", **SMALL)
