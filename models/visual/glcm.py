"""Grey-level co-occurrence matrix (GLCM), with numpy only.

Offsets follow scikit-image's convention — a pair is (pixel at (r, c), pixel at
(r + round(d·sin θ), c + round(d·cos θ))) — so angle 0° pairs a pixel with its
right-hand neighbour and 90° with the one below. The matrix is made symmetric,
so the sign of an offset does not matter.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def quantize(img: np.ndarray, levels: int) -> np.ndarray:
    """Map [0, 1] intensities to grey levels 0 … levels−1 in equal-width bins (1.0 → top level).

    img      (H, W) float in [0, 1]
    returns  (H, W) int64
    """
    if levels < 2:
        raise ValueError(f"levels must be ≥ 2, got {levels}")
    if img.ndim != 2:
        raise ValueError(f"img must be 2-D (H, W), got shape {img.shape}")
    if not np.all(np.isfinite(img)):
        raise ValueError("img has non-finite values")
    lo, hi = float(img.min()), float(img.max())
    if lo < 0.0 or hi > 1.0:
        raise ValueError(f"img must lie in [0, 1], got [{lo:g}, {hi:g}]")
    return np.minimum((img * levels).astype(np.int64), levels - 1)


def offset(distance: int, angle_deg: float) -> tuple[int, int]:
    """(row, column) step of a pair at `distance` pixels along `angle_deg`."""
    theta = np.deg2rad(angle_deg)
    return int(round(distance * np.sin(theta))), int(round(distance * np.cos(theta)))


def cooccurrence_counts(q: np.ndarray, levels: int, dr: int, dc: int) -> np.ndarray:
    """Unnormalised, non-symmetric pair counts for one offset.

    q        (H, W) int grey levels in [0, levels)
    returns  (levels, levels) int64: [i, j] = #pairs with q[r, c] = i and q[r+dr, c+dc] = j
    """
    height, width = q.shape
    r0, r1 = max(0, -dr), min(height, height - dr)
    c0, c1 = max(0, -dc), min(width, width - dc)
    if r1 <= r0 or c1 <= c0:
        raise ValueError(f"offset ({dr}, {dc}) leaves no pixel pairs in a {width}×{height} image")
    first = q[r0:r1, c0:c1]
    second = q[r0 + dr : r1 + dr, c0 + dc : c1 + dc]
    flat = (first * levels + second).ravel()
    return np.bincount(flat, minlength=levels * levels).reshape(levels, levels)


def glcm(
    img: np.ndarray,
    levels: int = 16,
    distances: Sequence[int] = (1,),
    angles: Sequence[float] = (0.0, 45.0, 90.0, 135.0),
) -> np.ndarray:
    """Normalised symmetric GLCM averaged over all (distance, angle) offsets.

    img        (H, W) float in [0, 1]
    distances  pixel distances, each ≥ 1
    angles     directions in degrees
    returns    (levels, levels) float64, symmetric, sums to 1; each offset weighs equally
    """
    if len(distances) == 0 or len(angles) == 0:
        raise ValueError("distances and angles must both be non-empty")
    if any(d < 1 for d in distances):
        raise ValueError(f"distances must be ≥ 1, got {tuple(distances)}")
    q = quantize(img, levels)
    total = np.zeros((levels, levels), dtype=np.float64)
    for distance in distances:
        for angle in angles:
            counts = cooccurrence_counts(q, levels, *offset(distance, angle))
            sym = counts + counts.T
            total += sym / sym.sum()
    return total / (len(distances) * len(angles))


def glcm_features(
    img: np.ndarray,
    levels: int = 16,
    distances: Sequence[int] = (1,),
    angles: Sequence[float] = (0.0, 45.0, 90.0, 135.0),
) -> np.ndarray:
    """The GLCM flattened row-major: (levels²,) float32 — 256 values for 16 levels."""
    return glcm(img, levels, distances, angles).astype(np.float32).ravel()
