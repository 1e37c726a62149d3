"""Shared fixtures: torch backbones built once per session, one torch thread per test package."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="package", autouse=True)
def single_torch_thread():
    """One torch thread while these tests run, restored after them.

    The backbone tests run tiny batches, where OpenMP's barrier spinning on a
    shared 2-core runner costs more than a second thread gains (measured: 60 s
    against 24 s for this package under load). Results do not depend on it.
    """
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def efficientnet_backbone():
    from models.offline.backbones.cnn import efficientnet_lite0_backbone

    return efficientnet_lite0_backbone()


@pytest.fixture(scope="session")
def resnet_random_backbone():
    from models.offline.backbones.cnn import resnet50_backbone

    return resnet50_backbone(None, seed=0)


@pytest.fixture(scope="session")
def resnet_checkpoint(tmp_path_factory, resnet_random_backbone):
    """A torchvision-layout ResNet-50 checkpoint file (random weights, seed 0)."""
    import torch

    path = tmp_path_factory.mktemp("weights") / "resnet50-test.pth"
    torch.save(resnet_random_backbone.encoder.trunk.net.state_dict(), path)
    return path
