"""Friction features: the tangential-to-normal force ratio while the tool slides (a stickiness cue).

Coulomb friction makes the tangential force μ·F_n against the motion, so the ratio of the
tangential force's magnitude √(fx² + fy²) to the normal force is μ whatever the stroke's
direction, speed or pressure. Per window (L samples, both forces low-passed by the preprocessor):

  friction_ratio      Σ F_t·F_n / Σ F_n²: the least-squares slope of F_t against F_n through the
                      origin — μ, weighted towards the samples pressed hardest (where the ratio is
                      least noisy); 0 when the tool does not press at all (Σ F_n² = 0)
  friction_ratio_std  standard deviation of F_t / F_n over the samples with F_n ≥ MIN_NORMAL_N:
                      how much the ratio wanders (stick–slip, speed-dependent friction); 0 if
                      fewer than two samples press that hard

The tangential magnitude is derived by the streaming preprocessor from 3-column force
(tangential x, tangential y, normal). With 1-column (normal only) force there is no friction
signal: a configuration with the friction group refuses such a stream with a ValueError
(models.tactile.preprocess); use a configuration without it.
"""

from __future__ import annotations

import numpy as np

FRICTION_NAMES: tuple[str, ...] = ("friction_ratio", "friction_ratio_std")
#: normal forces below this (N) are too light for a meaningful ratio (force-sensor noise ≈ 0.01 N)
MIN_NORMAL_N = 0.05


def friction_features(normal: np.ndarray, tangential: np.ndarray) -> np.ndarray:
    """normal: (n, L) N; tangential: (n, L) N, the magnitude of the tangential force → (n, 2) float64
    in FRICTION_NAMES order."""
    normal = np.asarray(normal, dtype=np.float64)
    tangential = np.asarray(tangential, dtype=np.float64)
    if normal.ndim != 2 or normal.shape != tangential.shape:
        raise ValueError(f"normal and tangential force must both be (n, L), got {normal.shape} and {tangential.shape}")
    if normal.shape[1] < 1:
        raise ValueError("friction features need windows of at least one sample")
    if not (np.all(np.isfinite(normal)) and np.all(np.isfinite(tangential))):
        raise ValueError("normal and tangential force must be finite (no NaN/Inf)")
    nn = np.sum(normal * normal, axis=1)
    ratio = np.divide(np.sum(tangential * normal, axis=1), nn, out=np.zeros_like(nn), where=nn > 0)
    pressed = normal >= MIN_NORMAL_N
    count = pressed.sum(axis=1)
    r = np.divide(tangential, normal, out=np.zeros_like(normal), where=pressed)
    mean = np.divide(r.sum(axis=1), count, out=np.zeros_like(nn), where=count > 0)
    var = np.divide(
        np.sum(np.where(pressed, (r - mean[:, None]) ** 2, 0.0), axis=1), count, out=np.zeros_like(nn), where=count > 1
    )
    return np.stack([ratio, np.sqrt(var)], axis=1)
