"""Leave-one-texture-out cross-validation, folds in parallel (processes by default, or Ray)."""

from __future__ import annotations

import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from models.evaluation.data import TextureData
from models.evaluation.registry import EstimatorSpec
from texture_library.attributes import RATING_MAX, RATING_MIN

BACKENDS = ("process", "serial", "ray")
_DATA: TextureData | None = None  # set once per worker process by _init_worker


@dataclass(frozen=True)
class LoocvRun:
    """predictions: (T, 4) bipolar, each from a model that never saw that texture."""

    predictions: np.ndarray
    fold_seconds: list[float]
    fold_info: list[dict]
    n_params: int
    wall_s: float
    seed: int


def _init_worker(data: TextureData, threads: int) -> None:
    global _DATA
    _DATA = data
    _set_threads(threads)


def _set_threads(threads: int) -> None:
    os.environ["OMP_NUM_THREADS"] = str(threads)
    try:
        import torch

        torch.set_num_threads(threads)
    except ImportError:
        pass


def run_fold(data: TextureData, spec: EstimatorSpec, held_out: int, seed: int) -> tuple[np.ndarray, float, dict, int]:
    """Fit on every texture but `held_out`, predict `held_out`: (prediction (4,), seconds, fit info, params)."""
    t0 = time.perf_counter()
    train = data.take([i for i in range(len(data)) if i != held_out])
    est = spec.build().fit(train, seed)
    # The held-out texture reaches predict without its ratings: nothing to leak, by construction.
    pred = est.predict(data.take([held_out]).with_targets(None))[0]
    pred = np.clip(pred, RATING_MIN, RATING_MAX)  # as every exported model clips its output
    return pred, time.perf_counter() - t0, est.fit_info(), est.n_params()


def _fold_in_worker(args: tuple[EstimatorSpec, int, int]):
    return run_fold(_DATA, *args)


def loocv(
    data: TextureData,
    spec: EstimatorSpec,
    *,
    seed: int = 0,
    workers: int | None = None,
    backend: str = "process",
    progress: bool = True,
) -> LoocvRun:
    """Run all len(data) folds. workers=None: one per core."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if data.targets is None or len(data) < 3:
        raise ValueError("leave-one-texture-out needs at least 3 rated textures")
    n = len(data)
    workers = max(1, min(workers or os.cpu_count() or 1, n))
    threads = max(1, (os.cpu_count() or 1) // workers)
    jobs = [(spec, i, seed) for i in range(n)]
    t0 = time.perf_counter()
    bar = tqdm(total=n, desc=f"LOOCV {spec.name} seed {seed}", unit="fold", disable=not progress)
    results: list = [None] * n
    if backend == "serial" or workers == 1:
        for i, job in enumerate(jobs):
            results[i] = run_fold(data, *job)
            bar.update()
    elif backend == "process":
        with ProcessPoolExecutor(max_workers=workers, initializer=_init_worker, initargs=(data, threads)) as pool:
            for i, res in enumerate(pool.map(_fold_in_worker, jobs)):
                results[i] = res
                bar.update()
    else:
        results = _ray_folds(data, jobs, bar)
    bar.close()
    return LoocvRun(
        predictions=np.array([r[0] for r in results]),
        fold_seconds=[r[1] for r in results],
        fold_info=[r[2] for r in results],
        n_params=int(np.median([r[3] for r in results])),
        wall_s=time.perf_counter() - t0,
        seed=seed,
    )


def _ray_folds(data: TextureData, jobs: list, bar) -> list:
    """The same folds as Ray tasks: spreads them over a cluster (`ray start` / RAY_ADDRESS)."""
    try:
        import ray
    except ImportError:
        raise ValueError("backend 'ray' needs Ray: pip install 'ray[default]'") from None
    if not ray.is_initialized():
        ray.init(address=os.environ.get("RAY_ADDRESS"), ignore_reinit_error=True, log_to_driver=False)
    data_ref = ray.put(data)
    remote_fold = ray.remote(num_cpus=1)(run_fold)
    pending = {remote_fold.remote(data_ref, *job): i for i, job in enumerate(jobs)}
    results: list = [None] * len(jobs)
    while pending:
        done, _ = ray.wait(list(pending), num_returns=1)
        for ref in done:
            results[pending.pop(ref)] = ray.get(ref)
            bar.update()
    return results
