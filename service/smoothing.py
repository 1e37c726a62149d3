"""Per-session temporal state of the ratings: EMA smoothing and steadiness.

Steadiness (per attribute, 0…1) measures how *stable* the estimate is, not how accurate (how far to
trust an estimate is its interval: service/uncertainty.py):

    steadiness_a = clip(1 − sd_a / SD_UNIFORM, 0, 1)

where sd_a is the standard deviation of the last `n` raw (unsmoothed) window predictions
of attribute a and SD_UNIFORM = 200/√12 ≈ 57.7 is the standard deviation of ratings spread
uniformly over the whole bipolar range. 1 means the last n windows agree exactly; 0 means
they scatter as much as random ratings would. With fewer than two windows it is 0 (unknown).
A steady estimate can be steadily wrong: an operator reads it beside the interval, never instead.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from texture_library.attributes import ATTRIBUTES, RATING_MAX, RATING_MIN

SD_UNIFORM = (RATING_MAX - RATING_MIN) / math.sqrt(12.0)


class ExponentialSmoother:
    """s_t = α·x_t + (1 − α)·s_{t−1}; the first window passes unchanged. x: (4,) bipolar."""

    def __init__(self, alpha: float) -> None:
        if not 0 < alpha <= 1:
            raise ValueError(f"alpha must lie in (0, 1], got {alpha}")
        self.alpha = alpha
        self.state: np.ndarray | None = None

    def update(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        self.state = x.copy() if self.state is None else self.alpha * x + (1.0 - self.alpha) * self.state
        return self.state.copy()


class Steadiness:
    """Steadiness from the spread of the last `n` raw predictions (see the module docstring)."""

    def __init__(self, n: int) -> None:
        if n < 2:
            raise ValueError(f"steadiness needs at least 2 windows, got {n}")
        self.recent: deque[np.ndarray] = deque(maxlen=n)

    def update(self, raw: np.ndarray) -> np.ndarray:
        """Add one raw prediction (4,) → steadiness (4,) in [0, 1]."""
        self.recent.append(np.asarray(raw, dtype=np.float64))
        if len(self.recent) < 2:
            return np.zeros(len(ATTRIBUTES))
        sd = np.stack(self.recent).std(axis=0)
        return np.clip(1.0 - sd / SD_UNIFORM, 0.0, 1.0)
