"""Deterministic augmented views of a texture image, for training.

A view is a small dict of parameters, applied in this order:
    rot90      k quarter turns counter-clockwise (0–3)
    flip       mirror left–right
    angle_deg  a further small rotation, degrees (bilinear, reflected borders)
    noise_std  std of additive Gaussian noise on [0, 1] intensities (clipped back to [0, 1])
    noise_seed seed of that noise
The dict goes into the feature cache key, so every view is computed once.
View 0 is always the identity. View i's parameters depend only on (seed, i),
so asking for more views keeps the earlier ones.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from scipy import ndimage

MAX_ANGLE_DEG = 15.0  # textures are mostly isotropic at this scale; bigger turns add little
MAX_NOISE_STD = 0.02  # about 5 grey levels of 8-bit sensor noise
VIEW_KEYS = ("rot90", "flip", "angle_deg", "noise_std", "noise_seed")
IDENTITY_VIEW: dict[str, Any] = {"rot90": 0, "flip": False, "angle_deg": 0.0, "noise_std": 0.0, "noise_seed": 0}


def view_params(n_views: int, seed: int) -> list[dict[str, Any]]:
    """Parameters of views 0 … n_views−1 (view 0 = IDENTITY_VIEW)."""
    if n_views < 1:
        raise ValueError(f"n_views must be ≥ 1, got {n_views}")
    views = [dict(IDENTITY_VIEW)]
    for index in range(1, n_views):
        rng = np.random.default_rng([seed, index])
        views.append(
            {
                "rot90": int(rng.integers(4)),
                "flip": bool(rng.random() < 0.5),
                # Rounded so the dict's JSON in the cache key is exactly what is applied.
                "angle_deg": round(float(rng.uniform(-MAX_ANGLE_DEG, MAX_ANGLE_DEG)), 3),
                "noise_std": round(float(rng.uniform(0.0, MAX_NOISE_STD)), 5),
                "noise_seed": int(rng.integers(2**31)),
            }
        )
    return views


def apply_view(img: np.ndarray, params: Mapping[str, Any]) -> np.ndarray:
    """One view of `img`.

    img      (H, W) float in [0, 1]
    params   a dict with exactly VIEW_KEYS
    returns  (H, W), or (W, H) after an odd number of quarter turns; float32 in [0, 1]
    """
    if img.ndim != 2:
        raise ValueError(f"img must be 2-D (H, W), got shape {img.shape}")
    if set(params) != set(VIEW_KEYS):
        raise ValueError(f"params must have keys {sorted(VIEW_KEYS)}, got {sorted(params)}")
    out = np.asarray(img, dtype=np.float32)
    out = np.rot90(out, k=int(params["rot90"]) % 4)
    if params["flip"]:
        out = out[:, ::-1]
    if params["angle_deg"]:
        # Reflected borders keep the corners textured instead of black wedges.
        out = ndimage.rotate(out, float(params["angle_deg"]), reshape=False, order=1, mode="reflect")
    if params["noise_std"]:
        rng = np.random.default_rng(int(params["noise_seed"]))
        out = out + rng.normal(0.0, float(params["noise_std"]), size=out.shape).astype(np.float32)
    return np.ascontiguousarray(np.clip(out, 0.0, 1.0), dtype=np.float32)


def augmented_views(img: np.ndarray, n_views: int, seed: int) -> list[np.ndarray]:
    """`n_views` views of `img` (view 0 is `img` itself); pair with `view_params(n_views, seed)`."""
    return [apply_view(img, params) for params in view_params(n_views, seed)]
