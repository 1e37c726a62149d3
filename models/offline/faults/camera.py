"""Faults of the camera frame. img: (H, W) float in [0, 1] grayscale (models.visual.image.load_image);
every function returns a new (H, W) float32 image in [0, 1] of the same shape."""

from __future__ import annotations

import io
import math

import numpy as np
from PIL import Image
from scipy import ndimage

from models.visual.image import check_size


def _image(img: np.ndarray) -> np.ndarray:
    if not isinstance(img, np.ndarray) or img.ndim != 2 or not np.issubdtype(img.dtype, np.floating):
        raise ValueError(f"img must be a 2-D float array in [0, 1], got {getattr(img, 'shape', type(img).__name__)}")
    check_size(img, 2)
    if not np.all(np.isfinite(img)) or img.min() < 0 or img.max() > 1:
        raise ValueError("img must hold finite values in [0, 1]")
    return np.asarray(img, dtype=np.float64)


def _out(x: np.ndarray) -> np.ndarray:
    return np.clip(x, 0.0, 1.0).astype(np.float32)


def blur(img: np.ndarray, sigma_px: float) -> np.ndarray:
    """Defocus or motion smear as a Gaussian blur of `sigma_px` pixels (reflected borders). sigma ≥ 0."""
    x = _image(img)
    if not (math.isfinite(sigma_px) and sigma_px >= 0):
        raise ValueError(f"sigma_px must be ≥ 0, got {sigma_px}")
    return _out(ndimage.gaussian_filter(x, sigma_px, mode="reflect") if sigma_px > 0 else x)


def exposure(img: np.ndarray, gain: float) -> np.ndarray:
    """Exposure `gain` times the original (linear intensities), saturating at 1: < 1 under-, > 1 over-exposed."""
    x = _image(img)
    if not (math.isfinite(gain) and gain > 0):
        raise ValueError(f"gain must be > 0, got {gain}")
    return _out(gain * x)


def sensor_noise(img: np.ndarray, std: float, rng: np.random.Generator) -> np.ndarray:
    """Additive white Gaussian noise of `std` (intensity units, 0.02 ≈ 5 grey levels of 8 bit), clipped to [0, 1]."""
    x = _image(img)
    if not (math.isfinite(std) and 0 <= std <= 1):
        raise ValueError(f"std must lie in [0, 1], got {std}")
    return _out(x + std * rng.standard_normal(x.shape))


def jpeg(img: np.ndarray, quality: int) -> np.ndarray:
    """The frame after an 8-bit JPEG round trip at `quality` (1 worst … 95 best, Pillow's scale)."""
    x = _image(img)
    if not (isinstance(quality, (int, np.integer)) and 1 <= quality <= 95):
        raise ValueError(f"quality must be an integer in [1, 95], got {quality!r}")
    buf = io.BytesIO()
    Image.fromarray(np.round(x * 255).astype(np.uint8), mode="L").save(buf, format="JPEG", quality=int(quality))
    return (np.asarray(Image.open(io.BytesIO(buf.getvalue())), dtype=np.float32) / 255.0).astype(np.float32)


def rotate(img: np.ndarray, angle_deg: float) -> np.ndarray:
    """The camera turned by `angle_deg` about its axis (bilinear, reflected borders keep corners textured)."""
    x = _image(img)
    if not math.isfinite(angle_deg):
        raise ValueError(f"angle_deg must be finite, got {angle_deg}")
    if angle_deg % 90 == 0 and x.shape[0] == x.shape[1]:
        return _out(np.rot90(x, k=int(angle_deg // 90) % 4))  # exact for quarter turns
    return _out(ndimage.rotate(x, angle_deg, reshape=False, order=1, mode="reflect"))


def distance(img: np.ndarray, factor: float) -> np.ndarray:
    """The camera at 1/`factor` of its distance: the surface appears `factor` times as large.

    factor > 1: closer, the centre 1/factor of the frame fills it (bilinear); factor < 1: farther,
    the texture shrinks (antialiased first) and continues by reflection past the original edges.
    factor in [0.1, 10]."""
    x = _image(img)
    if not (math.isfinite(factor) and 0.1 <= factor <= 10):
        raise ValueError(f"factor must lie in [0.1, 10], got {factor}")
    if factor == 1:
        return _out(x)
    if factor < 1:
        x = ndimage.gaussian_filter(x, (1 / factor - 1) / 2, mode="reflect")  # skimage's antialiasing sigma
    h, w = x.shape
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    cy, cx = (h - 1) / 2, (w - 1) / 2
    coords = np.stack([cy + (rows - cy) / factor, cx + (cols - cx) / factor])
    return _out(ndimage.map_coordinates(x, coords, order=1, mode="mirror"))


def occlude(img: np.ndarray, fraction: float, value: float = 0.0) -> np.ndarray:
    """Something in front of the surface: a band from the left edge covering `fraction` of the frame's
    area (round(fraction·W) full-height columns) is replaced by `value`. fraction in [0, 1)."""
    x = _image(img)
    if not (math.isfinite(fraction) and 0 <= fraction < 1):
        raise ValueError(f"fraction must lie in [0, 1), got {fraction}")
    if not (math.isfinite(value) and 0 <= value <= 1):
        raise ValueError(f"value must lie in [0, 1], got {value}")
    out = x.copy()
    out[:, : int(round(fraction * x.shape[1]))] = value
    return _out(out)
