"""Has the camera's scene changed? A cheap test on a small thumbnail, so a camera at 1–10 fps looking at one
surface costs one visual embedding, not one per frame.

`thumbnail(gray)`: (H, W) float in [0, 1] → (2, size, size) float32: the block means and the block
standard deviations over a size×size grid (no resampling library). `frame_difference(a, b)`: the
mean absolute difference of the means plus that of the standard deviations (grey levels, 0…2);
`scene_changed(a, b, threshold)`: above `threshold`. Block means see a moved tool or a change of
light; block standard deviations see the surface's texture, which block means average away — two
HaTT photos of equal brightness differ in them (with means alone, 42 % of pairs of 40 HaTT training
textures differed by less than 0.05; with both, 1.3 % by less than 0.02). Sensor noise and JPEG
artefacts of one camera average out over a block: successive frames of one surface, shifted by a
few pixels, differ by ≤ 0.011 there (`benchmarks/adaptive.py`'s camera model), hence the default
threshold `FRAME_CHANGE` = 0.015 (the service's HAPTICLINK_FRAME_CHANGE, the robot's --frame-change). A camera
whose noise level jumps changes the standard deviations, and counts as a new scene.

Both sides run it: the robot client sends a frame only when its scene changed (drivers/robot/frames.py's
`FrameGate`), and the service embeds only such frames (service/adaptive.py).
"""

from __future__ import annotations

import numpy as np

THUMBNAIL_SIZE = 16
FRAME_CHANGE = 0.015  # above successive frames of one surface (≤ 0.011), below two surfaces (see above)


def thumbnail(gray: np.ndarray, size: int = THUMBNAIL_SIZE) -> np.ndarray:
    """(H, W) grey image in [0, 1] → (2, size, size) float32: means and standard deviations over a size×size grid
    of blocks. ValueError if the image is not 2-D or smaller than size×size."""
    gray = np.asarray(gray)
    if gray.ndim != 2 or gray.shape[0] < size or gray.shape[1] < size:
        raise ValueError(f"gray must be (H, W) with H, W ≥ {size}, got shape {gray.shape}")
    if not isinstance(size, int) or size < 1:
        raise ValueError(f"size must be an integer ≥ 1, got {size!r}")
    h, w = (gray.shape[0] // size) * size, (gray.shape[1] // size) * size
    blocks = gray[:h, :w].astype(np.float32).reshape(size, h // size, size, w // size)
    n = (h // size) * (w // size)
    # summed along the rows first (contiguous), then down the block: a third of the time of mean/std over
    # axes (1, 3) at 448 × 448, which every frame a service or robot receives pays
    means = blocks.sum(axis=3).sum(axis=1) / n
    blocks -= means[:, None, :, None]
    deviations = np.sqrt(np.square(blocks, out=blocks).sum(axis=3).sum(axis=1) / n)
    return np.stack([means, deviations])


#: a thumbnail on the wire (a robot's scene check): (2, THUMBNAIL_SIZE, THUMBNAIL_SIZE) float32, little-endian
THUMBNAIL_BYTES = 2 * THUMBNAIL_SIZE * THUMBNAIL_SIZE * 4


def thumbnail_bytes(thumb: np.ndarray) -> bytes:
    """(2, 16, 16) thumbnail → its THUMBNAIL_BYTES on the wire (float32, little-endian, C order)."""
    if thumb.shape != (2, THUMBNAIL_SIZE, THUMBNAIL_SIZE):
        raise ValueError(f"thumbnail must have shape (2, {THUMBNAIL_SIZE}, {THUMBNAIL_SIZE}), got {thumb.shape}")
    return np.ascontiguousarray(thumb, dtype="<f4").tobytes()


def check_thumbnail_length(n: int) -> None:
    """ValueError unless n bytes can be a thumbnail on the wire (a service checks a declared length before reading)."""
    if n != THUMBNAIL_BYTES:
        raise ValueError(
            f"a scene thumbnail is {THUMBNAIL_BYTES} bytes (2×{THUMBNAIL_SIZE}×{THUMBNAIL_SIZE} float32, "
            f"little-endian), got {n}"
        )


def thumbnail_from_bytes(payload: bytes) -> np.ndarray:
    """THUMBNAIL_BYTES → (2, 16, 16) float32 thumbnail; ValueError naming the problem if the size is wrong or a value
    is not a grey level's mean or deviation (finite, in [0, 1])."""
    check_thumbnail_length(len(payload))
    thumb = np.frombuffer(payload, dtype="<f4").astype(np.float32).reshape(2, THUMBNAIL_SIZE, THUMBNAIL_SIZE)
    if not (np.isfinite(thumb).all() and thumb.min() >= 0 and thumb.max() <= 1):
        raise ValueError("a scene thumbnail's block means and deviations must be finite grey levels in [0, 1]")
    return thumb


def frame_difference(a: np.ndarray, b: np.ndarray) -> float:
    """Mean absolute difference of two thumbnails' block means plus that of their block standard deviations (0…2
    for images in [0, 1]); ValueError if shapes differ."""
    if a.shape != b.shape:
        raise ValueError(f"thumbnails must have the same shape, got {a.shape} and {b.shape}")
    return float(np.abs(a - b).mean(axis=(-2, -1)).sum())


def scene_changed(previous: np.ndarray | None, current: np.ndarray, threshold: float) -> bool:
    """True if there is no previous thumbnail or the current one differs from it by more than `threshold`."""
    if not 0 <= threshold <= 2:
        raise ValueError(f"threshold must lie in [0, 2], got {threshold!r}")
    return previous is None or frame_difference(previous, current) > threshold
