"""Tactile recordings rendered from vibration models along freehand trajectories.

HaTT and the synthetic world produce their tactile streams the same way — a
texture's vibration model driven along a seeded freehand (speed, force)
trajectory — with the very code the simulated robot uses (texture_library.stroke).
"""

from __future__ import annotations

import zlib
from collections.abc import Callable

import numpy as np

from texture_library.recording import Recording, recording_from_stroke
from texture_library.stroke import stroke
from texture_library.trajectory import Trajectory, freehand, model_ranges
from texture_library.vibration import VibrationModel


def texture_rng(seed: int, texture: str) -> np.random.Generator:
    """A generator that depends only on (seed, texture id), not on build order or worker."""
    return np.random.default_rng([seed, zlib.crc32(texture.encode())])


def simulated_recording(
    model: VibrationModel,
    duration_s: float,
    rng: np.random.Generator,
    transform: Callable[[Trajectory], Trajectory] | None = None,
) -> Recording:
    """duration_s of freehand stroking over `model`, as the tool's sensors would record it.

    transform: changes the trajectory before it is rendered (e.g. faster or harder strokes in a
    robustness study); with the same generator state the stroke is otherwise the dataset's own."""
    trajectory = freehand(duration_s, rng, rate_hz=model.rate_hz, **model_ranges(model.max_speed, model.max_force))
    if transform is not None:
        trajectory = transform(trajectory)
    s = stroke(model, trajectory, rng)
    return recording_from_stroke(s.accel, s.force, s.speed, s.rate_hz)
