"""Content-addressed on-disk cache of visual feature vectors.

key = sha256 over the image pixels (as float32, with shape), the view
parameters, the VisualConfig hash, the backbone name and its weights
fingerprint; value = a .npy file at ROOT/<key[:2]>/<key>.npy. Anything that
changes a feature changes its key, so entries never go stale and can be
deleted at any time.
"""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from texture_library.atomic_file import atomic_path

DEFAULT_CACHE_DIR = Path("cache") / "visual"
_KEY_FORMAT = "hapticlink-visual-cache-v1"
_KEY_PATTERN = re.compile(r"^[0-9a-f]{64}$")


def cache_key(
    image: np.ndarray,
    view: Mapping[str, Any],
    config_hash: str,
    backbone_name: str,
    weights_fingerprint: str,
) -> str:
    """64 hex digits identifying the features of one view of one image.

    image  (H, W) grayscale in [0, 1], or (H, W, 3) colour where the features read colour; hashed as contiguous
           float32 with its shape
    view   JSON-serialisable view parameters (see augment.view_params)
    """
    pixels = np.ascontiguousarray(image, dtype=np.float32)
    header = {
        "format": _KEY_FORMAT,
        "shape": list(pixels.shape),
        "view": dict(view),
        "config_hash": config_hash,
        "backbone": backbone_name,
        "weights_fingerprint": weights_fingerprint,
    }
    digest = hashlib.sha256()
    # Header first, length-prefixed, so no header/pixel split can collide with another.
    encoded = json.dumps(header, sort_keys=True, separators=(",", ":")).encode("utf-8")
    digest.update(len(encoded).to_bytes(8, "little"))
    digest.update(encoded)
    digest.update(pixels.tobytes())
    return digest.hexdigest()


class FeatureCache:
    """Feature vectors on disk under `root` (default: cache/visual relative to the current directory).

    The root is resolved when the cache is made, so a later chdir does not move it.
    """

    def __init__(self, root: str | Path = DEFAULT_CACHE_DIR) -> None:
        self.root = Path(root).expanduser().resolve()

    def __repr__(self) -> str:
        return f"FeatureCache(root={str(self.root)!r})"

    def path_for(self, key: str) -> Path:
        """Where the value of `key` lives (whether or not it exists)."""
        if not _KEY_PATTERN.match(key):
            raise ValueError(f"key must be 64 lowercase hex digits, got {key!r}")
        return self.root / key[:2] / f"{key}.npy"

    def __contains__(self, key: str) -> bool:
        return self.path_for(key).is_file()

    def get(self, key: str) -> np.ndarray | None:
        """The stored array, or None if absent or unreadable (an unreadable entry counts as a miss)."""
        path = self.path_for(key)
        if not path.is_file():
            return None
        try:
            return np.load(path, allow_pickle=False)
        except (OSError, ValueError, EOFError):
            return None

    def put(self, key: str, values: np.ndarray) -> Path:
        """Store `values` under `key` atomically (temp file in the same directory, then rename)."""
        path = self.path_for(key)
        with atomic_path(path) as tmp, open(tmp, "wb") as handle:
            np.save(handle, np.asarray(values), allow_pickle=False)
        return path
