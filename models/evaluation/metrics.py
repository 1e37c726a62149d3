"""Errors on the 0–100 report scale (bipolar error × 0.5) and the human noise ceiling."""

from __future__ import annotations

import numpy as np

from texture_library.attributes import ATTRIBUTES, REPORT_SCALE


def error_table(pred: np.ndarray, truth: np.ndarray) -> dict[str, dict[str, float]]:
    """MAE and RMSE per attribute and their mean, on the 0–100 scale.

    pred, truth: (T, 4) bipolar. Returns {"mae": {attr: v, …, "mean": v}, "rmse": {…}}.
    """
    pred = np.asarray(pred, float)
    truth = np.asarray(truth, float)
    if pred.shape != truth.shape or pred.ndim != 2 or pred.shape[1] != len(ATTRIBUTES):
        raise ValueError(f"pred and truth must both be (T, {len(ATTRIBUTES)}), got {pred.shape} and {truth.shape}")
    err = (pred - truth) * REPORT_SCALE
    mae = np.mean(np.abs(err), axis=0)
    rmse = np.sqrt(np.mean(err**2, axis=0))
    return {
        "mae": {**dict(zip(ATTRIBUTES, mae.tolist())), "mean": float(mae.mean())},
        "rmse": {**dict(zip(ATTRIBUTES, rmse.tolist())), "mean": float(rmse.mean())},
    }


def split_half_ceiling(table: np.ndarray, n_splits: int = 200, seed: int = 0) -> dict[str, dict[str, float]]:
    """Human noise ceiling: how far two random halves of the raters disagree.

    table: (T, R, 4) bipolar ratings with NaN where a rater did not rate.
    For each split the raters are halved at random and the two half-means
    compared per texture; MAE/RMSE (0–100 scale) are averaged over splits.
    """
    table = np.asarray(table, float)
    if table.ndim != 3 or table.shape[1] < 2:
        raise ValueError(f"table must be (textures, raters ≥ 2, 4), got {table.shape}")
    rng = np.random.default_rng(seed)
    maes, rmses = [], []
    for _ in range(n_splits):
        perm = rng.permutation(table.shape[1])
        half = table.shape[1] // 2
        with np.errstate(all="ignore"):
            a = np.nanmean(table[:, perm[:half]], axis=1)
            b = np.nanmean(table[:, perm[half:]], axis=1)
        ok = np.all(np.isfinite(a) & np.isfinite(b), axis=1)
        e = error_table(a[ok], b[ok])
        maes.append([e["mae"][k] for k in ATTRIBUTES])
        rmses.append([e["rmse"][k] for k in ATTRIBUTES])
    mae, rmse = np.mean(maes, axis=0), np.mean(rmses, axis=0)
    return {
        "mae": {**dict(zip(ATTRIBUTES, mae.tolist())), "mean": float(mae.mean())},
        "rmse": {**dict(zip(ATTRIBUTES, rmse.tolist())), "mean": float(rmse.mean())},
    }


def group_errors(pred: np.ndarray, truth: np.ndarray, groups: list[str]) -> dict[str, dict[str, float]]:
    """MAE per material group and attribute (0–100 scale): {group: {attr: mae, "mean": …, "n": count}}."""
    out = {}
    groups_arr = np.asarray(groups)
    for g in sorted(set(groups)):
        sel = groups_arr == g
        e = error_table(pred[sel], truth[sel])["mae"]
        out[g] = {**e, "n": int(sel.sum())}
    return out


def bootstrap_mae_samples(pred: np.ndarray, truth: np.ndarray, *, n_boot: int = 2000, seed: int = 0) -> np.ndarray:
    """Texture-level bootstrap of the MAE (0–100 scale): (n_boot, 5) — per attribute, then their mean.

    Each row resamples the T textures with replacement. The resamples depend only on (T, n_boot,
    seed), so two predictions of the same textures bootstrapped with the same seed are *paired*:
    differences and ratios of their rows give paired intervals.
    """
    pred = np.asarray(pred, float)
    truth = np.asarray(truth, float)
    if pred.shape != truth.shape or pred.ndim != 2 or pred.shape[1] != len(ATTRIBUTES) or pred.shape[0] < 2:
        raise ValueError(f"pred and truth must both be (T ≥ 2, {len(ATTRIBUTES)}), got {pred.shape} and {truth.shape}")
    if n_boot < 100:
        raise ValueError(f"n_boot must be ≥ 100 for a 95 % interval, got {n_boot}")
    err = np.abs(pred - truth) * REPORT_SCALE
    idx = np.random.default_rng(seed).integers(0, err.shape[0], size=(n_boot, err.shape[0]))
    mae = err[idx].mean(axis=1)  # (n_boot, 4)
    return np.concatenate([mae, mae.mean(axis=1, keepdims=True)], axis=1)


def percentile_interval(samples: np.ndarray, level: float = 0.95) -> np.ndarray:
    """(2, k) lower and upper percentile bounds of bootstrap samples (n_boot, k)."""
    if not 0 < level < 1:
        raise ValueError(f"level must lie in (0, 1), got {level}")
    tail = 100 * (1 - level) / 2
    return np.percentile(np.asarray(samples, float), [tail, 100 - tail], axis=0)
