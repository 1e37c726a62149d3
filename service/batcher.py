"""Gathers sessions that have complete windows and estimates them together in the window pool.

One job estimates the windows of up to `max_sessions_per_job` sessions in a single pool call
(pipeline.estimate_batch: one window_features and one model call for all of them). At most
`max_jobs` jobs run at once (the pool's threads), a session is in at most one job, and the oldest
sessions are served first: admission (service/capacity.py) keeps the oldest sessions at full speed, so a newer
session's backlog (a robot back from an outage resends seconds of blocks at once) must not queue ahead of them —
until a session's windows have waited `STARVING_S`: then it goes first, the longest-waiting first, so that no
session admitted goes without windows while the pool catches up (a crowd of robots starting together, served
strictly oldest first, would leave the newest without a window for as long as the pool is behind).
Under light load a job holds one session and starts at once; under heavy load jobs grow, and each window gets
cheaper — up to 8 sessions: a window then costs ≈ 0.8–1.1 ms against ≈ 0.7–0.8 at 32–64 and ≈ 2 alone
(`python -m benchmarks.window_batch`, the demo's tactile model), while every session of a job waits for the whole
job's lookups before any of its windows is published. A job also holds at most `max_windows_per_job` windows (a
session's oldest; the rest of its backlog waits for a later job): a robot back from an outage resends seconds of
blocks at once, and a job of eight such backlogs would hold a pool thread, and the windows of the oldest sessions
that wait for one, for a tenth of a second.

Jobs beyond the first start only once a ready session has waited `spill_after_s` for one. Two jobs at once share the
GIL with each other and the event loop, so each takes about twice as long; under moderate load one job at a time
publishes sooner and spends less CPU (60 `served` robots on one replica, three interleaved pairs: e2e p50, p99 and
CPU lower in each; docs/service.md), and the second thread joins when one cannot keep up.

`take_waits(now)` is, per session, the longest its windows waited for a job since the last call (or wait now):
admission reads from it the window queue delay it holds below its limit, of the sessions it serves (the windows a
shed session admitted before it was shed are served last and wait, but refusing more sessions would not shorten
that), and apart that of the sessions it protects.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from concurrent.futures import Executor

from service.live_session import Session
from service.log_throttle import LogThrottle
from service.pipeline import SessionJob, SessionResult, estimate_batch
from service.runtime import Runtime

log = logging.getLogger(__name__)

_surface_failures = LogThrottle(log)

MAX_SESSIONS_PER_JOB = 8
#: a session whose windows have waited this long (s) goes before the older sessions, the longest-waiting first: the
#: oldest-first order keeps the oldest at full speed while the pool keeps up, but when it falls behind (a crowd's
#: start, the backlogs robots resend) it would leave the newest sessions without a window for seconds while the
#: older ones are served every hop
STARVING_S = 1.0
#: ≈ 20 ms of a pool thread (≈ 1.1–1.2 ms a window in jobs of 8 sessions)
MAX_WINDOWS_PER_JOB = 16


class WindowBatcher:
    def __init__(
        self,
        pool: Executor,
        max_jobs: int,
        *,
        spill_after_s: float,
        max_sessions_per_job: int = MAX_SESSIONS_PER_JOB,
        max_windows_per_job: int = MAX_WINDOWS_PER_JOB,
    ) -> None:
        if min(max_jobs, max_sessions_per_job, max_windows_per_job) < 1:
            raise ValueError(
                "max_jobs, max_sessions_per_job and max_windows_per_job must be ≥ 1, got "
                f"{max_jobs}, {max_sessions_per_job}, {max_windows_per_job}"
            )
        if not spill_after_s >= 0:
            raise ValueError(f"spill_after_s must be ≥ 0 s, got {spill_after_s}")
        self.pool = pool
        self.max_jobs = max_jobs
        self.max_sessions_per_job = max_sessions_per_job
        self.max_windows_per_job = max_windows_per_job
        self.spill_after_s = spill_after_s
        # ready sessions and the time.monotonic() each became ready; bounded by the number of sessions
        self._ready: dict[str, tuple[Session, float]] = {}
        self._waited: dict[str, float] = {}  # the longest each session taken into a job waited (s), since take_waits
        self._wake = asyncio.Event()
        self._jobs: set[asyncio.Task] = set()
        self._runner: asyncio.Task | None = None
        self._spill_timer: asyncio.TimerHandle | None = None
        self._spill_due = 0.0  # time.monotonic() the timer wakes the runner at

    def start(self) -> None:
        self._runner = asyncio.create_task(self._run(), name="window-batcher")

    async def close(self) -> None:
        if self._spill_timer is not None:
            self._spill_timer.cancel()
        tasks = [t for t in (self._runner, *self._jobs) if t is not None]
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task

    def notify(self, session: Session) -> None:
        """`session` has complete windows (called on the event loop; never blocks)."""
        if session.id not in self._ready:
            self._ready[session.id] = (session, time.monotonic())
        self._wake.set()

    def take_waits(self, now: float) -> dict[str, float]:
        """Session id → the longest (s) its complete windows waited for a job since the last call, or have waited at
        `now` (time.monotonic()) and still wait; sessions whose windows did neither are absent. Resets the record."""
        waits = self._waited
        for sid, (_, since) in self._ready.items():
            waits[sid] = max(waits.get(sid, 0.0), now - since)
        self._waited = {}
        return waits

    async def _run(self) -> None:
        while True:
            await self._wake.wait()
            self._wake.clear()
            while self._may_start_job():
                batch = await self._gather()
                if not batch:
                    break
                job = asyncio.create_task(self._estimate(batch))
                self._jobs.add(job)
                job.add_done_callback(self._job_done)

    def _may_start_job(self) -> bool:
        """A free thread takes a job when none runs, or when a ready session has waited spill_after_s for one (else
        the runner is woken when the longest-waiting one will have)."""
        if len(self._jobs) >= self.max_jobs:
            return False
        if not self._jobs or not self._ready:
            return True
        waiting = [since for session, since in self._ready.values() if not session.in_job]
        if not waiting:
            return False
        due = min(waiting) + self.spill_after_s
        now = time.monotonic()
        if now >= due:
            return True
        if self._spill_timer is None or self._spill_due > due:
            if self._spill_timer is not None:
                self._spill_timer.cancel()
            self._spill_due = due
            self._spill_timer = asyncio.get_running_loop().call_later(due - now, self._spill)
        return False

    def _spill(self) -> None:
        self._spill_timer = None
        self._wake.set()

    def _job_done(self, job: asyncio.Task) -> None:
        self._jobs.discard(job)
        if not job.cancelled() and job.exception() is not None:
            log.error("estimation job failed", exc_info=job.exception())
        self._wake.set()  # a slot is free; sessions may have become ready meanwhile

    async def _gather(self) -> list[tuple[Session, SessionJob]]:
        """Take up to max_sessions_per_job ready sessions that are not in a job, the oldest sessions first (but those
        whose windows have waited STARVING_S before them, the longest-waiting first), with their jobs, until the jobs
        hold max_windows_per_job windows."""
        batch: list[tuple[Session, SessionJob]] = []
        room = self.max_windows_per_job
        starving = time.monotonic() - STARVING_S
        # the starving first, the longest-waiting first; then the rest, the oldest sessions first
        order = sorted(
            self._ready.items(),
            key=lambda item: (0, item[1][1]) if item[1][1] <= starving else (1, item[1][0].opened_at),
        )
        for sid, (session, since) in order:
            if len(batch) >= self.max_sessions_per_job or room <= 0:
                break
            if session.in_job:
                continue  # picked up again when its job is done
            del self._ready[sid]
            self._waited[sid] = max(self._waited.get(sid, 0.0), time.monotonic() - since)
            job = session.take_job(room)
            if job is None:
                if session.waiting_for_frame() or session.waiting_for_taps():
                    await session.tell_waiting()
                continue
            session.in_job = True
            room -= job.windows
            batch.append((session, job))
        return batch

    async def _fit_surface(self, session: Session) -> None:
        """Fit the session's learnt surface model in the pool, still inside its job (so nothing else touches its
        fitter), when it is due and no other session's windows wait for the pool (else it waits for a quieter job)."""
        surface = session.surface
        if surface is None or session.closed or session.library_pick is None or not surface.due(time.monotonic()):
            return
        if any(s is not session and not s.in_job for s, _ in self._ready.values()):
            return
        try:
            prior = session.runtime.library.model(session.library_pick)
            outcome = await asyncio.get_running_loop().run_in_executor(
                self.pool, surface.fit, prior, time.monotonic(), session.library_pick
            )
        except Exception:  # noqa: BLE001 - the learnt model is an extra: operators keep what they have
            if _surface_failures.admit(session.id) is not None:
                log.warning("session %s: fitting its surface model failed", session.id, exc_info=True)
            return
        await session.apply_fit(outcome)

    async def _estimate(self, batch: list[tuple[Session, SessionJob]]) -> None:
        sessions = [s for s, _ in batch]
        runtime: Runtime = sessions[0].runtime
        try:
            try:
                loop = asyncio.get_running_loop()
                results = await loop.run_in_executor(self.pool, estimate_batch, runtime, [j for _, j in batch])
            except Exception as exc:  # noqa: BLE001 - a failure outside any one session's steps (each is isolated)
                log.exception("estimating a batch of %d session(s) failed", len(sessions))
                for s in sessions:
                    s.estimator.restart()
                results = [SessionResult([], job.windows, exc) for _, job in batch]
            for session, result in zip(sessions, results, strict=True):
                # A session leaves the job only once its windows are published (publishing awaits the
                # broker): released earlier, its next job could publish later windows first.
                await session.apply_result(result)
                await self._fit_surface(session)
                session.in_job = False
                if session.has_work():
                    self.notify(session)
        finally:
            for session in sessions:
                session.in_job = False
