"""Overlapping square patches that tile an image on an evenly spaced grid."""

from __future__ import annotations

import numpy as np


def patch_origins(length: int, size: int, grid: int) -> np.ndarray:
    """Start offsets of `grid` patches of `size` along an axis of `length` pixels.

    The first starts at 0 and the last ends flush with the edge; the ones
    between are evenly spaced (rounded to whole pixels), so they overlap
    whenever grid × size > length. A grid of 1 takes the centred patch.
    returns (grid,) int64
    """
    if size < 1:
        raise ValueError(f"size must be ≥ 1, got {size}")
    if grid < 1:
        raise ValueError(f"grid must be ≥ 1, got {grid}")
    if length < size:
        raise ValueError(f"length {length} is smaller than the patch size {size}")
    if grid == 1:
        return np.array([(length - size) // 2], dtype=np.int64)
    return np.rint(np.linspace(0.0, float(length - size), grid)).astype(np.int64)


def extract_patches(img: np.ndarray, size: int = 224, grid: int = 7) -> np.ndarray:
    """Cut grid × grid overlapping patches from a grayscale image.

    img      (H, W) float, H and W ≥ size
    returns  (grid², size, size) float32, row-major: patch k is at grid row k // grid, column k % grid
    """
    if img.ndim != 2:
        raise ValueError(f"img must be 2-D (H, W), got shape {img.shape}")
    height, width = img.shape
    if height < size or width < size:
        raise ValueError(f"img is {width}×{height} pixels, smaller than one {size}×{size} patch")
    rows = patch_origins(height, size, grid)
    cols = patch_origins(width, size, grid)
    out = np.empty((grid * grid, size, size), dtype=np.float32)
    for i, r in enumerate(rows):
        for j, c in enumerate(cols):
            out[i * grid + j] = img[r : r + size, c : c + size]
    return out


def check_patch_batch(patches: np.ndarray, size: int) -> np.ndarray:
    """Validate a batch of grayscale patches for a backbone and return it as contiguous float32.

    patches  (n, size, size) float in [0, 1]; n may be 0
    """
    if not isinstance(patches, np.ndarray):
        raise ValueError(f"patches must be a numpy array, got {type(patches).__name__}")
    if patches.ndim != 3 or patches.shape[1:] != (size, size):
        raise ValueError(f"patches must have shape (n, {size}, {size}), got {patches.shape}")
    if not np.issubdtype(patches.dtype, np.floating):
        raise ValueError(f"patches must be float in [0, 1], got dtype {patches.dtype}")
    out = np.ascontiguousarray(patches, dtype=np.float32)
    if out.size:
        if not np.all(np.isfinite(out)):
            raise ValueError("patches has non-finite values")
        lo, hi = float(out.min()), float(out.max())
        if lo < 0.0 or hi > 1.0:
            raise ValueError(f"patches must lie in [0, 1], got [{lo:g}, {hi:g}]")
    return out
