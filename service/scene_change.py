"""Has the camera's scene changed? A cheap test on a small thumbnail, so a camera at 1–10 fps looking at one
surface costs one visual embedding, not one per frame.

`thumbnail(gray)`: (H, W) float in [0, 1] → (size, size) float32 block means (area average, no
resampling library). `scene_changed(a, b, threshold)`: mean absolute difference of two thumbnails
(0…1, grey levels) above `threshold`. Block means ignore sensor noise and JPEG artefacts (they
average out over a block) but see a different surface, a moved tool or a change of light.
"""

from __future__ import annotations

import numpy as np

THUMBNAIL_SIZE = 16


def thumbnail(gray: np.ndarray, size: int = THUMBNAIL_SIZE) -> np.ndarray:
    """(H, W) grey image in [0, 1] → (size, size) float32 means over a size×size grid of blocks.
    ValueError if the image is not 2-D or smaller than size×size."""
    gray = np.asarray(gray)
    if gray.ndim != 2 or gray.shape[0] < size or gray.shape[1] < size:
        raise ValueError(f"gray must be (H, W) with H, W ≥ {size}, got shape {gray.shape}")
    if not isinstance(size, int) or size < 1:
        raise ValueError(f"size must be an integer ≥ 1, got {size!r}")
    h, w = (gray.shape[0] // size) * size, (gray.shape[1] // size) * size
    g = gray[:h, :w].astype(np.float32)
    return g.reshape(size, h // size, size, w // size).mean(axis=(1, 3))


def frame_difference(a: np.ndarray, b: np.ndarray) -> float:
    """Mean absolute difference of two thumbnails (0…1 for images in [0, 1]); ValueError if shapes differ."""
    if a.shape != b.shape:
        raise ValueError(f"thumbnails must have the same shape, got {a.shape} and {b.shape}")
    return float(np.mean(np.abs(a - b)))


def scene_changed(previous: np.ndarray | None, current: np.ndarray, threshold: float) -> bool:
    """True if there is no previous thumbnail or the current one differs from it by more than `threshold`."""
    if not 0 <= threshold <= 1:
        raise ValueError(f"threshold must lie in [0, 1], got {threshold!r}")
    return previous is None or frame_difference(previous, current) > threshold
