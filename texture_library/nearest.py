"""Perceptual nearest neighbour: which library texture feels most like the estimate.

Distance is weighted Euclidean in the 4-D bipolar rating space. A hysteresis
selector keeps the rendering model from flickering between neighbours when
successive windows' estimates wobble around a boundary. `decision_margin` says how close an
estimate is to such a boundary (the service's adaptive policy asks the full model there). Each of
these takes the distances once computed (`distances`, `distances_many`), so one estimate's
distances are computed once for its matches, its choice and its margin.
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
            raise ValueError(
                f"ratings must be ({len(self.ids)}, {len(ATTRIBUTES)}) for {len(self.ids)} ids, "
                f"got {self.ratings.shape}"
            )
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

    def distances_many(self, ratings: np.ndarray) -> np.ndarray:
        """(n, M) weighted distances from n bipolar ratings (n, 4)."""
        q = np.asarray(ratings, float)
        if q.ndim != 2 or q.shape[1] != len(ATTRIBUTES) or not np.all(np.isfinite(q)):
            raise ValueError(f"ratings must be finite (n, {len(ATTRIBUTES)}), got shape {q.shape}")
        return np.sqrt((((self.ratings[None, :, :] - q[:, None, :]) ** 2) * self.weights).sum(axis=2))

    def query(self, rating: np.ndarray, k: int = 3, distances: np.ndarray | None = None) -> list[Match]:
        """The k nearest entries, nearest first (distances: this rating's `distances`, if already computed)."""
        if k < 1:
            raise ValueError(f"k must be ≥ 1, got {k}")
        d = self.distances(rating) if distances is None else self._checked(distances)
        order = np.argsort(d, kind="stable")[:k]
        return [Match(self.ids[i], float(d[i])) for i in order]

    def _checked(self, distances: np.ndarray) -> np.ndarray:
        d = np.asarray(distances, float)
        if d.shape != (len(self.ids),):
            raise ValueError(f"distances must be ({len(self.ids)},) for this index, got {d.shape}")
        return d


def decision_margin(distances: np.ndarray) -> np.ndarray:
    """How far an estimate is from a library decision boundary: distance to the second-nearest entry minus the
    distance to the nearest (bipolar, ≥ 0; 0 on the boundary). distances: (M,) or (n, M) → () or (n,); inf
    when the library holds one entry (no boundary)."""
    d = np.asarray(distances, float)
    if d.ndim not in (1, 2) or d.shape[-1] < 1:
        raise ValueError(f"distances must be (M,) or (n, M) with M ≥ 1, got shape {d.shape}")
    if d.shape[-1] == 1:
        return np.full(d.shape[:-1], np.inf)
    two = np.partition(d, 1, axis=-1)[..., :2]
    return two[..., 1] - two[..., 0]


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

    def update(self, index: PerceptualIndex, rating: np.ndarray, distances: np.ndarray | None = None) -> str:
        """The entry to render after this estimate (distances: the rating's `index.distances`, if computed)."""
        d = index.distances(rating) if distances is None else index._checked(distances)
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
