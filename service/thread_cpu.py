"""The CPU of the service's own Python threads: the time its event loop and its pools use, not whatever else shares
the process (a test's client, an embedding application) nor the native threads of a library that never hold the GIL;
and the share the OS gives a background pool when the cores are contended (`lower_priority`).

The pools' threads register themselves (`ThreadCpu.register`, a ThreadPoolExecutor initializer); `seconds()`, called
on the event-loop thread, adds that thread's own CPU clock to theirs, and `loop_seconds()` is that thread's alone.
Where a thread's CPU clock cannot be read (`time.pthread_getcpuclockid` is missing: not Linux or BSD), `seconds()` is
the whole process's CPU time instead.

Admission (service/capacity.py) reads a `CpuMeter`: `ThreadCpu` in a service; another one where what the CPU clocks
say must not decide (tests whose subject is not capacity run on hosts that are busy with other work).
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
import time
from typing import Protocol


class CpuMeter(Protocol):
    """What admission measures the service's CPU by; every method is called on the thread named."""

    def register(self) -> None:
        """Count the calling thread (a pool thread, as it starts) from now on."""

    def seconds(self) -> float:
        """CPU seconds the registered threads and the calling one (the event loop's) have used, s: a running sum."""
        ...

    def loop_seconds(self) -> float:
        """CPU seconds the calling thread (the event loop's) has used, s: a running sum."""
        ...


class ThreadCpu:
    def __init__(self) -> None:
        self._clocks: dict[int, int] = {}  # thread ident → its CPU clock id
        self._lock = threading.Lock()
        self.per_thread = hasattr(time, "pthread_getcpuclockid")

    def register(self) -> None:
        """Count the calling thread from now on (a pool thread, as it starts)."""
        if self.per_thread:
            ident = threading.get_ident()
            with self._lock:
                self._clocks[ident] = time.pthread_getcpuclockid(ident)

    def seconds(self) -> float:
        """CPU seconds the registered threads and the calling one have used (s); a registered thread that has ended
        leaves the sum (its time with it: callers take differences of a running sum and must clamp at 0)."""
        if not self.per_thread:
            return time.process_time()
        total = time.thread_time()
        with self._lock:
            clocks = list(self._clocks.items())
        for ident, clock in clocks:
            try:
                total += time.clock_gettime(clock)
            except OSError:  # the thread has ended
                with self._lock, contextlib.suppress(KeyError):
                    del self._clocks[ident]
        return total

    def loop_seconds(self) -> float:
        """CPU seconds the calling thread has used (s)."""
        return time.thread_time()


def lower_priority(niceness: int) -> bool:
    """Raise the calling thread's nice value by `niceness` (capped at 19), so that when the cores are contended the
    OS runs the other threads first (Linux schedules each thread on its own nice value). False where that cannot be
    done here (not Linux, or the OS refused); nothing changes then. niceness 0 changes nothing and returns True."""
    if niceness < 0:
        raise ValueError(f"niceness must be ≥ 0 (lowering a thread's priority only), got {niceness}")
    if niceness == 0:
        return True
    if not sys.platform.startswith("linux"):
        return False
    tid = threading.get_native_id()
    try:
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + niceness))
    except OSError:
        return False
    return True
