"""Stability from study runs: robustness curves, breaking points, and the spread over seeds and folds.

MAE is the texture-level LOOCV MAE (0–100 scale) over the textures a variant leaves at least one
window for; a model's curve averages its seeds' predictions (the spread over seeds is reported
beside it). The breaking point of a fault is the strength at which the curve reaches
predict-the-mean's MAE, linearly interpolated between the studied strengths (in the order mild →
severe, starting at the clean value); "not reached" when it stays below at the most severe.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from models.offline.evaluation.bootstrap import bootstrap_mean, per_texture_error
from models.offline.evaluation.metrics import group_errors
from models.offline.faults.catalog import FAULTS
from models.offline.tradeoffs.faulted import CLEAN, variant
from models.offline.tradeoffs.study import StudyRun


def variant_texture_preds(run: StudyRun, key: str, source: str = "loocv") -> tuple[np.ndarray, np.ndarray]:
    """((T, 4) predictions with NaN rows where the variant left no window, (T,) bool: present)."""
    preds = getattr(run, source)[key]
    present = np.array([p is not None for p in preds])
    out = np.full((len(preds), 4), np.nan)
    for i, p in enumerate(preds):
        if p is not None:
            out[i] = p.texture
    return out, present


def seed_mean(runs: list[StudyRun], key: str, source: str = "loocv") -> tuple[np.ndarray, np.ndarray]:
    arrays = [variant_texture_preds(r, key, source) for r in runs if key in getattr(r, source)]
    if not arrays:
        raise ValueError(f"no run has variant {key!r} in {source}")
    present = np.logical_and.reduce([a[1] for a in arrays])
    return np.mean([a[0] for a in arrays], axis=0), present


def variant_mae(runs: list[StudyRun], truth: np.ndarray, key: str, source: str = "loocv") -> dict:
    """MAE of the seed-averaged predictions with bootstrap interval, per-seed MAEs, textures covered."""
    pred, present = seed_mean(runs, key, source)
    err = per_texture_error(pred[present], truth[present])
    per_seed = []
    for r in runs:
        if key in getattr(r, source):
            p, ok = variant_texture_preds(r, key, source)
            per_seed.append(float(per_texture_error(p[ok], truth[ok]).mean()))
    return {
        "mae": float(err.mean()),
        "ci": bootstrap_mean(err),
        "per_seed": per_seed,
        "seed_std": float(np.std(per_seed)) if len(per_seed) > 1 else None,
        "n_textures": int(present.sum()),
    }


def fault_curve(runs: list[StudyRun], truth: np.ndarray, fault: str, source: str = "loocv") -> list[dict]:
    """[{strength, mae, …}] from the clean segment through every studied strength (mild → severe)."""
    f = FAULTS[fault]
    points = [{"strength": f.clean, **variant_mae(runs, truth, CLEAN, source)}]
    for s in f.strengths:
        key = variant(fault, s)
        if key in getattr(runs[0], source):
            points.append({"strength": s, **variant_mae(runs, truth, key, source)})
    return points


def breaking_point(curve: list[dict], reference: float) -> float | None:
    """Strength where the MAE first reaches `reference` (linear between points; None: never)."""
    for lo, hi in zip(curve, curve[1:]):
        if hi["mae"] >= reference:
            if lo["mae"] >= reference:
                return lo["strength"]
            a, b = lo["strength"], hi["strength"]
            if math.isinf(a):  # from clean (SNR ∞) to the first SNR: the first SNR is as close as it gets
                return b
            t = (reference - lo["mae"]) / (hi["mae"] - lo["mae"])
            return float(a + t * (b - a))
    return None


def restrict(run: StudyRun, held_out: list[int] | None) -> StudyRun:
    """`run` with its LOOCV predictions outside `held_out` set to None (None: unchanged), so a model run on
    a subset of folds is compared with a reference on the same textures."""
    if held_out is None:
        return run
    keep = set(held_out)
    loocv = {k: [p if i in keep else None for i, p in enumerate(v)] for k, v in run.loocv.items()}
    return replace(run, loocv=loocv, held_out=sorted(keep))


def spread(runs: list[StudyRun], truth: np.ndarray, groups: list[str]) -> dict:
    """How stable a model is, as numbers: clean LOOCV MAE per seed and its std; per-texture (fold)
    errors' std, inter-quartile range and worst; per material group MAE (over the folds the runs ran)."""
    pred, present = seed_mean(runs, CLEAN)
    per_seed = [per_texture_error(variant_texture_preds(r, CLEAN)[0][present], truth[present]) for r in runs]
    err = per_texture_error(pred[present], truth[present])
    seed_mae = [float(e.mean()) for e in per_seed]
    return {
        "seeds": [r.seed for r in runs],
        "mae_per_seed": seed_mae,
        "seed_std": float(np.std(seed_mae)) if len(seed_mae) > 1 else None,
        # how much one texture's error moves between seeds (mean over textures of the per-texture std)
        "texture_seed_std": float(np.mean(np.std(per_seed, axis=0))) if len(per_seed) > 1 else None,
        "fold_std": float(err.std()),
        "fold_iqr": [float(np.quantile(err, 0.25)), float(np.quantile(err, 0.75))],
        "fold_worst": float(err.max()),
        "group_mae": {
            g: v["mean"]
            for g, v in group_errors(pred[present], truth[present], [g for g, ok in zip(groups, present) if ok]).items()
        },
        "n_textures": int(present.sum()),
    }


def shift_mae(runs: list[StudyRun], truth: np.ndarray, groups: list[str]) -> dict | None:
    """Leave-one-material-group-out MAE (seed-averaged) and the clean LOOCV MAE on the same textures."""
    runs = [r for r in runs if r.shift]
    if not runs:
        return None
    pred = np.mean([np.stack([r.shift[i].texture for i in range(len(truth))]) for r in runs], axis=0)
    err = per_texture_error(pred, truth)
    per_group = {g: v["mean"] for g, v in group_errors(pred, truth, groups).items()}
    return {
        "mae": float(err.mean()),
        "ci": bootstrap_mean(err),
        "per_group": per_group,
        "seeds": [r.seed for r in runs],
    }
