"""Shared fixtures: synthetic texture images and backbones built once per session."""

from __future__ import annotations

import numpy as np
import pytest


def synthetic_texture(height: int = 300, width: int = 260, seed: int = 0) -> np.ndarray:
    """(height, width) float32 in [0, 1]: oriented gratings plus smoothed noise, like a photographed texture."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float64)
    grating = 0.5 + 0.25 * np.sin(2 * np.pi * (rows * 0.05 + cols * 0.11))
    noise = rng.normal(0.0, 0.15, size=(height, width))
    kernel = np.ones(5) / 5
    noise = np.apply_along_axis(lambda v: np.convolve(v, kernel, mode="same"), 1, noise)
    return np.clip(grating + noise, 0.0, 1.0).astype(np.float32)


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


@pytest.fixture
def texture() -> np.ndarray:
    return synthetic_texture()


@pytest.fixture(scope="session")
def efficientnet_backbone():
    from models.visual.backbone import efficientnet_lite0_backbone

    return efficientnet_lite0_backbone()


@pytest.fixture(scope="session")
def resnet_random_backbone():
    from models.visual.backbone import resnet50_backbone

    return resnet50_backbone(None, seed=0)


@pytest.fixture(scope="session")
def resnet_checkpoint(tmp_path_factory, resnet_random_backbone):
    """A torchvision-layout ResNet-50 checkpoint file (random weights, seed 0)."""
    import torch

    path = tmp_path_factory.mktemp("weights") / "resnet50-test.pth"
    torch.save(resnet_random_backbone.encoder.trunk.net.state_dict(), path)
    return path
