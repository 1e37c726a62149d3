"""ThreadCpu counts the service's own threads, not whatever else shares its process."""

from __future__ import annotations

import os
import sys
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


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread nice values are Linux's")
def test_lower_priority_lowers_only_the_calling_thread():
    from service.thread_cpu import lower_priority

    main_before = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    seen: dict[str, int] = {}

    def background() -> None:
        tid = threading.get_native_id()
        before = os.getpriority(os.PRIO_PROCESS, tid)
        seen["ok"] = lower_priority(5)
        seen["raised_by"] = os.getpriority(os.PRIO_PROCESS, tid) - before
        seen["capped"] = lower_priority(40) and os.getpriority(os.PRIO_PROCESS, tid)

    t = threading.Thread(target=background)
    t.start()
    t.join()
    assert seen == {"ok": True, "raised_by": min(5, 19 - main_before), "capped": 19}
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == main_before
    assert lower_priority(0)
    with pytest.raises(ValueError, match="niceness"):
        lower_priority(-1)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread nice values are Linux's")
def test_the_services_decoding_and_embedding_threads_run_behind_its_window_threads():
    """A burst of frames to decode and embed takes the CPU the tactile path leaves (HAPTICLINK_VISUAL_NICE)."""
    from service.settings import Settings
    from service.state import ServiceState

    def nice() -> int:
        return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    state = ServiceState(Settings(visual_nice=7))
    try:
        base = nice()
        assert state.window_pool.submit(nice).result() == base
        assert state.visual_pool.submit(nice).result() == min(19, base + 7)
        assert state.frame_pool.submit(nice).result() == min(19, base + 7)
    finally:
        for pool in (state.window_pool, state.frame_pool, state.visual_pool):
            pool.shutdown()
