import numpy as np
import pytest

from models.offline.evaluation.data import TextureData


def make_linear_world(
    n_textures: int = 30, n_windows: int = 6, n_tactile: int = 12, n_visual: int = 20, seed: int = 0, noise: float = 2.0
) -> TextureData:
    """Textures whose ratings are a known linear function of hidden factors seen by both modalities."""
    rng = np.random.default_rng(seed)
    factors = rng.normal(size=(n_textures, 4))
    targets = np.clip(40 * factors, -100, 100)
    mix_t = rng.normal(size=(4, n_tactile))
    mix_v = rng.normal(size=(4, n_visual))
    tactile = [
        (factors[i] @ mix_t + 0.3 * rng.normal(size=(n_windows, n_tactile))).astype(np.float32)
        for i in range(n_textures)
    ]
    visual = (factors @ mix_v)[:, None, :] + 0.1 * rng.normal(size=(n_textures, 3, n_visual))
    targets = targets + noise * rng.normal(size=targets.shape)
    groups = ["a" if i % 2 else "b" for i in range(n_textures)]
    return TextureData(
        [f"t{i:02d}" for i in range(n_textures)],
        groups,
        tactile,
        visual.astype(np.float32),
        np.clip(targets, -100, 100).astype(np.float32),
        {"dataset": "linear-world"},
    )


@pytest.fixture(scope="session")
def linear_world() -> TextureData:
    return make_linear_world()
