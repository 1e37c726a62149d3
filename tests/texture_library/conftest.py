"""Shared builders for the texture-library tests: small vibration models with known content."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from texture_library.lsf import poles_to_poly, poly_to_lsf
from texture_library.procedural import PhysicalParams
from texture_library.taps import TapSet
from texture_library.vibration import VibrationModel

PROJECT_ROOT = Path(__file__).resolve().parents[2]
HATT_DIR = (PROJECT_ROOT / ".." / "shared" / "data" / "hatt-texnet").resolve()


def square_model(*, with_taps: bool = False, name: str = "square") -> VibrationModel:
    """A 3×3 grid over speed 0…200 mm/s × force 0…4 N, two triangles per cell (8 triangles).

    Grid point k (speed sₖ, force fₖ) has AR poles at 60 + sₖ/2 Hz (r = 0.9) and 300 Hz (r = 0.8),
    MA zeros (1 − 0.5 z⁻¹)(1 − 0.2 z⁻¹), variance (sₖ/100)²·(1 + fₖ/4), gain 1 + fₖ/4.
    The variance is 0 wherever the speed is 0.
    """
    speeds_1d, forces_1d = np.array([0.0, 100.0, 200.0]), np.array([0.0, 2.0, 4.0])
    ss, ff = np.meshgrid(speeds_1d, forces_1d, indexing="ij")
    speeds, forces = ss.ravel(), ff.ravel()
    ar = [poly_to_lsf(poles_to_poly(np.array([60.0 + s / 2, 300.0]), np.array([0.9, 0.8]), 1000.0)) for s in speeds]
    ma = poly_to_lsf(np.convolve([1.0, -0.5], [1.0, -0.2]))
    tris = []
    for i in range(2):
        for j in range(2):
            a, b, c, d = i * 3 + j, (i + 1) * 3 + j, i * 3 + j + 1, (i + 1) * 3 + j + 1
            tris += [(a, b, c), (b, d, c)]
    taps = TapSet(np.array([10.0, 40.0]), np.arange(200.0).reshape(2, 100) / 100.0) if with_taps else None
    return VibrationModel(
        name=name,
        speeds=speeds,
        forces=forces,
        triangles=np.array(tris, dtype=np.int64),
        ar_lsf=np.array(ar),
        ma_lsf=np.tile(ma, (speeds.size, 1)),
        variance=(speeds / 100.0) ** 2 * (1 + forces / 4),
        gain=1 + forces / 4,
        mu=0.4,
        max_speed=200.0,
        max_force=4.0,
        taps=taps,
        provenance="test",
        extra={"note": "hand-made"},
    )


@pytest.fixture
def model() -> VibrationModel:
    return square_model()


@pytest.fixture
def model_with_taps() -> VibrationModel:
    return square_model(with_taps=True)


@pytest.fixture
def make_model():
    return square_model


@pytest.fixture
def params() -> PhysicalParams:
    """A middle-of-the-road texture: every true rating is 0 (the documented neutral points)."""
    return PhysicalParams(
        roughness_um=15.0,
        grain_mm=1.0,
        bump_height_mm=0.5,
        bump_period_mm=8.0,
        mu=0.6,
        stiffness_n_per_mm=1.0,
        albedo=0.5,
    )


@pytest.fixture
def hatt_dir() -> Path:
    """../shared/data/hatt-texnet; tests using it carry the `shared` marker and skip without it."""
    if not (HATT_DIR / "models").is_dir():
        pytest.skip(f"HaTT–TexNet data not found at {HATT_DIR} (needs ../shared)")
    return HATT_DIR
