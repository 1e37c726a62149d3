"""Shared builders for the tactile tests: synthetic strokes with known content."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from texture_library.recording import Recording, make_channel


def synthetic_recording(
    duration_s: float = 3.0,
    accel_rate: float = 1000.0,
    force_rate: float = 1000.0,
    motion_rate: float = 1000.0,
    force_axes: int = 1,
    motion: str = "speed",
    seed: int = 0,
) -> Recording:
    """A stroke: accel = gravity on z + 150 Hz tone + noise; force ≈ 1.5 N; 80 mm/s along x–y."""
    rng = np.random.default_rng(seed)
    na, nf, nm = (int(round(duration_s * r)) for r in (accel_rate, force_rate, motion_rate))
    ta = np.arange(na) / accel_rate
    accel = 0.3 * rng.standard_normal((na, 3))
    accel[:, 0] += 2.0 * np.sin(2 * np.pi * 150 * ta)
    accel[:, 2] += 9.81
    normal = 1.5 + 0.2 * np.sin(2 * np.pi * 1.0 * np.arange(nf) / force_rate) + 0.02 * rng.standard_normal(nf)
    force = normal if force_axes == 1 else np.column_stack([0.3 * rng.standard_normal(nf), 0.1 + 0 * normal, normal])
    tm = np.arange(nm) / motion_rate
    if motion == "speed":
        motion_ch = {"speed": make_channel("speed", 80.0 + 5 * np.sin(2 * np.pi * 0.5 * tm), motion_rate)}
    else:
        path = 80.0 * tm
        motion_ch = {"position": make_channel("position", np.column_stack([0.6 * path, 0.8 * path]), motion_rate)}
    return Recording(make_channel("accel", accel, accel_rate), make_channel("force", force, force_rate), **motion_ch)


@pytest.fixture(scope="session")
def make_recording() -> Callable[..., Recording]:
    return synthetic_recording
