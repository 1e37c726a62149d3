"""Texture-level bootstrap: 95 % intervals of MAE/RMSE and of paired MAE differences and ratios between two models.

Textures are the unit that was sampled (the raters and the photos come per texture), so the
bootstrap resamples textures with replacement — all four attributes of a texture together, and in
a paired comparison the same textures for both models. Percentile intervals; errors on the 0–100
report scale. `per_texture_error` and `bootstrap_mean` serve studies that carry one number per
texture (the trade-off studies: MAE over the attributes, coverage, a difference of two errors).
"""

from __future__ import annotations

import numpy as np

from texture_library.attributes import ATTRIBUTES, REPORT_SCALE

N_BOOT = 2000
LEVEL = 0.95
KEYS = (*ATTRIBUTES, "mean")


def texture_errors(predictions: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-texture absolute and squared errors (0–100 scale), averaged over seeds.

    predictions (S, T, 4) bipolar (S seeds; or (T, 4) for one), truth (T, 4) bipolar
    returns     (abs (T, 4), squared (T, 4)); the MAE over textures of abs is the seed-mean MAE."""
    pred = np.asarray(predictions, float)
    pred = pred[None] if pred.ndim == 2 else pred
    truth = np.asarray(truth, float)
    if pred.ndim != 3 or pred.shape[1:] != truth.shape or truth.ndim != 2 or truth.shape[1] != len(ATTRIBUTES):
        raise ValueError(
            f"predictions must be (S, T, {len(ATTRIBUTES)}) or (T, {len(ATTRIBUTES)}) matching truth (T, "
            f"{len(ATTRIBUTES)}), got {np.shape(predictions)} and {truth.shape}"
        )
    err = (pred - truth[None]) * REPORT_SCALE
    return np.abs(err).mean(axis=0), (err**2).mean(axis=0)


def resample_indices(n_textures: int, n_boot: int = N_BOOT, seed: int = 0) -> np.ndarray:
    """(n_boot, n_textures) texture indices drawn with replacement (fixed seed: reproducible intervals)."""
    if n_textures < 2:
        raise ValueError(f"a bootstrap needs at least 2 textures, got {n_textures}")
    if n_boot < 100:
        raise ValueError(f"n_boot must be ≥ 100 for a 95 % interval, got {n_boot}")
    return np.random.default_rng(seed).integers(0, n_textures, size=(n_boot, n_textures))


def _interval(samples: np.ndarray, level: float) -> tuple[np.ndarray, np.ndarray]:
    tail = (1.0 - level) / 2.0 * 100.0
    return np.percentile(samples, tail, axis=0), np.percentile(samples, 100.0 - tail, axis=0)


def _table(point: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> dict[str, dict[str, float]]:
    return {
        "value": dict(zip(KEYS, map(float, point))),
        "lo": dict(zip(KEYS, map(float, lo))),
        "hi": dict(zip(KEYS, map(float, hi))),
    }


def bootstrap_errors(
    abs_err: np.ndarray, sq_err: np.ndarray | None = None, *, n_boot: int = N_BOOT, seed: int = 0, level: float = LEVEL
) -> dict[str, dict]:
    """MAE (and RMSE when sq_err is given) per attribute and their mean, each with its interval.

    abs_err, sq_err: (T, 4) per-texture errors (see texture_errors).
    returns {"mae": {"value": {attr: v, …, "mean": v}, "lo": {…}, "hi": {…}}, "rmse": {…}}"""
    abs_err = np.asarray(abs_err, float)
    if abs_err.ndim != 2 or abs_err.shape[1] != len(ATTRIBUTES):
        raise ValueError(f"abs_err must be (T, {len(ATTRIBUTES)}), got {abs_err.shape}")
    idx = resample_indices(len(abs_err), n_boot, seed)
    mae = abs_err[idx].mean(axis=1)  # (B, 4)
    with_mean = lambda a: np.concatenate([a, a.mean(axis=-1, keepdims=True)], axis=-1)  # noqa: E731
    point = with_mean(abs_err.mean(axis=0))
    out = {"mae": _table(point, *_interval(with_mean(mae), level))}
    if sq_err is not None:
        sq_err = np.asarray(sq_err, float)
        if sq_err.shape != abs_err.shape:
            raise ValueError(f"sq_err must have abs_err's shape {abs_err.shape}, got {sq_err.shape}")
        rmse = np.sqrt(sq_err[idx].mean(axis=1))
        out["rmse"] = _table(with_mean(np.sqrt(sq_err.mean(axis=0))), *_interval(with_mean(rmse), level))
    return out


def _paired(abs_a: np.ndarray, abs_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    abs_a, abs_b = np.asarray(abs_a, float), np.asarray(abs_b, float)
    if abs_a.shape != abs_b.shape or abs_a.ndim != 2 or abs_a.shape[1] != len(ATTRIBUTES):
        raise ValueError(
            f"paired errors must both be (T, {len(ATTRIBUTES)}) over the same textures, got "
            f"{abs_a.shape} and {abs_b.shape}"
        )
    return abs_a, abs_b


def paired_ratio(
    abs_a: np.ndarray, abs_b: np.ndarray, *, n_boot: int = N_BOOT, seed: int = 0, level: float = LEVEL
) -> dict[str, dict[str, float]]:
    """MAE(a) ÷ MAE(b) per attribute and for the mean over attributes, with the interval from resampling the
    same textures for both (e.g. a model against predict-the-mean: below 1 it beats the mean).

    ValueError when b's MAE is 0 on some attribute (no ratio to take)."""
    abs_a, abs_b = _paired(abs_a, abs_b)
    if np.any(abs_b.mean(axis=0) == 0):
        raise ValueError("paired_ratio: the reference has zero error on some attribute; its ratio is undefined")
    idx = resample_indices(len(abs_a), n_boot, seed)
    with_mean = lambda a: np.concatenate([a, a.mean(axis=-1, keepdims=True)], axis=-1)  # noqa: E731
    with np.errstate(divide="ignore", invalid="ignore"):  # a resample of only error-free reference textures
        samples = with_mean(abs_a[idx].mean(axis=1)) / with_mean(abs_b[idx].mean(axis=1))
    samples = np.where(np.isfinite(samples), samples, np.inf)
    point = with_mean(abs_a.mean(axis=0)) / with_mean(abs_b.mean(axis=0))
    return _table(point, *_interval(samples, level))


def paired_difference(
    abs_a: np.ndarray, abs_b: np.ndarray, *, n_boot: int = N_BOOT, seed: int = 0, level: float = LEVEL
) -> dict[str, dict[str, float]]:
    """MAE(a) − MAE(b) per attribute and mean, with the interval from resampling the same textures for both.

    An interval that excludes 0 says a and b differ on this set of textures; negative: a is better."""
    abs_a, abs_b = _paired(abs_a, abs_b)
    diff = abs_a - abs_b
    idx = resample_indices(len(diff), n_boot, seed)
    samples = diff[idx].mean(axis=1)
    samples = np.concatenate([samples, samples.mean(axis=1, keepdims=True)], axis=1)
    point = np.concatenate([diff.mean(axis=0), [diff.mean()]])
    return _table(point, *_interval(samples, level))


def per_texture_error(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(T,) mean absolute error over the attributes, 0–100 scale; pred, truth: (T, A) bipolar."""
    pred, truth = np.asarray(pred, float), np.asarray(truth, float)
    if pred.shape != truth.shape or pred.ndim != 2:
        raise ValueError(f"pred and truth must be equal (T, A) arrays, got {pred.shape} and {truth.shape}")
    return np.mean(np.abs(pred - truth), axis=1) * REPORT_SCALE


def bootstrap_mean(
    values: np.ndarray, *, level: float = LEVEL, n_boot: int = N_BOOT, seed: int = 0
) -> dict[str, float]:
    """Mean of per-texture values with a percentile bootstrap interval over textures.

    values: (T,) one number per texture (for a paired comparison: the difference of two models' errors on
    the same textures). Returns {"mean", "lo", "hi"}."""
    values = np.asarray(values, float)
    if values.ndim != 1 or not np.all(np.isfinite(values)):
        raise ValueError(f"values must be a finite 1-D array, one per texture, got shape {values.shape}")
    if not 0 < level < 1:
        raise ValueError(f"level must lie in (0, 1), got {level}")
    lo, hi = _interval(values[resample_indices(values.size, n_boot, seed)].mean(axis=1), level)
    return {"mean": float(values.mean()), "lo": float(lo), "hi": float(hi)}
