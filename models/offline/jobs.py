"""A list of independent jobs run in worker processes with a progress bar (dataset builds, feature extraction).

Its own module so that the dataset builders and the feature code can share it without importing each
other (models.offline.datasets.build dispatches to the builders, which used to import run_jobs back from it).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor

from tqdm import tqdm


def run_jobs(fn: Callable, jobs: list, workers: int | None, desc: str) -> Iterable:
    """fn over jobs, results in job order, with a progress bar; in worker processes when there is more
    than one job and worker. fn and the jobs must be picklable."""
    workers = min(workers or os.cpu_count() or 1, len(jobs))
    bar = tqdm(total=len(jobs), desc=desc, unit="texture", disable=len(jobs) < 4)
    try:
        if workers <= 1:
            for job in jobs:
                yield fn(job)
                bar.update()
        else:
            with ProcessPoolExecutor(max_workers=workers) as pool:
                for result in pool.map(fn, jobs):
                    yield result
                    bar.update()
    finally:
        bar.close()
