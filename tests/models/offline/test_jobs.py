"""The offline wing's one parallel runner: results in job order, one thread cap, in and out of worker processes."""

import os

import pytest
from threadpoolctl import threadpool_info

from models.offline.jobs import capped_threads, run_jobs


def blas_threads(offset: int) -> tuple[int, int, str | None]:
    """(offset, the most threads any BLAS/OpenMP pool of this process may use now, OMP_NUM_THREADS)."""
    return offset, max(p["num_threads"] for p in threadpool_info()), os.environ.get("OMP_NUM_THREADS")


def test_the_cap_holds_inside_the_block_and_is_lifted_after():
    before = blas_threads(0)[1]
    with capped_threads(1):
        assert blas_threads(0)[1:] == (1, "1")
    assert blas_threads(0)[1] == before
    with pytest.raises(ValueError, match="threads must be at least 1, got 0"):
        with capped_threads(0):
            pass


@pytest.mark.parametrize("workers", [1, 2])
def test_results_come_in_job_order_each_job_under_the_cap(workers):
    results = list(run_jobs(blas_threads, list(range(7)), workers, "cap", threads=1, progress=False))
    assert [r[0] for r in results] == list(range(7))
    assert all(r[1:] == (1, "1") for r in results), results


def test_the_default_cap_shares_the_cores_among_the_workers():
    (result,) = run_jobs(blas_threads, [0], 1, "one", progress=False)
    assert result[2] == str(os.cpu_count() or 1)  # one job, one worker: every core
