"""benchmarks.frame_post: the service's CPU per request, read per thread from /proc."""

from __future__ import annotations

import os
import sys
import threading
import time

import pytest

from benchmarks.frame_post import split_cpu, thread_cpu_seconds


def test_split_cpu_puts_the_loop_apart_from_every_other_thread():
    before = {10: 1.0, 11: 2.0, 13: 4.0}  # 13 ended meanwhile: it adds nothing
    after = {10: 1.5, 11: 2.25, 12: 0.5}  # 12 started meanwhile: all its CPU counts
    assert split_cpu(10, before, after) == (0.5, 0.75)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread CPU is read from /proc")
def test_thread_cpu_seconds_sees_a_busy_thread_and_the_main_one():
    pid = os.getpid()
    seen: dict[str, int] = {}
    busy, stop = threading.Event(), threading.Event()

    def spin() -> None:
        seen["tid"] = threading.get_native_id()
        start = time.thread_time()
        while not stop.is_set():
            if time.thread_time() - start >= 0.15:
                busy.set()

    before = thread_cpu_seconds(pid)
    worker = threading.Thread(target=spin)
    worker.start()
    try:
        assert busy.wait(timeout=30)
        during = thread_cpu_seconds(pid)
    finally:
        stop.set()
        worker.join()
    assert pid in before and pid in during
    assert during[seen["tid"]] >= 0.1  # the kernel counts in clock ticks (10 ms)
    loop, rest = split_cpu(pid, before, during)
    assert rest >= 0.1 and loop >= 0
