"""The training sets of the studies and the inputs each one predicts — one definition for fits and detectors.

* loocv i          train on every texture but i; predict texture i (clean and every variant)
* calibration key  the intervals' nested calibration without 79 × K refits: the textures are split
                   into K groups G_1…G_K once; model (a, b) trains without G_a ∪ G_b, model (a,)
                   without G_a. For held-out texture i ∈ G_a, the calibration residual of texture
                   j comes from model (a, b(j)) (or (a,) when j ∈ G_a): a model that saw neither
                   i nor j. K + K(K−1)/2 fits serve all folds; each calibration model trains on
                   (K−2)/K of the textures instead of (K−1)/K, so residuals err on the large side.
* shift g          train without material group g; predict its textures (inner K-fold inside the
                   training groups calibrates the intervals under shift)
"""

from __future__ import annotations

import numpy as np

CALIBRATION_GROUPS = 10


def partition(n: int, k: int = CALIBRATION_GROUPS, seed: int = 0) -> np.ndarray:
    """(n,) group index 0…k−1 per texture, balanced and seeded (fixed across models and seeds)."""
    if not 2 <= k <= n:
        raise ValueError(f"need 2 ≤ k ≤ n textures, got k={k}, n={n}")
    part = np.empty(n, int)
    part[np.random.default_rng(seed).permutation(n)] = np.arange(n) % k
    return part


def calibration_keys(k: int) -> list[tuple[int, ...]]:
    return [(a,) for a in range(k)] + [(a, b) for a in range(k) for b in range(a + 1, k)]


def key_excludes(part: np.ndarray, key: tuple[int, ...]) -> np.ndarray:
    """(n,) True for the textures the calibration model `key` does not train on."""
    return np.isin(part, key)


def calibration_key(part: np.ndarray, i: int, j: int) -> tuple[int, ...]:
    """The model whose prediction of texture j calibrates the interval of held-out texture i (j ≠ i)."""
    a, b = int(part[i]), int(part[j])
    return (a,) if a == b else (min(a, b), max(a, b))


def calibration_sources(part: np.ndarray, i: int) -> list[tuple[int, tuple[int, ...]]]:
    """[(j, key)] for every texture j ≠ i."""
    return [(j, calibration_key(part, i, j)) for j in range(part.size) if j != i]


def inner_folds(train: np.ndarray, k: int, seed: int = 0) -> list[np.ndarray]:
    """k disjoint held-out sets covering `train` (indices), seeded."""
    perm = np.random.default_rng(seed).permutation(train)
    return [np.sort(perm[f::k]) for f in range(k)]
