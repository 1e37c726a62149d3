"""Shared fixtures for the dataset tests: one small synthetic dataset, copied before it is corrupted."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from models.offline.datasets.synthetic import build_synthetic

PROJECT_ROOT = Path(__file__).resolve().parents[4]
HATT_DIR = (PROJECT_ROOT / ".." / "shared" / "data" / "hatt-texnet").resolve()


@pytest.fixture(scope="session")
def synthetic_dataset(tmp_path_factory) -> Path:
    """3 textures (synth_000, synth_001 rated by 4 raters; synth_002 withheld), one 2 s recording each,
    224 px images. Read-only: tests that change it take `dataset_copy`."""
    return build_synthetic(
        tmp_path_factory.mktemp("synthetic") / "ds",
        n_textures=3,
        seed=0,
        duration_s=2.0,
        n_raters=4,
        image_size=224,
        withheld=1,
    )


@pytest.fixture
def dataset_copy(synthetic_dataset, tmp_path) -> Path:
    """A private copy of the synthetic dataset, free to corrupt."""
    return Path(shutil.copytree(synthetic_dataset, tmp_path / "ds", ignore=shutil.ignore_patterns("features")))


@pytest.fixture(scope="session")
def hatt_dir() -> Path:
    """../shared/data/hatt-texnet; tests using it carry the `shared` marker and skip without it."""
    if not (HATT_DIR / "models").is_dir():
        pytest.skip(f"HaTT–TexNet data not found at {HATT_DIR} (needs ../shared)")
    return HATT_DIR
