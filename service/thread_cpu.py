"""The CPU time of the service's own Python threads: its event loop and its pools, not whatever else shares the
process (a test's client, an embedding application) nor the native threads of a library that never hold the GIL.

The pools' threads register themselves (`ThreadCpu.register`, a ThreadPoolExecutor initializer); `seconds()`, called
on the event-loop thread, adds that thread's own CPU clock to theirs. Where a thread's CPU clock cannot be read
(`time.pthread_getcpuclockid` is missing: not Linux or BSD), `seconds()` is the whole process's CPU time instead.
"""

from __future__ import annotations

import contextlib
import threading
import time


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
