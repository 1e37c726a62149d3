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
