"""The same leave-one-texture-out evaluation on each backend: serial, worker processes, Ray (local instance).

Run from the repository root:
    python -m benchmarks.loocv [--dataset data/hatt-texnet] [--model ksvr-pooled] [--seeds 0 1] [--workers N]

Every backend runs the same (seed, fold) jobs of one model and must give the same predictions
(checked); wall times are measured in one run, so their ratios hold on a busy machine even when
the absolute times do not. Ray's start-up (a local instance) and the worker processes' start (a small LOOCV
that starts them and loads the stack) are timed apart from the evaluation.
Without a dataset directory it uses a synthetic texture set (no ../shared needed). Writes
reports/bench/loocv.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.report_file import write_report
from models.offline.evaluation.data import TextureData
from models.offline.evaluation.estimator_registry import EstimatorSpec
from models.offline.evaluation.loocv import loocv_seeds, ray_init
from models.offline.provenance import dataset_inputs

DEFAULT_OUT = Path("reports/bench/loocv.json")


def synthetic_data(n_textures: int = 40, n_windows: int = 40, seed: int = 0) -> TextureData:
    """Textures whose ratings follow hidden factors seen by a stand-in camera (8 views) and by touch."""
    rng = np.random.default_rng(seed)
    factors = rng.normal(size=(n_textures, 4))
    visual = (factors @ rng.normal(size=(4, 256)))[:, None, :] + 0.2 * rng.normal(size=(n_textures, 8, 256))
    mix = rng.normal(size=(4, 526))
    tactile = [(factors[i] @ mix + rng.normal(size=(n_windows, 526))).astype(np.float32) for i in range(n_textures)]
    targets = np.clip(40 * factors + 3 * rng.normal(size=factors.shape), -100, 100)
    return TextureData(
        [f"t{i:03d}" for i in range(n_textures)],
        ["g"] * n_textures,
        tactile,
        visual.astype(np.float32),
        targets.astype(np.float32),
        {"dataset": "synthetic-benchmark"},
    )


def run(data: TextureData, model: str, seeds: tuple[int, ...], workers: int) -> dict:
    spec = EstimatorSpec(model)
    timings, predictions = {}, {}
    for backend in ("serial", "process", "ray"):
        if backend == "ray":
            t0 = time.perf_counter()
            ray_init(None, num_cpus=workers)
            timings["ray_start_s"] = round(time.perf_counter() - t0, 2)
        if backend == "process":  # the workers' start and imports, paid once per process (as Ray's start)
            t0 = time.perf_counter()
            few = data.take(list(range(max(3, workers))))
            loocv_seeds(few, spec, seeds[:1], workers=workers, backend="process", progress=False)
            timings["process_start_s"] = round(time.perf_counter() - t0, 2)
        t0 = time.perf_counter()
        runs = loocv_seeds(
            data, spec, seeds, workers=1 if backend == "serial" else workers, backend=backend, progress=True
        )
        timings[f"{backend}_s"] = round(time.perf_counter() - t0, 2)
        predictions[backend] = np.stack([r.predictions for r in runs])
        print(f"{backend:8s} {timings[f'{backend}_s']:8.1f} s", flush=True)
    diff = max(float(np.abs(predictions[b] - predictions["serial"]).max()) for b in ("process", "ray"))
    if diff > 1e-6:
        raise AssertionError(f"backends disagree by {diff} rating points")
    jobs = len(seeds) * len(data)
    return {
        "model": model,
        "dataset": data.meta.get("dataset"),
        "n_textures": len(data),
        "seeds": list(seeds),
        "jobs": jobs,
        "workers": workers,
        "wall_s": timings,
        "speedup_over_serial": {b: round(timings["serial_s"] / timings[f"{b}_s"], 2) for b in ("process", "ray")},
        "speedup_ray_with_start": round(timings["serial_s"] / (timings["ray_s"] + timings["ray_start_s"]), 2),
        "speedup_process_with_start": round(
            timings["serial_s"] / (timings["process_s"] + timings["process_start_s"]), 2
        ),
        "max_abs_diff_between_backends": diff,
        "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(), "loadavg_at_end": os.getloadavg()},
        "command": "python -m benchmarks.loocv " + " ".join(sys.argv[1:]),
    }


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.loocv", description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", help="dataset directory (default: a synthetic texture set)")
    parser.add_argument("--model", default="ksvr-pooled")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--out", default=str(DEFAULT_OUT))
    args = parser.parse_args(argv)
    if args.dataset:
        from models.offline.evaluation.data import load_texture_data

        data = load_texture_data(args.dataset)
    else:
        data = synthetic_data()
    result = run(data, args.model, tuple(args.seeds), args.workers)
    print(json.dumps({k: result[k] for k in ("wall_s", "speedup_over_serial", "speedup_ray_with_start")}, indent=1))
    out = Path(args.out)
    write_report(out, result, dataset_inputs(args.dataset) if args.dataset else ())
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
