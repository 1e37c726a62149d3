"""Texture-level bootstrap intervals: textures, not windows, are the independent units."""

from __future__ import annotations

import numpy as np

from texture_library.attributes import REPORT_SCALE

DEFAULT_RESAMPLES = 2000


def per_texture_error(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(T,) mean absolute error over the attributes, 0–100 scale; pred, truth: (T, A) bipolar."""
    pred, truth = np.asarray(pred, float), np.asarray(truth, float)
    if pred.shape != truth.shape or pred.ndim != 2:
        raise ValueError(f"pred and truth must be equal (T, A) arrays, got {pred.shape} and {truth.shape}")
    return np.mean(np.abs(pred - truth), axis=1) * REPORT_SCALE


def bootstrap_mean(values: np.ndarray, *, level: float = 0.95, resamples: int = DEFAULT_RESAMPLES,
                   seed: int = 0) -> dict[str, float]:
    """Mean of per-texture values with a percentile bootstrap interval over textures.

    values: (T,) one number per texture. Returns {"mean", "lo", "hi"}."""
    values = np.asarray(values, float)
    if values.ndim != 1 or values.size < 2 or not np.all(np.isfinite(values)):
        raise ValueError(f"values must be a finite 1-D array of ≥ 2 textures, got shape {values.shape}")
    if not 0 < level < 1:
        raise ValueError(f"level must lie in (0, 1), got {level}")
    if resamples < 100:
        raise ValueError(f"resamples must be ≥ 100, got {resamples}")
    rng = np.random.default_rng(seed)
    means = values[rng.integers(0, values.size, size=(resamples, values.size))].mean(axis=1)
    tail = (1 - level) / 2
    return {"mean": float(values.mean()), "lo": float(np.quantile(means, tail)), "hi": float(np.quantile(means, 1 - tail))}


def paired_difference(a: np.ndarray, b: np.ndarray, **kwargs) -> dict[str, float]:
    """mean(a − b) over textures with its bootstrap interval (the same textures resampled for both)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.shape != b.shape:
        raise ValueError(f"a and b must hold the same textures, got shapes {a.shape} and {b.shape}")
    return bootstrap_mean(a - b, **kwargs)
