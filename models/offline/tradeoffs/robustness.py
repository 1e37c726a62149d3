"""The robustness and intervals pipeline: faulted inputs → detector tables → per (model, seed) study runs → summaries.

Everything per texture stays in the work folder (git-ignored); the summaries written under
reports/tradeoffs/ hold aggregates only (no per-texture ratings).
"""

from __future__ import annotations

import hashlib
import json
import math
import pickle
from dataclasses import replace
from pathlib import Path

import numpy as np

from models.offline.evaluation.bootstrap import bootstrap_mean, per_texture_error
from models.offline.faults.catalog import FAULTS
from models.offline.tradeoffs import analysis
from models.offline.tradeoffs.common import load_state, tactile_data, views_for, with_visual
from models.offline.tradeoffs.coverage import (
    coverage_after_n_windows,
    coverage_rows,
    coverage_scores,
    nested_recommendation,
    recommend,
)
from models.offline.tradeoffs.detection import calibration_distances, fold_checks, shift_checks
from models.offline.tradeoffs.faulted import CLEAN, FaultedInputs, faulted_inputs
from models.offline.tradeoffs.folds import CALIBRATION_GROUPS, partition
from models.offline.tradeoffs.study import AUGMENTED_FAULTS, StudyRun, run_study
from models.visual.config import VisualConfig
from texture_library.atomic_file import write_bytes

#: recorded with every study: ridge leaves a texture's augmented copies out together when it chooses α
AUGMENTATION_LOO = "by texture"


def _finite(x: float) -> float | None:
    return None if math.isinf(x) else x


def _finite_or_none(x: float | None) -> float | None:
    return None if x is None else _finite(x)


def _pickle(path: Path, make):
    if path.is_file():
        with open(path, "rb") as fh:
            return pickle.load(fh)
    value = make()
    write_bytes(path, pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL))
    return value


def study_inputs(root: str | Path, work: Path, *, visual: bool = True, workers: int = 2):
    """(clean data with the default visual features, faulted inputs, calibration partition, detector tables)."""
    data = tactile_data(root, workers=workers)
    if visual:
        data = with_visual(data, root, VisualConfig(), n_views=views_for("ann"))
    inputs = faulted_inputs(root, data.textures, work, visual=visual, workers=workers)
    part = partition(len(data), CALIBRATION_GROUPS, seed=0)
    tag = hashlib.sha256(
        json.dumps([data.textures, data.meta.get("tactile_hash"), data.meta.get("visual_hash"), part.tolist()]).encode()
    ).hexdigest()[:12]
    tables = _pickle(
        work / f"detector-tables-{tag}.pkl",
        lambda: {
            "folds": fold_checks(data, inputs, with_visual=visual, workers=workers),
            "calibration": calibration_distances(data, inputs, part, with_visual=visual, workers=workers),
            "shift": shift_checks(data, inputs, with_visual=visual, workers=workers),
        },
    )
    return data, inputs, part, tables


def held_out_subset(n: int, size: int, seed: int = 0) -> np.ndarray:
    """A fixed, seeded subset of `size` texture indices (sorted): the folds slow models run."""
    if not 2 <= size <= n:
        raise ValueError(f"subset size must lie in 2…{n}, got {size}")
    return np.sort(np.random.default_rng(seed).choice(n, size, replace=False))


def run_model(
    data,
    inputs: FaultedInputs,
    part: np.ndarray,
    work: Path,
    model: str,
    seed: int,
    *,
    options: dict | None = None,
    calibration: bool,
    augmentation: bool,
    workers: int,
    held_out: np.ndarray | None = None,
    force: bool = False,
) -> StudyRun:
    """One (model, seed) study run, cached in work/runs/ under the data it saw (textures, feature hashes,
    faulted inputs' variants) and the folds it ran."""
    opts = options or {}
    tag = "" if not opts else "-" + hashlib.sha256(json.dumps(opts, sort_keys=True).encode()).hexdigest()[:8]
    data_tag = hashlib.sha256(
        json.dumps(
            [
                data.textures,
                data.meta.get("tactile_hash"),
                data.meta.get("visual_hash"),
                sorted(inputs.tactile),
                inputs.visual_keys,
                part.tolist(),
                None if held_out is None else [int(i) for i in held_out],
            ]
        ).encode()
    ).hexdigest()[:10]
    sub = "" if held_out is None else f"-sub{len(held_out)}"
    path = (
        work / "runs" / f"{model}{tag}-s{seed}{'-cal' if calibration else ''}{'-aug' if augmentation else ''}"
        f"{sub}-{data_tag}.pkl"
    )
    if force and path.is_file():
        path.unlink()
    needs_visual = model.removeprefix("shuffled-") not in ("mean",) and data.visual is not None
    d = data
    if needs_visual and views_for(model) != data.visual.shape[1]:
        d = replace(data, visual=data.visual[:, : views_for(model)])
    return _pickle(
        path,
        lambda: run_study(
            d,
            inputs,
            part,
            model,
            seed=seed,
            options=opts,
            calibration=calibration,
            augmentation=augmentation,
            workers=workers,
            held_out=held_out,
        ),
    )


def summarise(data, runs: dict[str, list[StudyRun]], tables: dict, part: np.ndarray) -> dict:
    """Robustness curves, breaking points, spread, shift, augmentation and coverage (aggregates only)."""
    truth = data.targets.astype(float)
    mean_runs = runs.get("mean")
    if not mean_runs:
        raise ValueError("the summary needs the 'mean' model (predict-the-mean) as the breaking-point reference")
    reference = analysis.variant_mae(mean_runs, truth, CLEAN)["mae"]
    clean_all = {}
    robustness, breaking, spread, shift, augmentation, coverage, recommended = [], [], {}, {}, [], [], {}
    nested: dict[str, dict] = {}
    by_windows: list[dict] = []
    for model, model_runs in runs.items():
        held_out = model_runs[0].held_out
        if any(r.held_out != held_out for r in model_runs):
            raise ValueError(f"the runs of {model!r} ran different folds; rerun them on the same held-out textures")
        # a model run on a subset of folds breaks where it reaches predict-the-mean on the same textures
        model_ref = (
            reference
            if held_out is None
            else analysis.variant_mae([analysis.restrict(r, held_out) for r in mean_runs], truth, CLEAN)["mae"]
        )
        full, present = analysis.seed_mean(model_runs, CLEAN)
        err = per_texture_error(full[present], truth[present])
        clean_all[model] = {
            "mae": float(err.mean()),
            "ci": bootstrap_mean(err),
            "n_textures": int(present.sum()),
            "reference_mean_mae": model_ref,
            "subset": held_out is not None,
        }
        spread[model] = analysis.spread(model_runs, truth, data.groups)
        shift[model] = analysis.shift_mae(model_runs, truth, data.groups)
        for name in FAULTS:
            if not any(k.startswith(name + "@") for k in model_runs[0].loocv):
                continue
            curve = analysis.fault_curve(model_runs, truth, name)
            for k, pt in enumerate(curve):
                # SNR ∞ (clean noise) is no JSON number: None, with "clean" saying which point is the origin
                robustness.append(
                    {
                        "model": model,
                        "fault": name,
                        "strength": None if math.isinf(pt["strength"]) else pt["strength"],
                        "clean": k == 0,
                        "mae": pt["mae"],
                        "ci": pt["ci"],
                        "seed_std": pt["seed_std"],
                        "n_textures": pt["n_textures"],
                    }
                )
            bp = analysis.breaking_point(curve, model_ref)
            breaking.append(
                {
                    "model": model,
                    "fault": name,
                    "breaking_point": None if bp is None else _finite(bp),
                    "reached": bp is not None,
                    "broken_when_clean": curve[0]["mae"] >= model_ref,
                    "reference_mean_mae": model_ref,
                    "worst_mae": max(p["mae"] for p in curve[1:]) if len(curve) > 1 else None,
                }
            )
        aug_runs = [r for r in model_runs if r.aug]
        for name in AUGMENTED_FAULTS:
            if not aug_runs or not any(k.startswith(name + "@") for k in aug_runs[0].aug):
                continue
            before = analysis.fault_curve([r for r in model_runs if r.seed in {a.seed for a in aug_runs}], truth, name)
            after = analysis.fault_curve(aug_runs, truth, name, source="aug")
            augmentation.append(
                {
                    "model": model,
                    "fault": name,
                    "seeds": [r.seed for r in aug_runs],
                    "before": [{"strength": _finite(p["strength"]), "mae": p["mae"]} for p in before],
                    "after": [{"strength": _finite(p["strength"]), "mae": p["mae"]} for p in after],
                    "breaking_before": _finite_or_none(analysis.breaking_point(before, model_ref)),
                    "breaking_after": _finite_or_none(analysis.breaking_point(after, model_ref)),
                }
            )
        for r in model_runs:
            if r.calib:
                scores = coverage_scores(
                    r, truth, part, tables["folds"], tables["calibration"], tables["shift"], data.groups
                )
                rows = coverage_rows(r, scores)
                coverage += rows
                recommended[model] = recommend(rows)
                nested[model] = nested_recommendation(r, scores)
                by_windows += coverage_after_n_windows(r, truth, part)
                break  # one seed's intervals per model
    flags = {k: float(np.mean([c.flags.mean() for c in v if len(c.flags)])) for k, v in tables["folds"].items()}
    return {
        "reference_mean_mae": reference,
        "clean": clean_all,
        "robustness": robustness,
        "breaking_points": breaking,
        "spread": spread,
        "shift": shift,
        "augmentation": augmentation,
        # how the texture-level models' α saw the augmented copies: a texture's copies left out together
        "augmentation_loo": AUGMENTATION_LOO,
        "coverage": coverage,
        "recommended_intervals": recommended,
        # the same rule run inside the folds: what its pick covers on textures it never saw
        "nested_intervals": nested,
        "coverage_after_n_windows": by_windows,
        "flag_rate": flags,
        "load": load_state(),
    }
