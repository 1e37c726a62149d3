"""Per-attribute prediction intervals with conformal coverage, for the service to emit per window.

An `IntervalCalibration` holds, for a grid of coverage levels, the conformal quantile of the
calibration scores |truth − prediction| / scale (scale = 1 when unnormalised), computed from
out-of-fold predictions (cross-validation over training textures: the textures the interval is
later used on were never part of any calibration model's training, and never of the
calibration itself). `interval(pred, scale, level)` is then pred ± q(level)·scale, clipped to
the rating range: numpy, a few µs per window.

What was calibrated is named by `target`: "window" (the raw prediction of one 0.5 s window),
"ema" (the service's EMA-smoothed prediction, alpha `ema_alpha`), or "texture" (the mean over a
texture's windows, as LOOCV scores it). Windows of one texture are not independent: each
calibration texture weighs 1 in total, and the finite-sample correction counts textures.

When the input is flagged out of distribution the interval falls back to the hull of its own
band and the population band: the training ratings' central `level` interval, with the same
conformal correction (what is known of a texture when the input says nothing trustworthy). A
flagged window therefore never keeps a narrow interval.

JSON round trip: `to_dict` / `from_dict` (arrays as base64 float32, see models.inference.jsonarrays).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field

import numpy as np

from models.inference import jsonarrays
from texture_library.attributes import ATTRIBUTES, RATING_MAX, RATING_MIN

FORMAT = "hapticlink-interval-calibration"
VERSION = 1
LEVELS: tuple[float, ...] = tuple(round(0.5 + 0.01 * k, 2) for k in range(50))  # 0.50 … 0.99
TARGETS = ("window", "ema", "texture")
SCALES = ("none", "distance")


def conformal_quantile(scores: np.ndarray, level: float, groups: np.ndarray | None = None) -> float:
    """The split-conformal quantile of `scores` at `level`: the smallest s with
    (weighted) fraction of scores ≤ s at least level·(n + 1)/n, n the number of exchangeable units.

    scores: (m,) ≥ 0; groups: (m,) unit id per score (e.g. the texture of each window; every unit
    weighs 1, shared by its scores), None: every score is its own unit. Returns inf when n is too
    small for the level (no finite quantile guarantees it)."""
    scores = np.asarray(scores, float)
    if scores.ndim != 1 or scores.size == 0 or not np.all(np.isfinite(scores)):
        raise ValueError(f"scores must be a non-empty finite 1-D array, got shape {scores.shape}")
    if not 0 < level < 1:
        raise ValueError(f"level must lie in (0, 1), got {level}")
    if groups is None:
        weights, n = np.ones(scores.size), scores.size
    else:
        groups = np.asarray(groups)
        if groups.shape != scores.shape:
            raise ValueError(f"groups must be ({scores.size},), got {groups.shape}")
        _, inverse, counts = np.unique(groups, return_inverse=True, return_counts=True)
        weights, n = 1.0 / counts[inverse], counts.size
    need = level * (n + 1) / n
    if need > 1:
        return math.inf
    order = np.argsort(scores, kind="stable")
    cum = np.cumsum(weights[order]) / weights.sum()
    k = int(np.searchsorted(cum, need - 1e-12))
    return float(scores[order][min(k, scores.size - 1)])


def ema(preds: np.ndarray, alpha: float) -> np.ndarray:
    """The service's smoothing over a window sequence: s₀ = x₀, sₜ = α·xₜ + (1 − α)·sₜ₋₁. preds: (n, A)."""
    preds = np.asarray(preds, float)
    if not 0 < alpha <= 1:
        raise ValueError(f"alpha must lie in (0, 1], got {alpha}")
    out = np.empty_like(preds)
    state = None
    for t, x in enumerate(preds):
        state = x if state is None else alpha * x + (1 - alpha) * state
        out[t] = state
    return out


OOD_EMA_THRESHOLD = 0.1  # a flagged window's weight in the EMA state below which it no longer taints it


def ema_flags(flags: np.ndarray, alpha: float) -> np.ndarray:
    """Flags of the EMA-smoothed estimate: an estimate is flagged while flagged windows still carry
    more than OOD_EMA_THRESHOLD of its weight (α = 0.5: the flagged window and the next three)."""
    f = np.asarray(flags, float).reshape(-1, 1)
    return ema(f, alpha)[:, 0] > OOD_EMA_THRESHOLD


class EmaUncertainty:
    """Per-stream state for the interval of the EMA-smoothed estimate: the distance and the flag are
    smoothed exactly like the ratings (equal to `ema` / `ema_flags` over the same sequence)."""

    def __init__(self, alpha: float) -> None:
        if not 0 < alpha <= 1:
            raise ValueError(f"alpha must lie in (0, 1], got {alpha}")
        self.alpha = alpha
        self._distance: float | None = None
        self._flag = 0.0

    def update(self, flagged: bool, distance: float = 1.0) -> tuple[bool, float]:
        """One window's flag and distance → (is the smoothed estimate flagged, smoothed distance)."""
        if not (math.isfinite(distance) and distance > 0):
            raise ValueError(f"distance must be finite and > 0, got {distance}")
        before = self._distance
        first = before is None
        self._distance = distance if before is None else self.alpha * distance + (1 - self.alpha) * before
        self._flag = float(flagged) if first else self.alpha * float(flagged) + (1 - self.alpha) * self._flag
        return self._flag > OOD_EMA_THRESHOLD, self._distance


def calibrations_from_card(intervals: dict | None) -> dict[str, IntervalCalibration]:
    """A model card's `intervals` field → {target: IntervalCalibration} ({} for a card without one)."""
    if intervals is None:
        return {}
    if not isinstance(intervals, dict):
        raise ValueError(f"card intervals must be a dict of target → calibration, got {type(intervals).__name__}")
    return {target: IntervalCalibration.from_dict(obj) for target, obj in intervals.items()}


@dataclass(frozen=True)
class IntervalCalibration:
    """Conformal quantiles per level and attribute; see the module docstring.

    levels: (L,) increasing; quantiles: (L, A) of |r| / scale; prior_center: (A,) training mean
    rating; prior_quantiles: (L, A) conformal quantiles of |rating − prior_center| over training
    textures (the out-of-distribution fallback)."""

    target: str
    scale: str
    levels: tuple[float, ...]
    quantiles: np.ndarray
    prior_center: np.ndarray
    prior_quantiles: np.ndarray
    n_textures: int
    ema_alpha: float | None = None
    method: str = ""
    attributes: tuple[str, ...] = field(default=ATTRIBUTES)

    def __post_init__(self) -> None:
        if self.target not in TARGETS:
            raise ValueError(f"target must be one of {TARGETS}, got {self.target!r}")
        if self.scale not in SCALES:
            raise ValueError(f"scale must be one of {SCALES}, got {self.scale!r}")
        if self.target == "ema" and not (self.ema_alpha is not None and 0 < self.ema_alpha <= 1):
            raise ValueError(f"an 'ema' calibration needs ema_alpha in (0, 1], got {self.ema_alpha}")
        levels = np.asarray(self.levels, float)
        a = len(self.attributes)
        if levels.ndim != 1 or levels.size < 1 or np.any(np.diff(levels) <= 0) or levels[0] <= 0 or levels[-1] >= 1:
            raise ValueError(f"levels must increase strictly inside (0, 1), got {self.levels}")
        for name, arr, shape in (
            ("quantiles", self.quantiles, (levels.size, a)),
            ("prior_center", self.prior_center, (a,)),
            ("prior_quantiles", self.prior_quantiles, (levels.size, a)),
        ):
            if np.shape(arr) != shape:
                raise ValueError(f"{name} must be {shape}, got {np.shape(arr)}")
            if np.any(np.isnan(arr)) or (name != "prior_center" and np.any(np.asarray(arr) < 0)):
                raise ValueError(f"{name} must be non-negative numbers")

    # ---- fitting -----------------------------------------------------------------------------------
    @classmethod
    def fit(
        cls,
        pred: np.ndarray,
        truth: np.ndarray,
        *,
        groups: np.ndarray | None = None,
        scale: np.ndarray | None = None,
        scale_kind: str = "none",
        prior_ratings: np.ndarray,
        target: str = "window",
        ema_alpha: float | None = None,
        levels: tuple[float, ...] = LEVELS,
        method: str = "",
    ) -> IntervalCalibration:
        """From out-of-fold predictions.

        pred, truth: (m, A) bipolar (truth: the texture's mean rating, repeated per window);
        groups: (m,) texture of each row (None: one row per texture); scale: (m,) or (m, A) > 0,
        given iff scale_kind != "none"; prior_ratings: (T, A) training textures' ratings."""
        pred, truth = np.asarray(pred, float), np.asarray(truth, float)
        if pred.shape != truth.shape or pred.ndim != 2:
            raise ValueError(f"pred and truth must be equal (m, A) arrays, got {pred.shape} and {truth.shape}")
        s = _scale(scale, scale_kind, pred.shape)
        scores = np.abs(truth - pred) / s
        q = np.array([[conformal_quantile(scores[:, j], lv, groups) for j in range(pred.shape[1])] for lv in levels])
        prior = np.asarray(prior_ratings, float)
        center = prior.mean(axis=0)
        pq = np.array(
            [[conformal_quantile(np.abs(prior[:, j] - center[j]), lv) for j in range(prior.shape[1])] for lv in levels]
        )
        n = len(np.unique(groups)) if groups is not None else pred.shape[0]
        # inf (too few units for a level) cannot go into JSON: the widest band there is the whole range
        full = RATING_MAX - RATING_MIN
        return cls(
            target,
            scale_kind,
            tuple(levels),
            np.minimum(q, full / np.min(s) if s.size else full),
            center,
            np.minimum(pq, full),
            int(n),
            ema_alpha,
            method,
        )

    # ---- use ---------------------------------------------------------------------------------------
    def quantile(self, level: float) -> tuple[np.ndarray, np.ndarray]:
        """(model quantile (A,), prior quantile (A,)) at `level`, linear between calibrated levels (memoised:
        a service asks for the same level every window)."""
        memo = self.__dict__.setdefault("_memo", {})
        if level not in memo:
            lv = np.asarray(self.levels)
            if not lv[0] - 1e-9 <= level <= lv[-1] + 1e-9:
                raise ValueError(f"level {level} lies outside the calibrated {lv[0]:g}…{lv[-1]:g}")
            k = int(np.clip(np.searchsorted(lv, level), 1, max(lv.size - 1, 1)))
            if lv.size == 1:
                w, k = 0.0, 0
            else:
                w = float(np.clip((level - lv[k - 1]) / (lv[k] - lv[k - 1]), 0.0, 1.0))
            lo = max(k - 1, 0)
            memo[level] = (
                (1 - w) * self.quantiles[lo] + w * self.quantiles[k],
                (1 - w) * self.prior_quantiles[lo] + w * self.prior_quantiles[k],
            )
        q, p = memo[level]
        return q.copy(), p.copy()

    def interval(
        self, pred: np.ndarray, scale: np.ndarray | None = None, level: float = 0.9, ood: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi), each (n, A) bipolar in [−100, 100].

        pred: (n, A) or (A,); scale: (n,) or (n, A), required iff this calibration is normalised;
        ood: (n,) bool, windows flagged out of distribution (their band widens to include the
        population band)."""
        p = np.asarray(pred, float)
        one = p.ndim == 1
        p = np.atleast_2d(p)
        if p.ndim != 2 or p.shape[1] != len(self.attributes) or not np.all(np.isfinite(p)):
            raise ValueError(f"pred must be finite (n, {len(self.attributes)}), got {np.shape(pred)}")
        s = _scale(scale, self.scale, p.shape)
        q, prior = self.quantile(level)
        lo, hi = p - q * s, p + q * s
        if ood is not None:
            flags = np.asarray(ood, bool).reshape(-1)
            if flags.shape != (p.shape[0],):
                raise ValueError(f"ood must be ({p.shape[0]},) bool, got {np.shape(ood)}")
            lo[flags] = np.minimum(lo[flags], self.prior_center - prior)
            hi[flags] = np.maximum(hi[flags], self.prior_center + prior)
        lo, hi = np.clip(lo, RATING_MIN, RATING_MAX), np.clip(hi, RATING_MIN, RATING_MAX)
        return (lo[0], hi[0]) if one else (lo, hi)

    # ---- JSON --------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "format": FORMAT,
            "version": VERSION,
            "target": self.target,
            "scale": self.scale,
            "ema_alpha": self.ema_alpha,
            "method": self.method,
            "n_textures": self.n_textures,
            "attributes": list(self.attributes),
            "levels": list(self.levels),
            "quantiles": jsonarrays.encode(self.quantiles),
            "prior_center": jsonarrays.encode(self.prior_center),
            "prior_quantiles": jsonarrays.encode(self.prior_quantiles),
        }

    @classmethod
    def from_dict(cls, obj: object) -> IntervalCalibration:
        if not isinstance(obj, dict) or obj.get("format") != FORMAT:
            raise ValueError(
                f"not an interval calibration (format {obj.get('format') if isinstance(obj, dict) else obj!r})"
            )
        if obj.get("version") != VERSION:
            raise ValueError(f"interval calibration version {obj.get('version')!r}; this hapticlink reads {VERSION}")
        try:
            return cls(
                target=obj["target"],
                scale=obj["scale"],
                levels=tuple(float(v) for v in obj["levels"]),
                quantiles=jsonarrays.decode(obj["quantiles"], "quantiles").astype(float),
                prior_center=jsonarrays.decode(obj["prior_center"], "prior_center").astype(float),
                prior_quantiles=jsonarrays.decode(obj["prior_quantiles"], "prior_quantiles").astype(float),
                n_textures=int(obj["n_textures"]),
                ema_alpha=obj.get("ema_alpha"),
                method=obj.get("method", ""),
                attributes=tuple(obj["attributes"]),
            )
        except KeyError as exc:
            raise ValueError(f"interval calibration lacks {exc}") from None

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> IntervalCalibration:
        return cls.from_dict(jsonarrays.parse(text, "interval calibration"))


def _scale(scale: np.ndarray | None, kind: str, shape: tuple[int, int]) -> np.ndarray:
    if kind == "none":
        if scale is not None:
            raise ValueError("this calibration is unnormalised: pass scale=None")
        return np.ones(shape)
    if scale is None:
        raise ValueError(f"this calibration is normalised by {kind!r}: pass its scale")
    s = np.asarray(scale, float)
    if s.ndim == 1:
        s = s[:, None]
    if s.shape not in ((shape[0], 1), shape) or not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise ValueError(f"scale must be positive and finite, ({shape[0]},) or {shape}, got {np.shape(scale)}")
    return np.broadcast_to(s, shape)
