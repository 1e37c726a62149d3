"""The four perceptual attributes and their bipolar scale.

Inside hapticlink every rating is bipolar, −100…100: −100 is the first pole
(rough, flat, sticky, hard) and +100 the second (smooth, bumpy, slippery,
soft). Metrics are reported on the 0–100 scale, i.e. bipolar error ÷ 2.
"""

from __future__ import annotations

import numpy as np

ATTRIBUTES: tuple[str, ...] = ("rough_smooth", "flat_bumpy", "sticky_slippery", "hard_soft")
POLES: dict[str, tuple[str, str]] = {
    "rough_smooth": ("rough", "smooth"),
    "flat_bumpy": ("flat", "bumpy"),
    "sticky_slippery": ("sticky", "slippery"),
    "hard_soft": ("hard", "soft"),
}
RATING_MIN = -100.0
RATING_MAX = 100.0
#: bipolar error × this = error on the 0–100 scale used in reports
REPORT_SCALE = 0.5


def check_ratings(ratings: np.ndarray, what: str = "ratings") -> np.ndarray:
    """Validate bipolar ratings: (..., 4) finite values in [−100, 100]."""
    arr = np.asarray(ratings, dtype=float)
    if arr.ndim == 0 or arr.shape[-1] != len(ATTRIBUTES):
        raise ValueError(
            f"{what}: last axis must have {len(ATTRIBUTES)} attributes {ATTRIBUTES}, got shape {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{what}: contains NaN or Inf")
    if arr.min() < RATING_MIN or arr.max() > RATING_MAX:
        raise ValueError(
            f"{what}: values must lie in [{RATING_MIN:g}, {RATING_MAX:g}], got [{arr.min():g}, {arr.max():g}]"
        )
    return arr
