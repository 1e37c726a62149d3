"""The offline wing's one parallel runner: independent jobs in worker processes (joblib), each with a cap on
the threads it may use, results in job order, with a progress bar.

Dataset builds, feature extraction, leave-one-texture-out folds and the trade-off studies all run through
`run_jobs`; the thread cap they share is `capped_threads`. Nothing is kept at module level: what every job
needs (the data, the faulted inputs) travels bound to the job function (`functools.partial`), pickled once
per batch of jobs that joblib sends to a worker.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import TypeVar

from tqdm import tqdm

J = TypeVar("J")
R = TypeVar("R")


def cpu_count() -> int:
    return os.cpu_count() or 1


@contextmanager
def capped_threads(threads: int) -> Iterator[None]:
    """BLAS/OpenMP pools and torch (when loaded) use at most `threads` threads inside the block.

    Setting OMP_NUM_THREADS is too late once numpy is loaded, hence threadpoolctl; small matrices on a
    busy machine ran up to 100× slower with oversubscribed BLAS (a 78×2062 SVD: 1.15 s against 0.04 s)."""
    if threads < 1:
        raise ValueError(f"threads must be at least 1, got {threads}")
    from threadpoolctl import threadpool_limits

    torch = sys.modules.get("torch")
    before = torch.get_num_threads() if torch is not None else None
    # torch imported inside the block reads OMP_NUM_THREADS when it starts
    env_before = os.environ.get("OMP_NUM_THREADS")
    os.environ["OMP_NUM_THREADS"] = str(threads)
    with threadpool_limits(limits=threads):
        if torch is not None:
            torch.set_num_threads(threads)
        try:
            yield
        finally:
            if torch is not None and before is not None:
                torch.set_num_threads(before)
            if env_before is None:
                os.environ.pop("OMP_NUM_THREADS", None)
            else:
                os.environ["OMP_NUM_THREADS"] = env_before


def _capped(fn: Callable[[J], R], threads: int, job: J) -> R:
    with capped_threads(threads):
        return fn(job)


def run_jobs(
    fn: Callable[[J], R],
    jobs: Sequence[J],
    workers: int | None,
    desc: str,
    *,
    unit: str = "texture",
    threads: int | None = None,
    progress: bool | None = None,
) -> Iterator[R]:
    """fn(job) for every job, results in job order; in `workers` processes (None: one per core) when there is
    more than one job and worker, else in this process.

    fn and the jobs must be picklable (bind shared inputs with functools.partial). threads: the cap on
    BLAS/OpenMP/torch threads of each job (None: the cores shared out among the workers). progress: show
    the bar (None: when there are at least 4 jobs)."""
    jobs = list(jobs)
    workers = max(1, min(workers or cpu_count(), len(jobs)))
    threads = threads or max(1, cpu_count() // workers)
    bar = tqdm(total=len(jobs), desc=desc, unit=unit, disable=len(jobs) < 4 if progress is None else not progress)
    try:
        if workers == 1:
            for job in jobs:
                result = _capped(fn, threads, job)
                bar.update()  # before handing it on: a consumer may stop at the last one (zip)
                yield result
        else:
            from joblib import Parallel, delayed, parallel_config

            # loky: fresh worker interpreters, reused by later calls (their start-up, seconds on a busy machine,
            # is paid once per process); inner_max_num_threads caps libraries they load outside capped_threads.
            # max_nbytes=None: each job gets its own writable arrays, as in this process.
            with parallel_config(backend="loky", inner_max_num_threads=threads):
                results = Parallel(n_jobs=workers, return_as="generator", max_nbytes=None)(
                    delayed(_capped)(fn, threads, job) for job in jobs
                )
                for result in results:
                    bar.update()
                    yield result
    finally:
        bar.close()
