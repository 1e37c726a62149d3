"""Synthetic texture images for the visual feature tests."""

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


@pytest.fixture
def texture() -> np.ndarray:
    return synthetic_texture()
