"""Sliding windows as strided views (no copies)."""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import as_strided


def n_windows(n_samples: int, length: int, hop: int) -> int:
    """Complete windows of ``length`` samples, ``hop`` apart, in ``n_samples`` samples (0 if too short)."""
    if length < 1:
        raise ValueError(f"length must be ≥ 1 sample, got {length}")
    if hop < 1:
        raise ValueError(f"hop must be ≥ 1 sample, got {hop}")
    if n_samples < 0:
        raise ValueError(f"n_samples must be ≥ 0, got {n_samples}")
    return 0 if n_samples < length else 1 + (n_samples - length) // hop


def sliding_windows(x: np.ndarray, length: int, hop: int, axis: int = 0) -> np.ndarray:
    """Read-only view of complete windows along ``axis``.

    x: (..., n, ...) with n along ``axis`` → (..., n_windows, ..., length): the window index
    replaces ``axis`` and the window samples form a new last axis (numpy's convention).
    """
    x = np.asarray(x)
    n = x.shape[axis]
    count = n_windows(n, length, hop)
    if count == 0:
        raise ValueError(f"x has {n} samples along axis {axis}; a window needs {length}")
    # as_strided directly: sliding_window_view's argument handling costs more than the view, once per window batch
    ax = axis % x.ndim
    shape = x.shape[:ax] + (count,) + x.shape[ax + 1 :] + (length,)
    strides = x.strides[:ax] + (x.strides[ax] * hop,) + x.strides[ax + 1 :] + (x.strides[ax],)
    return as_strided(x, shape=shape, strides=strides, writeable=False)
