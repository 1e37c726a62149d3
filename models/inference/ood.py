"""Is this window like what the model was trained on? An out-of-distribution detector for the service.

Fit on the training textures' features (offline); at serving time numpy only, a few µs per
window. A window is flagged `out_of_distribution` with its reasons when:

* tactile_outlier     its tactile feature vector lies off the training distribution: after
                      standardisation, a PCA subspace of the training windows gives Hotelling's T²
                      (far along the subspace) and Q (far from it); either above its limit
* speed_out_of_range  one of its speed statistics (min, max, mean over the window) lies outside
* force_out_of_range  the training windows' range, widened by `margin` of that range
* taps_out_of_range   one of its tap features (the taps group: from the surface's tap block, a tap speed and
                      its transient) lies outside the training windows' range, widened the same way: a tap
                      inside the physical bounds the service admits but unlike any the model learnt from
* visual_outlier      the frame's visual vector, scored the same way against the training views
* no_frame            the model reads images but there is no visual vector (tactile-only fallback)
* frame_*             the frame itself looks wrong (`check_frame`: under/over-exposed, blurred,
                      low contrast, a large black region) against the training photos' ranges

Limits are set from held-out textures, not training fits: inside `fit`, K folds over the
training textures score each texture with a subspace fitted without it, and a limit is the
`quantile` of those held-out scores. A clean texture from the same population is therefore
flagged at about 1 − quantile of its windows.

`scale(…)` turns the same scores into a positive per-window distance (≈ 1 on typical held-out
data, growing off-distribution) for intervals normalised by feature-space distance.

JSON round trip: `to_dict` / `from_dict` (arrays as base64 float32).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

from models.inference import jsonarrays
from models.tactile.config import STAT_NAMES
from models.tactile.taps import TAP_NAMES

FORMAT = "hapticlink-ood-detector"
VERSION = 1
TAP_COLUMNS = len(TAP_NAMES)
STD_FLOOR = 0.1  # × the block's median column std: a column nearly constant in training must not dominate


@dataclass(frozen=True)
class Subspace:
    """A PCA outlier model of one feature block. mean, std: (F,); components: (k, F); variances: (k,);
    t2_limit, q_limit: held-out limits; t2_typical, q_typical: held-out medians."""

    mean: np.ndarray
    std: np.ndarray
    components: np.ndarray
    variances: np.ndarray
    t2_limit: float
    q_limit: float
    t2_typical: float
    q_typical: float

    @staticmethod
    def _basis(X: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        mean = X.mean(axis=0)
        std = X.std(axis=0)
        std = np.maximum(std, STD_FLOOR * max(float(np.median(std)), 1e-12))
        Z = (X - mean) / std
        _, s, vt = np.linalg.svd(Z, full_matrices=False)
        k = min(k, vt.shape[0])
        variances = np.maximum(s[:k] ** 2 / max(Z.shape[0] - 1, 1), 1e-12)
        return mean, std, vt[:k], variances

    @staticmethod
    def _raw(X: np.ndarray, mean, std, components, variances) -> tuple[np.ndarray, np.ndarray]:
        Z = (X - mean) / std
        P = Z @ components.T
        t2 = np.sum(P**2 / variances, axis=1)
        q = np.sum((Z - P @ components) ** 2, axis=1) / Z.shape[1]
        return t2, q

    @classmethod
    def fit(
        cls, X: np.ndarray, groups: np.ndarray, *, k: int, quantile: float, folds: int = 5, seed: int = 0
    ) -> Subspace:
        """X: (n, F) rows; groups: (n,) texture per row (held-out limits split by texture)."""
        X, groups = np.asarray(X, float), np.asarray(groups)
        uniq = np.unique(groups)
        if uniq.size < 3:
            raise ValueError(f"fitting an OOD subspace needs rows of ≥ 3 textures, got {uniq.size}")
        if not 0.5 < quantile < 1:
            raise ValueError(f"quantile must lie in (0.5, 1), got {quantile}")
        perm = np.random.default_rng(seed).permutation(uniq)
        t2s, qs, weights = [], [], []
        for f in range(min(folds, uniq.size)):
            out = np.isin(groups, perm[f :: min(folds, uniq.size)])
            t2, q = cls._raw(X[out], *cls._basis(X[~out], k))
            t2s.append(t2)
            qs.append(q)
            # every held-out texture weighs the same, however many rows it has
            _, inv, cnt = np.unique(groups[out], return_inverse=True, return_counts=True)
            weights.append(1.0 / cnt[inv])
        t2, q, w = np.concatenate(t2s), np.concatenate(qs), np.concatenate(weights)
        basis = cls._basis(X, k)
        return cls(
            *basis,
            _wquantile(t2, w, quantile),
            _wquantile(q, w, quantile),
            _wquantile(t2, w, 0.5),
            _wquantile(q, w, 0.5),
        )

    def evaluate(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(score (n,), distance (n,)): score is the larger of T²/limit and Q/limit (> 1: outlier); distance
        the mean of T² and Q relative to their held-out medians (≈ 1 for typical held-out rows)."""
        t2, q = self._raw(np.atleast_2d(np.asarray(X, float)), self.mean, self.std, self.components, self.variances)
        return np.maximum(t2 / self.t2_limit, q / self.q_limit), 0.5 * (t2 / self.t2_typical + q / self.q_typical)

    def score(self, X: np.ndarray) -> np.ndarray:
        return self.evaluate(X)[0]

    def distance(self, X: np.ndarray) -> np.ndarray:
        return self.evaluate(X)[1]

    def to_dict(self) -> dict:
        return {
            "mean": jsonarrays.encode(self.mean),
            "std": jsonarrays.encode(self.std),
            "components": jsonarrays.encode(self.components),
            "variances": jsonarrays.encode(self.variances),
            "t2_limit": self.t2_limit,
            "q_limit": self.q_limit,
            "t2_typical": self.t2_typical,
            "q_typical": self.q_typical,
        }

    @classmethod
    def from_dict(cls, obj: dict, what: str) -> Subspace:
        try:
            mean, std, components, variances = (
                jsonarrays.decode(obj[k], f"{what}.{k}").astype(float)
                for k in ("mean", "std", "components", "variances")
            )
            t2_limit, q_limit, t2_typical, q_typical = (
                float(obj[k]) for k in ("t2_limit", "q_limit", "t2_typical", "q_typical")
            )
            return cls(mean, std, components, variances, t2_limit, q_limit, t2_typical, q_typical)
        except KeyError as exc:
            raise ValueError(f"{what} lacks {exc}") from None


def _wquantile(values: np.ndarray, weights: np.ndarray, q: float) -> float:
    order = np.argsort(values)
    cum = np.cumsum(weights[order]) / weights.sum()
    return float(max(values[order][min(int(np.searchsorted(cum, q)), values.size - 1)], 1e-12))


# ---- frames -----------------------------------------------------------------------------------------
FRAME_STATS = ("brightness", "contrast", "sharpness", "dark_fraction", "bright_fraction")
# least widening of each training range: photos of a collection can all share a value (none has a black
# pixel: dark_fraction ∈ [0, 0]) that one stray pixel of a good frame would otherwise leave
FRAME_MIN_PAD = np.array([0.05, 0.02, 0.2, 0.02, 0.02])
FRAME_REASONS = {  # (statistic, side) → reason
    ("brightness", "low"): "frame_underexposed",
    ("brightness", "high"): "frame_overexposed",
    ("bright_fraction", "high"): "frame_overexposed",
    ("dark_fraction", "high"): "frame_dark_region",
    ("contrast", "low"): "frame_low_contrast",
    ("sharpness", "low"): "frame_blurred",
}


def frame_statistics(gray: np.ndarray) -> np.ndarray:
    """(5,) of a grayscale frame (H, W) in [0, 1], on every second pixel (≈ 1 ms for 1024²):
    mean, std, sharpness (mean |Laplacian| / std: scale-free), fraction ≤ 2/255, fraction ≥ 253/255."""
    g = np.asarray(gray, np.float32)
    if g.ndim != 2 or min(g.shape) < 8:
        raise ValueError(f"gray must be an (H, W) image of at least 8×8, got {g.shape}")
    g = g[::2, ::2]
    std = float(g.std())
    lap = np.abs(4 * g[1:-1, 1:-1] - g[:-2, 1:-1] - g[2:, 1:-1] - g[1:-1, :-2] - g[1:-1, 2:])
    return np.array([g.mean(), std, float(lap.mean()) / max(std, 1e-6), np.mean(g <= 2 / 255), np.mean(g >= 253 / 255)])


# ---- the detector -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class OODResult:
    """flags: (n,) bool; reasons: per window, the sorted reasons (empty when in distribution);
    tactile_score: (n,) (> 1 outlier); visual_score: the frame's score or None; distance: (n,) > 0."""

    flags: np.ndarray
    reasons: list[list[str]]
    tactile_score: np.ndarray
    visual_score: float | None
    distance: np.ndarray


@dataclass(frozen=True)
class FrameCheck:
    """What one camera frame contributes to every window until the next frame: reasons (frame_*,
    visual_outlier, no_frame), the visual score (None without a frame) and the visual distance."""

    reasons: tuple[str, ...]
    visual_score: float | None
    visual_distance: float | None


def stat_columns(X: np.ndarray, start: int | None) -> np.ndarray:
    """(n, F) window features → (n, 6) speed/force statistics (STAT_NAMES): the 6 columns from `start`, or the
    last 6 when start is None. ValueError when they do not fit in F."""
    n = len(STAT_NAMES)
    if start is None:
        return X[:, -n:]
    if not 0 <= start <= X.shape[1] - n:
        raise ValueError(f"the speed/force statistics start at column {start}, beyond {X.shape[1]} features")
    return X[:, start : start + n]


def tap_columns(X: np.ndarray, start: int) -> np.ndarray:
    """(n, F) window features → (n, 3) tap features (models.tactile.taps.TAP_NAMES) from column `start`."""
    n = TAP_COLUMNS
    if not 0 <= start <= X.shape[1] - n:
        raise ValueError(f"the tap features start at column {start}, beyond {X.shape[1]} features")
    return X[:, start : start + n]


@dataclass(frozen=True)
class OODDetector:
    """See the module docstring. stat_lo, stat_hi: (6,) allowed range of the speed/force statistics
    (models.tactile.config.STAT_NAMES: the 6 tactile columns from `stat_start`, which the feature set's
    columns precede and the extra groups' follow — TactileConfig.group_slices()["base"] ends with them; None:
    the last 6 columns, right for a configuration without extra groups); frame_lo, frame_hi: (5,) allowed
    range of `frame_statistics` or None; taps_start: the first column of the taps group (None: no taps group, or a
    detector fitted before it was checked) and taps_lo, taps_hi: its columns' allowed range."""

    tactile: Subspace
    stat_lo: np.ndarray
    stat_hi: np.ndarray
    visual: Subspace | None = None
    frame_lo: np.ndarray | None = None
    frame_hi: np.ndarray | None = None
    n_textures: int = 0
    settings: dict = field(default_factory=dict)
    stat_start: int | None = None
    taps_start: int | None = None
    taps_lo: np.ndarray | None = None
    taps_hi: np.ndarray | None = None

    @property
    def n_tactile(self) -> int:
        return int(self.tactile.mean.size)

    @property
    def n_visual(self) -> int | None:
        return None if self.visual is None else int(self.visual.mean.size)

    @classmethod
    def fit(
        cls,
        tactile: list[np.ndarray],
        visual: np.ndarray | None = None,
        frames: np.ndarray | None = None,
        *,
        k_tactile: int = 16,
        k_visual: int = 8,
        quantile: float = 0.995,
        margin: float = 0.1,
        windows_per_texture: int | None = 64,
        folds: int = 5,
        seed: int = 0,
        stat_start: int | None = None,
        taps_start: int | None = None,
    ) -> OODDetector:
        """tactile: per training texture its windows (n_i, F); visual: (T, V, D) views or None;
        frames: (T, 5) `frame_statistics` of the training photos or None. windows_per_texture:
        a seeded subset per texture keeps fitting fast (windows of one stroke are redundant).
        stat_start: the first of the 6 speed/force statistic columns (None: the last 6); taps_start: the first of the
        taps group's columns (None: no taps group)."""
        if len(tactile) < 3:
            raise ValueError(f"an OOD detector needs ≥ 3 training textures, got {len(tactile)}")
        if not 0 <= margin <= 1:
            raise ValueError(f"margin must lie in [0, 1], got {margin}")
        rng = np.random.default_rng(seed)
        rows, groups = [], []
        for i, w in enumerate(tactile):
            w = np.asarray(w, float)
            if w.ndim != 2 or w.shape[1] != tactile[0].shape[1] or len(w) == 0:
                raise ValueError(f"texture {i}: tactile windows must be (n ≥ 1, {tactile[0].shape[1]}), got {w.shape}")
            keep = rng.permutation(len(w))[:windows_per_texture] if windows_per_texture else slice(None)
            rows.append(w[keep])
            groups.append(np.full(len(rows[-1]), i))
        X, g = np.concatenate(rows), np.concatenate(groups)
        sub_t = Subspace.fit(X, g, k=k_tactile, quantile=quantile, folds=folds, seed=seed)
        stats = np.concatenate([stat_columns(np.asarray(w, float), stat_start) for w in tactile])
        lo, hi = stats.min(axis=0), stats.max(axis=0)
        pad = margin * (hi - lo)
        sub_v = None
        if visual is not None:
            visual = np.asarray(visual, float)
            if visual.ndim != 3 or visual.shape[0] != len(tactile):
                raise ValueError(f"visual must be (T={len(tactile)}, V, D), got {visual.shape}")
            Xv = visual.reshape(-1, visual.shape[2])
            gv = np.repeat(np.arange(visual.shape[0]), visual.shape[1])
            sub_v = Subspace.fit(
                Xv, gv, k=min(k_visual, visual.shape[0] - 2), quantile=quantile, folds=folds, seed=seed
            )
        tlo = thi = None
        if taps_start is not None:
            taps = np.concatenate([tap_columns(np.asarray(w, float), taps_start) for w in tactile])
            tpad = margin * (taps.max(axis=0) - taps.min(axis=0))
            tlo, thi = taps.min(axis=0) - tpad, taps.max(axis=0) + tpad
        flo = fhi = None
        if frames is not None:
            frames = np.asarray(frames, float)
            if frames.shape != (len(tactile), len(FRAME_STATS)):
                raise ValueError(f"frames must be ({len(tactile)}, {len(FRAME_STATS)}), got {frames.shape}")
            fpad = np.maximum(margin * (frames.max(axis=0) - frames.min(axis=0)), FRAME_MIN_PAD)
            flo, fhi = frames.min(axis=0) - fpad, frames.max(axis=0) + fpad
        settings = {
            "k_tactile": k_tactile,
            "k_visual": k_visual,
            "quantile": quantile,
            "margin": margin,
            "windows_per_texture": windows_per_texture,
            "folds": folds,
            "seed": seed,
        }
        return cls(sub_t, lo - pad, hi + pad, sub_v, flo, fhi, len(tactile), settings, stat_start, taps_start, tlo, thi)

    # ---- serving -----------------------------------------------------------------------------------
    def check_visual(self, visual: np.ndarray | None, frame_reasons: list[str] | tuple[str, ...] = ()) -> FrameCheck:
        """Once per frame: visual (D,) the frame's visual vector (None: no frame); frame_reasons: `check_frame`."""
        reasons = set(frame_reasons)
        if self.visual is None:
            return FrameCheck(tuple(sorted(reasons)), None, None)
        if visual is None:
            return FrameCheck(tuple(sorted(reasons | {"no_frame"})), None, None)
        v = np.asarray(visual, float).reshape(-1)
        if v.size != self.n_visual or not np.all(np.isfinite(v)):
            raise ValueError(f"visual must be a finite ({self.n_visual},) vector, got {np.shape(visual)}")
        score, distance = self.visual.evaluate(v)
        if score[0] > 1:
            reasons.add("visual_outlier")
        return FrameCheck(tuple(sorted(reasons)), float(score[0]), float(distance[0]))

    def check(
        self,
        tactile: np.ndarray,
        visual: np.ndarray | None = None,
        *,
        frame_reasons: list[str] | tuple[str, ...] = (),
        frame: FrameCheck | None = None,
    ) -> OODResult:
        """tactile: (n, F) window features (the model's input); visual: (D,) the frame's visual vector,
        None when there is no frame; frame_reasons: `check_frame`'s answer for that frame. Or, cheaper per
        window, frame: `check_visual`'s answer computed once when the frame arrived (then visual and
        frame_reasons are ignored). Returns flags, reasons and distances per window."""
        X = np.asarray(tactile, float)
        if X.ndim == 1:
            X = X[None, :]
        if X.ndim != 2 or X.shape[1] != self.n_tactile:
            raise ValueError(f"tactile must be (n, {self.n_tactile}), got {np.shape(tactile)}")
        if not np.all(np.isfinite(X)):
            raise ValueError("tactile contains NaN or Inf")
        n = X.shape[0]
        t_score, distance = self.tactile.evaluate(X)
        f = frame if frame is not None else self.check_visual(visual, frame_reasons)
        common = list(f.reasons)
        v_score = f.visual_score
        if f.visual_distance is not None:
            distance = 0.5 * (distance + f.visual_distance)
        stats = stat_columns(X, self.stat_start)
        outside = (stats < self.stat_lo) | (stats > self.stat_hi)
        speed_bad = np.asarray(outside[:, :3].any(axis=1))
        force_bad = np.asarray(outside[:, 3:].any(axis=1))
        taps_bad = np.zeros(n, dtype=bool)
        if self.taps_start is not None and self.taps_lo is not None and self.taps_hi is not None:
            taps = tap_columns(X, self.taps_start)
            taps_bad = np.asarray(((taps < self.taps_lo) | (taps > self.taps_hi)).any(axis=1))
        reasons = []
        for i in range(n):
            r = common + [
                name
                for name, bad in (
                    ("force_out_of_range", force_bad[i]),
                    ("speed_out_of_range", speed_bad[i]),
                    ("taps_out_of_range", taps_bad[i]),
                    ("tactile_outlier", t_score[i] > 1),
                )
                if bad
            ]
            reasons.append(sorted(r))
        flags = np.array([bool(r) for r in reasons], dtype=bool)
        return OODResult(flags, reasons, t_score, v_score, np.maximum(distance, 1e-6))

    def check_frame(self, gray: np.ndarray) -> list[str]:
        """Reasons a frame (H, W) in [0, 1] looks unlike the training photos (empty: fine, or no ranges fitted)."""
        return self.frame_reasons(frame_statistics(gray))

    def frame_reasons(self, stats: np.ndarray) -> list[str]:
        """Reasons from a frame's `frame_statistics` (5,) (empty: fine, or no ranges fitted)."""
        if self.frame_lo is None or self.frame_hi is None:
            return []
        stats = np.asarray(stats, float)
        if stats.shape != (len(FRAME_STATS),):
            raise ValueError(f"stats must be ({len(FRAME_STATS)},), got {stats.shape}")
        out = set()
        for k, name in enumerate(FRAME_STATS):
            if stats[k] < self.frame_lo[k] and (name, "low") in FRAME_REASONS:
                out.add(FRAME_REASONS[(name, "low")])
            if stats[k] > self.frame_hi[k] and (name, "high") in FRAME_REASONS:
                out.add(FRAME_REASONS[(name, "high")])
        return sorted(out)

    @staticmethod
    def scale(result: OODResult) -> np.ndarray:
        """(n,) interval scale from a check: √distance (≈ 1 on typical data, growing off-distribution)."""
        return np.sqrt(result.distance)

    # ---- JSON --------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "format": FORMAT,
            "version": VERSION,
            "n_textures": self.n_textures,
            "settings": self.settings,
            "stat_names": list(STAT_NAMES),
            "stat_start": self.stat_start,
            "tactile": self.tactile.to_dict(),
            "stat_lo": jsonarrays.encode(self.stat_lo),
            "stat_hi": jsonarrays.encode(self.stat_hi),
            "visual": None if self.visual is None else self.visual.to_dict(),
            "frame_stats": list(FRAME_STATS),
            "frame_lo": None if self.frame_lo is None else jsonarrays.encode(self.frame_lo),
            "frame_hi": None if self.frame_hi is None else jsonarrays.encode(self.frame_hi),
            "taps_start": self.taps_start,
            "taps_lo": None if self.taps_lo is None else jsonarrays.encode(self.taps_lo),
            "taps_hi": None if self.taps_hi is None else jsonarrays.encode(self.taps_hi),
        }

    @classmethod
    def from_dict(cls, obj: object) -> OODDetector:
        if not isinstance(obj, dict) or obj.get("format") != FORMAT:
            raise ValueError("not an OOD detector (format field missing or different)")
        if obj.get("version") != VERSION:
            raise ValueError(f"OOD detector version {obj.get('version')!r}; this hapticlink reads {VERSION}")
        if obj.get("stat_names") != list(STAT_NAMES):
            raise ValueError(f"OOD detector statistics {obj.get('stat_names')} differ from {list(STAT_NAMES)}")
        try:
            dec = jsonarrays.decode
            return cls(
                Subspace.from_dict(obj["tactile"], "tactile"),
                dec(obj["stat_lo"]).astype(float),
                dec(obj["stat_hi"]).astype(float),
                None if obj["visual"] is None else Subspace.from_dict(obj["visual"], "visual"),
                None if obj["frame_lo"] is None else dec(obj["frame_lo"]).astype(float),
                None if obj["frame_hi"] is None else dec(obj["frame_hi"]).astype(float),
                int(obj["n_textures"]),
                dict(obj.get("settings", {})),
                None if obj.get("stat_start") is None else int(obj["stat_start"]),
                # absent from a detector written before the taps range was kept: no taps check
                None if obj.get("taps_start") is None else int(obj["taps_start"]),
                None if obj.get("taps_lo") is None else dec(obj["taps_lo"]).astype(float),
                None if obj.get("taps_hi") is None else dec(obj["taps_hi"]).astype(float),
            )
        except KeyError as exc:
            raise ValueError(f"OOD detector lacks {exc}") from None

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> OODDetector:
        return cls.from_dict(jsonarrays.parse(text, "OOD detector"))
