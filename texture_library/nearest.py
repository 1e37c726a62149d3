"""Perceptual nearest neighbour: which library texture feels most like the estimate.

Distance is weighted Euclidean in the 4-D bipolar rating space. A hysteresis
selector keeps the rendering model from flickering between neighbours when
successive windows' estimates wobble around a boundary.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from texture_library.attributes import ATTRIBUTES


@dataclass(frozen=True)
class Match:
    id: str
    distance: float


class PerceptualIndex:
    """ids: M entry ids; ratings: (M, 4) bipolar; weights: (4,) ≥ 0, not all zero."""

    def __init__(self, ids: list[str], ratings: np.ndarray, weights: np.ndarray | None = None):
        self.ids = list(ids)
        self.ratings = np.asarray(ratings, float)
        if self.ratings.shape != (len(self.ids), len(ATTRIBUTES)) or not self.ids:
            raise ValueError(f"ratings must be ({len(self.ids)}, {len(ATTRIBUTES)}) for {len(self.ids)} ids, got {self.ratings.shape}")
        w = np.ones(len(ATTRIBUTES)) if weights is None else np.asarray(weights, float)
        if w.shape != (len(ATTRIBUTES),) or np.any(w < 0) or not np.any(w > 0) or not np.all(np.isfinite(w)):
            raise ValueError(f"weights must be {len(ATTRIBUTES)} finite values ≥ 0, not all zero; got {weights!r}")
        self.weights = w

    def distances(self, rating: np.ndarray) -> np.ndarray:
        """(M,) weighted distances from one bipolar rating (4,)."""
        q = np.asarray(rating, float)
        if q.shape != (len(ATTRIBUTES),) or not np.all(np.isfinite(q)):
            raise ValueError(f"rating must be {len(ATTRIBUTES)} finite values, got {rating!r}")
        return np.sqrt(((self.ratings - q) ** 2 * self.weights).sum(axis=1))

    def query(self, rating: np.ndarray, k: int = 3) -> list[Match]:
        """The k nearest entries, nearest first."""
        if k < 1:
            raise ValueError(f"k must be ≥ 1, got {k}")
        d = self.distances(rating)
        order = np.argsort(d, kind="stable")[:k]
        return [Match(self.ids[i], float(d[i])) for i in order]


class HysteresisSelector:
    """Keeps the current choice until a challenger is nearer by `margin` for `hold` windows in a row."""

    def __init__(self, margin: float = 5.0, hold: int = 2):
        if margin < 0 or hold < 1:
            raise ValueError(f"margin must be ≥ 0 and hold ≥ 1, got {margin}, {hold}")
        self.margin = margin
        self.hold = hold
        self.current: str | None = None
        self._challenger: str | None = None
        self._streak = 0

    def update(self, index: PerceptualIndex, rating: np.ndarray) -> str:
        d = index.distances(rating)
        best = index.ids[int(np.argmin(d))]
        if self.current is None or self.current not in index.ids:
            # first window, or the library no longer holds the current choice
            self.current, self._challenger, self._streak = best, None, 0
            return best
        if best == self.current:
            self._challenger, self._streak = None, 0
            return self.current
        gain = d[index.ids.index(self.current)] - d.min()
        if gain < self.margin:
            self._challenger, self._streak = None, 0
            return self.current
        self._streak = self._streak + 1 if best == self._challenger else 1
        self._challenger = best
        if self._streak >= self.hold:
            self.current, self._challenger, self._streak = best, None, 0
        return self.current
