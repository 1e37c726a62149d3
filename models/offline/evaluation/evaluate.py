"""`hapticlink evaluate`: LOOCV of one model over seeds → results.json (the report draws the figures)."""

from __future__ import annotations

import json
import os
import platform
import shlex
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from models.offline.evaluation.data import TextureData
from models.offline.evaluation.estimator_registry import EstimatorSpec
from models.offline.evaluation.loocv import LoocvRun, loocv_seeds
from models.offline.evaluation.metrics import error_table, group_errors
from models.offline.host import host
from models.offline.provenance import Input, provenance
from texture_library.attributes import ATTRIBUTES


def hardware() -> dict:
    info = {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
        "processor": platform.processor() or platform.machine(),
        "host": host(),  # the CPU model and ISA flags: per-window latencies are absolute times on this host
    }
    try:
        import torch

        info["torch"] = torch.__version__
        info["torch_threads"] = torch.get_num_threads()
    except ImportError:
        pass
    return info


def window_latency(data: TextureData, spec: EstimatorSpec, seed: int = 0, n: int = 200) -> dict:
    """Per-window inference cost of the model fit on all textures: onnxruntime (CPU, 1 thread, batch 1)
    for models that export to ONNX; otherwise the estimator's own predict on one window (numpy/sklearn)."""
    import tempfile

    from models.offline.nets.latency import call_latency, onnx_latency

    est = spec.build().fit(data, seed)
    why = "no ONNX export"
    if hasattr(est, "export"):
        with tempfile.TemporaryDirectory() as tmp:
            try:
                path = est.export(Path(tmp) / "model.onnx", {})
            except ValueError as exc:  # e.g. a model on visual descriptor blocks: its graph is not written yet
                why = f"no ONNX export: {exc}"
            else:
                return {**onnx_latency(path, n=n, threads=1), "runtime": "onnxruntime", "threads": 1, "batch": 1}
    one = data.take([0])
    one = replace(one, tactile=[one.tactile[0][:1]])
    timing = call_latency(lambda: est.predict(one), n=min(n, 50), warmup=5)
    return {**timing, "runtime": f"python ({why})", "threads": 1, "batch": 1}


def summarize_runs(data: TextureData, runs: list[LoocvRun]) -> dict:
    """Seed-averaged metrics (mean ± std over seeds) and the predictions, per seed and seed-averaged.

    Holds no per-texture ratings: results.json files are committed, and the licensed ratings must not
    be (the report reads them from the dataset when it needs them)."""
    per_seed = []
    for run in runs:
        e = error_table(run.predictions, data.targets)
        per_seed.append(
            {
                "seed": run.seed,
                "mae": e["mae"],
                "rmse": e["rmse"],
                "wall_s": run.wall_s,
                "fold_seconds_median": float(np.median(run.fold_seconds)),
            }
        )
    keys = list(ATTRIBUTES) + ["mean"]

    def agg(metric: str, fn) -> dict:
        return {k: float(fn([s[metric][k] for s in per_seed])) for k in keys}

    mean_pred = np.mean([r.predictions for r in runs], axis=0)
    return {
        "mae": agg("mae", np.mean),
        "rmse": agg("rmse", np.mean),
        "mae_std": agg("mae", np.std),
        "rmse_std": agg("rmse", np.std),
        "per_seed": per_seed,
        "ensemble_of_seeds": error_table(mean_pred, data.targets),
        "predictions": {t: dict(zip(ATTRIBUTES, map(float, p))) for t, p in zip(data.textures, mean_pred)},
        "predictions_per_seed": {
            str(r.seed): {t: [round(float(v), 4) for v in p] for t, p in zip(data.textures, r.predictions)}
            for r in runs
        },
        "group_mae": group_errors(mean_pred, data.targets, data.groups),
        # synthetic world: how well the documented physics → rating mapping is recovered
        "vs_true_mapping": error_table(mean_pred, data.meta["true_ratings"]) if "true_ratings" in data.meta else None,
        "fold_info": [r.fold_info for r in runs],
    }


def evaluate(
    data: TextureData,
    spec: EstimatorSpec,
    out: str | Path,
    *,
    seeds: tuple[int, ...] = (0, 1, 2),
    workers: int | None = None,
    backend: str = "process",
    progress: bool = True,
    latency: bool = True,
    ray_address: str | None = None,
    test_views: int | None = None,
    leave_out: str = "texture",
    inputs: Sequence[Input] = (),
) -> dict:
    """LOOCV for every seed (all folds of all seeds as one batch of jobs); writes out/results.json
    and returns the results dict. leave_out "family": each fold keeps the held-out texture's family out of
    training too (models.offline.evaluation.families). inputs: the files `data` was read from
    (`models.offline.provenance.dataset_inputs`), recorded with their digests under `provenance`."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    runs = loocv_seeds(
        data,
        spec,
        tuple(seeds),
        workers=workers,
        backend=backend,
        progress=progress,
        ray_address=ray_address,
        test_views=test_views,
        leave_out=leave_out,
    )
    command = "hapticlink " + " ".join(shlex.quote(a) for a in sys.argv[1:]) if "evaluate" in sys.argv else None
    results = {
        "dataset": data.meta.get("dataset"),
        "model": spec.name,
        "options": spec.options,
        "modality": spec.build().modality,
        "n_textures": len(data),
        "seeds": list(seeds),
        # image views pooled into each texture's visual input (None: the model reads no images)
        "views": spec.build().pooled_views(data.visual.shape[1]) if data.visual is not None else None,
        # the held-out texture seen through only this many views (a service that pooled that many frames)
        "test_views": test_views,
        # what each fold keeps out of training besides the held-out texture: nothing, or its family
        "leave_out": leave_out,
        "backend": backend,
        "scale": "0-100 (bipolar error / 2)",
        **summarize_runs(data, runs),
        "n_params": runs[0].n_params,
        # an image-only dataset has no windows: per-frame visual cost is measured by benchmarks/visual.py
        "latency_us": window_latency(data, spec) if latency and data.has_tactile else None,
        "wall_s": time.perf_counter() - t0,
        "hardware": hardware(),
        "features": {
            **{k: v for k, v in data.meta.items() if k not in ("tactile_config", "true_ratings")},
            "tactile_features": data.meta["tactile_config"]["feature_set"] if data.has_tactile else None,
            "extra_groups": list(data.meta.get("tactile_config", {}).get("extra_groups", [])),
        },
        "command": command,
        "provenance": provenance(inputs, command),
    }
    (out / "results.json").write_text(json.dumps(results, indent=1))
    return results
