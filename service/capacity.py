"""Admission by what the process can serve: refuse early instead of slowing every session down.

A replica is one Python process: one event loop, one GIL, about one core. `CapacityGuard` measures,
every `SAMPLE_EVERY_S`, two things that say how close the process is to saturation:

- **loop lag**: how late the event loop runs a timer. Every request, block and acknowledgement
  waits this long before the loop gets to it; it grows without bound once the loop has more work
  than time.
- **loop CPU share**: the event-loop thread's CPU time per wall second (0…1). The loop thread is
  what saturates first: it parses every request and WebSocket frame, decodes and admits every
  block and publishes every event, under one GIL shared with the pool threads. (The process's
  total CPU would also count whatever else shares the process, e.g. a test client.)

A late timer alone may mean the machine is busy with other processes; the lag counts as the
process's own only while the process is busy too: its loop thread over half its budget, or all its
threads together over the budget (then the pool threads hold the GIL, and every socket operation of
the loop waits for it: the loop is late while using little CPU itself).

Both are smoothed (an exponential average, time constant ≈ `SMOOTHING_S`). From them:

- `admit_session(n)` refuses a new session (429 + Retry-After, the reason in the message) while
  the lag is above `session_lag_s`, the loop's CPU share is above `cpu_budget` with two or more
  sessions streaming, or (four or more streaming: enough to measure) one more session of the
  measured loop CPU per streaming session would not fit the budget. The first session is always
  admitted.
- `admit_block(session)` refuses the blocks of the newest sessions (429 / WebSocket close 4429,
  Retry-After) while the loop is over its CPU budget or its lag is above `shed_lag_s`: the
  sessions the measured CPU per session says do not fit, newest first. The oldest sessions keep streaming
  at full quality, and the refused robots back off and resend later (nothing accepted is lost).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import Callable, Iterable

from service.errors import ServiceError
from service.live_session import Session
from service.metrics import ServiceMetrics
from service.settings import Settings

log = logging.getLogger(__name__)

SAMPLE_EVERY_S = 0.05
SMOOTHING_S = 0.5
#: a session that sent nothing for this long does not count as streaming (its CPU is not in the measure)
STREAMING_WITHIN_S = 1.0
RETRY_AFTER_S = 2.0
#: at most one WARNING about shedding per this many seconds
LOG_EVERY_S = 10.0


class AtCapacity(ServiceError):
    """429: the replica is at capacity (a new session, or a block of one of its newest sessions)."""

    def __init__(self, detail: str) -> None:
        super().__init__(429, detail, {"Retry-After": f"{RETRY_AFTER_S:g}"})


class CapacityGuard:
    """See the module docstring. `start()` inside the event loop; `sessions` lists this replica's sessions in
    creation order (oldest first)."""

    def __init__(self, settings: Settings, metrics: ServiceMetrics) -> None:
        self.settings = settings
        self.metrics = metrics
        self.lag_s = 0.0
        self.cpu_share = 0.0
        self.process_share = 0.0  # cores the whole process used (all threads), smoothed
        self.cpu_per_session = 0.0  # loop CPU per streaming session (0 until measured)
        self._streaming = 0
        self._shed: set[str] = set()
        self._sessions: Callable[[], Iterable[Session]] = lambda: ()
        self._task: asyncio.Task | None = None
        self._last_log = 0.0

    def start(self, sessions: Callable[[], Iterable[Session]] | None = None) -> None:
        if sessions is not None:
            self._sessions = sessions
        self._task = asyncio.create_task(self._sample(), name="capacity-guard")

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task

    # ---- the measures ----------------------------------------------------------------------------
    async def _sample(self) -> None:
        weight = 1 - math.exp(-SAMPLE_EVERY_S / SMOOTHING_S)
        wall, cpu = time.monotonic(), time.thread_time()  # this runs on the loop thread: its CPU clock
        process_cpu = time.process_time()
        while True:
            await asyncio.sleep(SAMPLE_EVERY_S)
            now, now_cpu, now_process = time.monotonic(), time.thread_time(), time.process_time()
            elapsed = now - wall
            lag = max(0.0, elapsed - SAMPLE_EVERY_S)
            share = (now_cpu - cpu) / elapsed if elapsed > 0 else 0.0
            process = (now_process - process_cpu) / elapsed if elapsed > 0 else 0.0
            wall, cpu, process_cpu = now, now_cpu, now_process
            # a late timer means the loop was busy for all of it: weigh it by how long it stood
            w = min(1.0, weight * elapsed / SAMPLE_EVERY_S)
            self.lag_s += w * (lag - self.lag_s)
            self.cpu_share += w * (share - self.cpu_share)
            self.process_share += w * (process - self.process_share)
            self.metrics.loop_lag.set(self.lag_s)
            self.metrics.cpu_share.set(self.cpu_share)
            self.metrics.process_cpu_share.set(self.process_share)
            self._update_shedding(now)

    def _update_shedding(self, now: float) -> None:
        streaming = self.streaming(now)
        self._streaming = len(streaming)
        if self._shed:
            self._shed &= {s.id for s in self._sessions()}  # ended sessions leave
        if streaming:
            self.cpu_per_session = self.cpu_share / len(streaming)
        over = self.cpu_share > self.settings.cpu_budget or (self._busy() and self.lag_s > self.settings.shed_lag_s)
        if not over:
            if (
                self._shed
                and self.cpu_share < 0.9 * self.settings.cpu_budget
                and self.lag_s < self.settings.shed_lag_s / 2
            ):
                self._shed.clear()  # caught up with a margin: everyone streams again
            return
        if len(streaming) < 2:
            return  # one session is never shed for being alone: its own queue bounds it
        fits = self.sessions_that_fit()
        keep = max(1, min(len(streaming) - 1, fits))
        newest = [s.id for s in streaming[keep:]]
        if not set(newest) <= self._shed:
            self._shed.update(newest)
            if now - self._last_log > LOG_EVERY_S:
                self._last_log = now
                log.warning(
                    "at capacity (event loop CPU %.2f of %.2f, lag %.0f ms): refusing the blocks of the %d newest "
                    "of %d streaming sessions until it catches up",
                    self.cpu_share,
                    self.settings.cpu_budget,
                    self.lag_s * 1e3,
                    len(self._shed),
                    len(streaming),
                )

    def streaming(self, now: float) -> list[Session]:
        """Sessions that sent something within STREAMING_WITHIN_S, oldest first."""
        return [s for s in self._sessions() if now - s.last_activity < STREAMING_WITHIN_S and s.last_seq >= 0]

    def _busy(self) -> bool:
        """The lag is the process's own: its loop is busy, or its threads together keep the interpreter busy (pool
        threads holding the GIL make every socket operation of the loop wait for it)."""
        return self.cpu_share > self.settings.cpu_budget / 2 or self.process_share > self.settings.cpu_budget

    def sessions_that_fit(self) -> int:
        """Streaming sessions the CPU budget holds at the measured CPU per session (a large number until measured)."""
        if self.cpu_per_session <= 0:
            return 1_000_000
        return int(self.settings.cpu_budget / self.cpu_per_session)

    # ---- decisions -------------------------------------------------------------------------------
    def admit_session(self, open_sessions: int) -> None:
        """Raise ServiceError 429 (Retry-After) when a new session would not be served well."""
        if open_sessions == 0:
            return
        why = None
        budget = self.settings.cpu_budget
        if self._busy() and self.lag_s > self.settings.session_lag_s:
            why = (
                f"its event loop runs {self.lag_s * 1e3:.0f} ms late (limit {self.settings.session_lag_s * 1e3:.0f} ms)"
            )
        elif self._streaming >= 2 and self.cpu_share > budget:
            why = f"its event loop uses {self.cpu_share:.2f} of a core, over its budget of {budget:g}"
        elif self._streaming >= 4 and self.cpu_share + self.cpu_per_session > budget:
            why = (
                f"one more session ({self.cpu_per_session:.3f} of a core each) would take its event loop over its "
                f"budget of {budget:g} (now {self.cpu_share:.2f})"
            )
        if why is not None:
            self.metrics.sessions_refused.labels(reason="capacity").inc()
            raise AtCapacity(f"this replica is at capacity: {why}; try later or another replica")

    def admit_block(self, session: Session) -> None:
        """Raise ServiceError 429 (Retry-After) when `session` is among those shed while the process is over
        capacity; nothing of the block is taken."""
        if session.id in self._shed:
            raise AtCapacity(
                f"this replica is at capacity (event loop CPU {self.cpu_share:.2f} of {self.settings.cpu_budget:g}, "
                f"loop lag {self.lag_s * 1e3:.0f} ms) and session {session.id} is among its newest; "
                "resend from the oldest unacknowledged block later"
            )
