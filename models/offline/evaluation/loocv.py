"""Leave-one-texture-out cross-validation. Every (seed, fold) pair is an independent job, run serially,
in local worker processes (default; models.offline.jobs) or as Ray tasks on a local Ray instance or a cluster.
With `leave_out="family"` each fold also keeps the held-out texture's family out of training
(models.offline.evaluation.families).

Ray: `backend="ray"` connects to the cluster at `ray_address` (or the RAY_ADDRESS environment
variable) and starts a local instance when neither is set. On a cluster the models/ and
texture_library/ packages travel with the job (Ray `py_modules`); the nodes need the same Python
packages (`pip install 'hapticlink[train]' ray`). The data goes once into the object store.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, replace
from functools import partial

import numpy as np
from tqdm import tqdm

from models.offline.evaluation.data import TextureData
from models.offline.evaluation.estimator_registry import EstimatorSpec
from models.offline.evaluation.families import family_of, left_out_with
from models.offline.jobs import capped_threads, cpu_count, run_jobs
from texture_library.attributes import RATING_MAX, RATING_MIN

BACKENDS = ("process", "serial", "ray")


@dataclass(frozen=True)
class LoocvRun:
    """predictions: (T, 4) bipolar, each from a model that never saw that texture."""

    predictions: np.ndarray
    fold_seconds: list[float]
    fold_info: list[dict]
    n_params: int
    wall_s: float
    seed: int


def check_test_views(views: int, stored: int | None) -> None:
    """ValueError unless a held-out texture can be seen through its first `views` of `stored` image views (None:
    the data has no visual features). The CLI asks before computing features, seen_through when it applies them."""
    if stored is None:
        raise ValueError("test views need visual features, but the data has none")
    if views < 1 or stored % views:
        raise ValueError(f"test views must divide the {stored} stored views, got {views}")


def seen_through(data: TextureData, views: int) -> TextureData:
    """The textures as a camera that gave only their first `views` views would show them: those views
    tiled over the stored slots, so any model pools exactly them (views must divide the stored count)."""
    stored = None if data.visual is None else data.visual.shape[1]
    check_test_views(views, stored)
    return replace(data, visual=np.tile(data.visual[:, :views], (1, stored // views, 1)))


def run_fold(
    data: TextureData,
    spec: EstimatorSpec,
    held_out: int,
    seed: int,
    test_views: int | None = None,
    also_out: tuple[int, ...] = (),
) -> tuple[np.ndarray, float, dict, int]:
    """Fit on every texture but `held_out` (and `also_out`: its family, say), predict `held_out`:
    (prediction (4,), seconds, fit info, params).

    test_views: the held-out texture is seen through only its first test_views image views (a service
    that pooled that many frames); the model is still fit as usual."""
    t0 = time.perf_counter()
    out = {held_out, *also_out}
    train = data.take([i for i in range(len(data)) if i not in out])
    est = spec.build().fit(train, seed)
    held = data.take([held_out]).with_targets(None)
    if test_views is not None:
        held = seen_through(held, test_views)
    # The held-out texture reaches predict without its ratings: nothing to leak, by construction.
    pred = est.predict(held)[0]
    pred = np.clip(pred, RATING_MIN, RATING_MAX)  # as every exported model clips its output
    return pred, time.perf_counter() - t0, est.fit_info(), est.n_params()


def _fold_job(data: TextureData, job: tuple[EstimatorSpec, int, int, int | None, tuple[int, ...]]):
    return run_fold(data, *job)


def _fold_in_ray_task(
    data: TextureData,
    spec: EstimatorSpec,
    held_out: int,
    seed: int,
    test_views: int | None,
    also_out: tuple[int, ...],
    threads: int,
):
    with capped_threads(threads):
        return run_fold(data, spec, held_out, seed, test_views, also_out)


def loocv(
    data: TextureData,
    spec: EstimatorSpec,
    *,
    seed: int = 0,
    workers: int | None = None,
    backend: str = "process",
    progress: bool = True,
    ray_address: str | None = None,
    test_views: int | None = None,
    leave_out: str = "texture",
) -> LoocvRun:
    """Run all len(data) folds of one seed. workers=None: one per core."""
    return loocv_seeds(
        data,
        spec,
        (seed,),
        workers=workers,
        backend=backend,
        progress=progress,
        ray_address=ray_address,
        test_views=test_views,
        leave_out=leave_out,
    )[0]


def loocv_seeds(
    data: TextureData,
    spec: EstimatorSpec,
    seeds: tuple[int, ...],
    *,
    workers: int | None = None,
    backend: str = "process",
    progress: bool = True,
    ray_address: str | None = None,
    test_views: int | None = None,
    leave_out: str = "texture",
) -> list[LoocvRun]:
    """All folds of all seeds as one batch of independent jobs; one LoocvRun per seed, in `seeds` order.

    workers: parallel jobs (process: worker processes; ray: CPUs of a local instance; None: one per core);
    test_views: see run_fold; leave_out: "texture", or "family" (each fold keeps the held-out texture's
    family out of training too)."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if data.targets is None or len(data) < 3:
        raise ValueError("leave-one-texture-out needs at least 3 rated textures")
    if not data.has_tactile and spec.build().modality in ("tactile", "both"):
        raise ValueError(
            f"model {spec.name!r} needs touch (tactile recordings), but {data.meta.get('dataset', 'the dataset')!r} "
            "is image-only; see registry.for_dataset for the image-only variants"
        )
    if not seeds:
        raise ValueError("give at least one seed")
    if test_views is not None:
        seen_through(data.take([0]), test_views)  # refuse a bad value before any job starts
    also_out = left_out_with(data.textures, leave_out)
    crowded = next((i for i, o in enumerate(also_out) if len(data) - 1 - len(o) < 2), None)
    if crowded is not None:
        raise ValueError(
            f"leaving family {family_of(data.textures[crowded])!r} ({len(also_out[crowded]) + 1} of the {len(data)} "
            "textures) out leaves fewer than 2 to train on: these texture names form no families to leave out"
        )
    n = len(data)
    jobs = [(spec, i, s, test_views, also_out[i]) for s in seeds for i in range(n)]
    workers = max(1, min(workers or cpu_count(), len(jobs)))
    threads = max(1, cpu_count() // workers)  # the serial backend too: it shares the machine alike
    desc = f"LOOCV {spec.name} seeds {list(seeds)}" + (", families left out" if leave_out == "family" else "")
    t0 = time.perf_counter()
    if backend == "ray":
        with tqdm(total=len(jobs), desc=desc, unit="fold", disable=not progress) as bar:
            results = _ray_folds(data, jobs, bar, workers, ray_address)
    else:
        in_processes = 1 if backend == "serial" else workers
        folds = run_jobs(
            partial(_fold_job, data), jobs, in_processes, desc, unit="fold", threads=threads, progress=progress
        )
        results = list(folds)
    wall = time.perf_counter() - t0
    runs = []
    for k, s in enumerate(seeds):
        part = results[k * n : (k + 1) * n]
        runs.append(
            LoocvRun(
                predictions=np.array([r[0] for r in part]),
                fold_seconds=[r[1] for r in part],
                fold_info=[r[2] for r in part],
                n_params=int(np.median([r[3] for r in part])),
                wall_s=wall / len(seeds),  # the seeds ran together; each gets its share of the wall time
                seed=s,
            )
        )
    return runs


def ray_init(address: str | None = None, num_cpus: int | None = None) -> None:
    """Connect to Ray: `address`, else RAY_ADDRESS, else start a local instance with `num_cpus` CPUs.

    Raises ValueError (with the reason) when Ray is missing or cannot start."""
    try:
        import ray
    except ImportError:
        raise ValueError("backend 'ray' needs Ray: pip install 'ray>=2.9'") from None
    if ray.is_initialized():
        return
    address = address or os.environ.get("RAY_ADDRESS") or None
    try:
        if address:
            import models
            import texture_library

            ray.init(
                address=address,
                log_to_driver=False,
                runtime_env={
                    "py_modules": [os.path.dirname(models.__file__), os.path.dirname(texture_library.__file__)]
                },
            )
        else:
            ray.init(num_cpus=num_cpus, include_dashboard=False, log_to_driver=False)
    except Exception as exc:  # noqa: BLE001 - Ray raises many types when it cannot start or connect
        raise ValueError(f"Ray could not start or connect ({address or 'local instance'}): {exc}") from None


def _ray_folds(data: TextureData, jobs: list, bar, workers: int, address: str | None) -> list:
    """The same jobs as Ray tasks (one CPU and one BLAS thread each), results in job order."""
    import ray

    ray_init(address, num_cpus=workers)
    data_ref = ray.put(data)
    remote_fold = ray.remote(num_cpus=1)(_fold_in_ray_task)
    pending = {remote_fold.remote(data_ref, *job, 1): i for i, job in enumerate(jobs)}  # 1 BLAS thread
    results: list = [None] * len(jobs)
    while pending:
        done, _ = ray.wait(list(pending), num_returns=1)
        for ref in done:
            results[pending.pop(ref)] = ray.get(ref)
            bar.update()
    return results
