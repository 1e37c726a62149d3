"""Images in → grayscale float arrays in [0, 1] out.

Accepts a path, encoded bytes, a Pillow image or a numpy array (camera frames),
so the dataset builders and the service share one conversion.
"""

from __future__ import annotations

import io
import re
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

ImageSource = str | Path | bytes | bytearray | Image.Image | np.ndarray

# ITU-R 601-2 luma, the weights Pillow's convert("L") uses, so a frame given as
# an RGB array and the same frame given as a PNG convert identically.
_LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float64)

_SIXTEEN_BIT_MODES = frozenset({"I;16", "I;16B", "I;16L", "I;16N", "I"})


def load_image(source: ImageSource, *, min_size: int = 224) -> np.ndarray:
    """Decode `source` to a grayscale image.

    source    path or bytes of any Pillow-readable file, a PIL image, or an array
              (H, W) / (H, W, 3|4) of uint8, uint16, or float in [0, 1]
    min_size  smallest allowed height and width, pixels (one patch must fit)
    returns   (H, W) float32 in [0, 1]
    """
    if isinstance(source, np.ndarray):
        gray = array_to_gray(source)
    else:
        gray = pil_to_gray(_open(source))
    check_size(gray, min_size)
    return gray


def load_colour(source: ImageSource, *, min_size: int = 224) -> np.ndarray:
    """Decode `source` in colour: (H, W, 3) float32 in [0, 1] (grayscale repeated over the channels, alpha
    dropped). The same frame `load_image` reads as gray: Pillow's luma of this array is that gray."""
    if isinstance(source, np.ndarray):
        if source.ndim == 2:
            rgb = np.repeat(_scale(source, "array")[..., None], 3, axis=2)
        elif source.ndim == 3 and source.shape[2] in (3, 4):
            rgb = _scale(source[..., :3], "array")
        else:
            raise ValueError(f"array must have shape (H, W) or (H, W, 3|4), got {source.shape}")
    else:
        image = _open(source)
        if image.mode in _SIXTEEN_BIT_MODES or image.mode == "F":
            rgb = np.repeat(pil_to_gray(image)[..., None].astype(np.float64), 3, axis=2)
        else:
            rgb = np.asarray(image.convert("RGB"), dtype=np.float64) / 255.0
    check_size(rgb[..., 0], min_size)
    return rgb.astype(np.float32)


def _open(source: str | Path | bytes | bytearray | Image.Image) -> Image.Image:
    if isinstance(source, Image.Image):
        return source
    stream: io.BytesIO | Path
    if isinstance(source, (bytes, bytearray)):
        stream, label = io.BytesIO(bytes(source)), f"{len(source)} bytes"
    elif isinstance(source, (str, Path)):
        path = Path(source)
        if not path.is_file():
            raise ValueError(f"source {str(path)!r} is not a file")
        stream, label = path, repr(str(path))
    else:
        raise ValueError(f"source must be a path, bytes, PIL image or numpy array, got {type(source).__name__}")
    try:
        image = Image.open(stream)
        image.load()  # decode now, so a truncated file fails here and not later
    except (UnidentifiedImageError, OSError, SyntaxError) as exc:
        # Pillow names an in-memory stream by its repr (<_io.BytesIO object at 0x…>); the label already says what it was
        why = re.sub(r" ?<_io\.BytesIO object at 0x[0-9A-Fa-f]+>", "", str(exc))
        raise ValueError(f"source {label} is not a readable image: {why}") from exc
    return image


def pil_to_gray(image: Image.Image) -> np.ndarray:
    """(H, W) float32 in [0, 1] from a Pillow image of any mode; 16-bit stays 16-bit."""
    if image.mode in _SIXTEEN_BIT_MODES:
        # Pillow opens 16-bit grayscale PNGs as "I;16" or "I"; keep the precision.
        values = np.asarray(image, dtype=np.float64)
        return np.clip(values / 65535.0, 0.0, 1.0).astype(np.float32)
    if image.mode == "F":
        return array_to_gray(np.asarray(image, dtype=np.float32))
    if image.mode != "L":
        # Alpha is dropped: a texture photo's transparency says nothing about the surface.
        image = image.convert("L")
    gray = np.array(image, dtype=np.float32)  # one conversion pass, divided in place: every served frame pays it
    gray /= 255.0
    return gray


def array_to_gray(array: np.ndarray) -> np.ndarray:
    """(H, W) float32 in [0, 1] from an (H, W) or (H, W, 3|4) uint8/uint16/float array."""
    if array.ndim == 3 and array.shape[2] in (3, 4):
        channels = array[..., :3]
        gray = _scale(channels, "array") @ _LUMA
    elif array.ndim == 2:
        gray = _scale(array, "array")
    else:
        raise ValueError(f"array must have shape (H, W) or (H, W, 3|4), got {array.shape}")
    return gray.astype(np.float32)


def _scale(values: np.ndarray, name: str) -> np.ndarray:
    if values.dtype == np.uint8:
        return values.astype(np.float64) / 255.0
    if values.dtype == np.uint16:
        return values.astype(np.float64) / 65535.0
    if np.issubdtype(values.dtype, np.floating):
        if not np.all(np.isfinite(values)):
            raise ValueError(f"{name} has non-finite values")
        lo, hi = float(values.min()), float(values.max())
        if lo < 0.0 or hi > 1.0:
            raise ValueError(f"{name} of floats must lie in [0, 1], got [{lo:g}, {hi:g}]")
        return values.astype(np.float64)
    raise ValueError(f"{name} dtype must be uint8, uint16 or float, got {values.dtype}")


def resize_shorter(gray: np.ndarray, size: int) -> np.ndarray:
    """Scale an image so its shorter side is `size` pixels, aspect ratio kept.

    gray     (H, W) float in [0, 1]
    returns  (round(H·k), round(W·k)) float32 in [0, 1], k = size / min(H, W); the input itself when k = 1.
             Pillow's bilinear filter widens with the reduction factor (antialiased) and has non-negative
             weights, so the output stays in [0, 1].
    """
    if size < 1:
        raise ValueError(f"size must be ≥ 1 pixel, got {size}")
    if gray.ndim != 2:
        raise ValueError(f"image must be 2-D (H, W), got shape {gray.shape}")
    height, width = gray.shape
    if min(height, width) == size:
        return np.asarray(gray, dtype=np.float32)
    k = size / min(height, width)
    shape = (max(size, int(round(width * k))), max(size, int(round(height * k))))  # Pillow: (width, height)
    image = Image.fromarray(np.ascontiguousarray(gray, dtype=np.float32), mode="F")
    out = np.asarray(image.resize(shape, Image.Resampling.BILINEAR), dtype=np.float32)
    return np.clip(out, 0.0, 1.0)


def check_size(gray: np.ndarray, min_size: int) -> None:
    """Raise ValueError unless `gray` is (H, W) with H, W ≥ min_size."""
    if gray.ndim != 2:
        raise ValueError(f"image must be 2-D (H, W), got shape {gray.shape}")
    height, width = gray.shape
    if min(height, width) < min_size:
        raise ValueError(
            f"image is {width}×{height} pixels; need at least {min_size}×{min_size} for {min_size}-pixel patches"
        )


def check_gray(img: np.ndarray, min_size: int) -> None:
    """Raise ValueError unless `img` is what `load_image` returns: (H, W) float in [0, 1], H, W ≥ min_size."""
    if not isinstance(img, np.ndarray) or not np.issubdtype(img.dtype, np.floating):
        kind = img.dtype if isinstance(img, np.ndarray) else type(img).__name__
        raise ValueError(f"img must be a float array in [0, 1] (see load_image), got {kind}")
    check_size(img, min_size)
    if not np.all(np.isfinite(img)):
        raise ValueError("img has non-finite values")
    lo, hi = float(img.min()), float(img.max())
    if lo < 0.0 or hi > 1.0:
        raise ValueError(f"img must lie in [0, 1], got [{lo:g}, {hi:g}]")
