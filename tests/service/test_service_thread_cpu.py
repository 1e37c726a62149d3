"""ThreadCpu counts the service's own threads, not whatever else shares its process."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from service.thread_cpu import ThreadCpu


def _spin(seconds: float) -> None:
    """Burn CPU on the calling thread for `seconds` of its own CPU time."""
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        pass


@pytest.mark.skipif(not hasattr(time, "pthread_getcpuclockid"), reason="no per-thread CPU clocks on this platform")
def test_a_registered_pool_threads_cpu_counts_and_another_threads_does_not():
    clock = ThreadCpu()
    with ThreadPoolExecutor(1, initializer=clock.register) as pool:
        pool.submit(lambda: None).result()  # the pool's thread exists and is registered
        before = clock.seconds()
        stranger = threading.Thread(target=_spin, args=(0.3,))  # e.g. a test's client in the same process
        stranger.start()
        stranger.join()
        pool.submit(_spin, 0.2).result()
        used = clock.seconds() - before
    # the pool's 0.2 s (and a little of this thread's), not the stranger's 0.3 s
    assert 0.2 <= used < 0.3


@pytest.mark.skipif(not hasattr(time, "pthread_getcpuclockid"), reason="no per-thread CPU clocks on this platform")
def test_a_thread_that_ended_leaves_the_sum():
    clock = ThreadCpu()
    with ThreadPoolExecutor(1, initializer=clock.register) as pool:
        pool.submit(_spin, 0.05).result()
        assert clock.seconds() >= 0.05
    time.sleep(0.05)  # the pool's thread has exited
    assert clock.seconds() - time.thread_time() < 0.01  # this thread's own time only
    assert clock._clocks == {}
