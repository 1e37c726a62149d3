"""NumPy arrays inside JSON, exactly: {"dtype", "shape", "base64"} of the little-endian bytes.

Model cards carry calibrations as JSON strings; base64 float32 is exact and about a third the
size of decimal text."""

from __future__ import annotations

import base64
import json

import numpy as np

_DTYPES = {"float32": "<f4", "float64": "<f8", "int64": "<i8", "bool": "|b1"}


def encode(array: np.ndarray, dtype: str = "float32") -> dict:
    if dtype not in _DTYPES:
        raise ValueError(f"dtype must be one of {sorted(_DTYPES)}, got {dtype!r}")
    arr = np.ascontiguousarray(np.asarray(array), dtype=_DTYPES[dtype])
    return {"dtype": dtype, "shape": list(arr.shape), "base64": base64.b64encode(arr.tobytes()).decode("ascii")}


def decode(obj: dict, what: str = "array") -> np.ndarray:
    try:
        dtype, shape, data = obj["dtype"], tuple(int(s) for s in obj["shape"]), obj["base64"]
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{what}: not an encoded array ({exc})") from None
    if dtype not in _DTYPES:
        raise ValueError(f"{what}: unknown dtype {dtype!r}")
    try:
        raw = base64.b64decode(data, validate=True)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{what}: bad base64 ({exc})") from None
    arr = np.frombuffer(raw, dtype=_DTYPES[dtype])
    if arr.size != int(np.prod(shape)):
        raise ValueError(f"{what}: {arr.size} values do not fill shape {shape}")
    return arr.reshape(shape).astype(dtype, copy=True)


def parse(text: str, what: str) -> object:
    """json.loads with a ValueError naming `what` (a model card's calibration, detector, …) on bad text."""
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{what} is not JSON: {exc}") from None
