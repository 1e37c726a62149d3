"""Pool the visual feature vectors of several views of one surface into the one vector a model reads.

A view is a camera frame of the surface, or an augmented view of one photo (models.visual.augment).
Training pools the stored augmented views of each texture's photo; the service pools the vectors
of successive camera frames of the scene with the same function, so a model sees the same kind of
input in both. Torch-free (the service imports it).

The contract: (k, D) float32 → (D,) float32, the element-wise mean over the k views. The mean is
permutation-invariant and a running mean reaches the same value frame by frame (`ViewPool`).
A model's card records how many views it was trained with (`visual.views`): pooling fewer views
in the service gives a noisier input than the model was fit on (see the views curve in
reports/hatt-texnet/README.md for what that costs).
"""

from __future__ import annotations

import numpy as np

POOLING = "mean"  # recorded in model cards; the only pooling there is


def pool_views(embeddings: np.ndarray) -> np.ndarray:
    """The mean of k views' feature vectors.

    embeddings  (k, D) float, k ≥ 1: one row per view (backbone ⊕ GLCM, or any per-view vector)
    returns     (D,) float32
    """
    arr = np.asarray(embeddings)
    if arr.ndim != 2:
        raise ValueError(f"embeddings must be (k, D): one row per view, got shape {arr.shape}")
    if arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ValueError(f"embeddings must hold at least one view of at least one feature, got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.floating):
        raise ValueError(f"embeddings must be float, got dtype {arr.dtype}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("embeddings contain NaN or Inf")
    return arr.mean(axis=0, dtype=np.float64).astype(np.float32)


def pool_texture_views(visual: np.ndarray, views: int) -> np.ndarray:
    """Pool the first `views` views of every texture: (T, V, D) → (T, D) float32 (view 0 is the original photo)."""
    arr = np.asarray(visual)
    if arr.ndim != 3:
        raise ValueError(f"visual must be (textures, views, D), got shape {arr.shape}")
    if not 1 <= views <= arr.shape[1]:
        raise ValueError(f"views must lie in 1…{arr.shape[1]} (the views stored per texture), got {views}")
    return np.stack([pool_views(t[:views]) for t in arr]) if len(arr) else np.zeros((0, arr.shape[2]), np.float32)


class ViewPool:
    """Running pool of the latest `max_views` view vectors of one scene (the service: one per camera frame).

    add(vector (D,)) keeps the last max_views vectors; value() is pool_views of them, (D,) float32.
    reset() when the scene changes."""

    def __init__(self, max_views: int):
        if max_views < 1:
            raise ValueError(f"max_views must be ≥ 1, got {max_views}")
        self.max_views = max_views
        self._views: list[np.ndarray] = []

    def add(self, vector: np.ndarray) -> None:
        vec = np.asarray(vector)
        if vec.ndim != 1:
            raise ValueError(f"a view vector must be (D,), got shape {vec.shape}")
        if self._views and vec.shape != self._views[0].shape:
            raise ValueError(
                f"a view vector of width {vec.shape[0]} does not match the pool's {self._views[0].shape[0]}"
            )
        pool_views(vec[None])  # same checks as the pooled value: float, finite
        self._views.append(vec.astype(np.float32))
        del self._views[: -self.max_views]

    def __len__(self) -> int:
        return len(self._views)

    def value(self) -> np.ndarray:
        if not self._views:
            raise ValueError("no view has been added to the pool yet")
        return pool_views(np.stack(self._views))

    def reset(self) -> None:
        self._views.clear()
