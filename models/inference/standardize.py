"""Column standardisation shared by every model: fit on training rows, z bounded at ±Z_CLIP.

The same bound sits inside every exported graph (models.offline.onnx_graph, models.offline.nets.export), so a
model answers the same in evaluation and in the service.
"""

from __future__ import annotations

import numpy as np

Z_CLIP = 6.0  # |z| bound of standardised features


class Standardizer:
    """Column standardisation fit on training rows; constant columns pass through unscaled.

    transform clips z to ±Z_CLIP: a channel (e.g. a backbone unit) that is nearly silent on every
    training texture but fires on a new one would otherwise reach |z| in the hundreds and throw a
    linear model's prediction far outside the rating scale (seen on the synthetic world: ridge
    predicted +477 on a ±100 scale)."""

    @classmethod
    def from_stats(cls, mean: np.ndarray, std: np.ndarray) -> Standardizer:
        """A fitted standardiser from known column means and (positive) standard deviations."""
        s = cls()
        s.mean, s.std = np.asarray(mean, np.float64), np.asarray(std, np.float64)
        return s

    def fit(self, X: np.ndarray) -> Standardizer:
        self.mean = X.mean(axis=0)
        std = X.std(axis=0)
        self.std = np.where(std > 1e-12, std, 1.0)
        return self

    def transform(self, X: np.ndarray) -> np.ndarray:
        return np.clip((X - self.mean) / self.std, -Z_CLIP, Z_CLIP)
