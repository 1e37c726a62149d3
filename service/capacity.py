"""Admission by what the process can serve: refuse early instead of slowing every session down.

A replica is one Python process: one event loop, one GIL, about one core. `CapacityGuard` measures,
every `SAMPLE_EVERY_S`, what says how close the process is to saturation:

- **loop lag**: how late the event loop runs a timer. Every request, block and acknowledgement
  waits this long before the loop gets to it; it grows without bound once the loop has more work
  than time.
- **loop CPU share**: the event-loop thread's CPU time per wall second (0…1). The loop thread is
  what saturates first: it parses every request and WebSocket frame, decodes and admits every
  block and publishes every event, under one GIL shared with the pool threads.
- **threads' CPU share**: the loop's and its pools' threads together (`threads_cpu`, service/thread_cpu.py: not the
  process's total, which would count whatever else shares it, e.g. a test's client).

A late timer alone may mean the machine is busy with other processes; the lag counts as the
process's own only while the process is busy too: its loop thread over half its budget, or all its
threads together over the budget (then the pool threads hold the GIL, and every socket operation of
the loop waits for it: the loop is late while using little CPU itself).

- **window queue delay**: the longest the complete windows of any session not shed waited for the window pool
  (service/batcher.py, which serves the oldest sessions first). The loop can keep up with every block while the
  pool threads, sharing its GIL, fall behind on the windows: then operators' views lag although the loop is
  punctual. The windows a shed session had admitted before it was shed are served last and wait; they do not
  count, or one burst of backlog would shed session after session, the oldest in the end, for a delay that
  refusing them cannot shorten. The same delay of the protected sessions alone (below) is held apart: served
  first, their windows are late only when they themselves are more than the process can serve.

The first two are smoothed (an exponential average, time constant ≈ `SMOOTHING_S`). The queue delay is held
at its peak, decaying with time constant `QUEUE_HOLD_S`: windows come in bursts (robots that started
together complete their windows together, every hop), and an average over the quiet time between bursts
would hide the delay of each burst's last windows. From them:

- `admit_session(n)` refuses a new session (429 + Retry-After, the reason in the message) while
  any session is shed, while the lag is above `session_lag_s` or the window queue delay above
  `session_queue_s`, the loop's CPU share is above
  `cpu_budget` with two or more sessions streaming, or (four or more streaming: enough to measure)
  one more session of the measured loop CPU per streaming session would not fit the budget — counting as streaming
  the sessions opened or let start within `STARTING_WITHIN_S`, beyond the first `STARTING_UNCOUNTED` (robots that
  start together ask within a second, each before the measures show any of the others). The first session is always
  admitted. A robot that has not streamed yet starts under the same rule (below).
- `admit_block(session)` refuses the blocks of shed sessions (429 / WebSocket close 4429, Retry-After), and
  `admit_frame(session)` their camera frames (429); both refuse a session whose robot has not streamed yet while
  `admit_session` would refuse a new one (sessions opened earlier may start together), while anything streams.
  While the loop is over its CPU budget, its lag is above
  `shed_lag_s` or the window queue delay above `shed_queue_s`, one more step of the streaming sessions is shed,
  newest first: a quarter of those still served (`STEP_SHARE`), or more when the measured CPU per session says more
  do not fit, or every newcomer at once (robots that start together tip it over together). A session is *served
  well* when it was streaming while the process was last a full `SETTLE_S` within its limits and it was not
  readmitted within `PROTECT_S` (a readmitted robot resends its backlog at once: a second within the limits before
  says nothing); the others are newcomers. The oldest session is never shed, and for `PROTECT_S` into an overload
  neither is any session served well, unless their own windows have waited past twice `shed_queue_s` for a full
  `SETTLE_S`: the newcomers tipped it over, and the backlog their refusal leaves, and the refusals themselves, take
  seconds to drain. A step follows the last after `SHED_EVERY_S` while the process gets worse, after `SETTLE_S`
  while it gets no better (its pressure, the largest measure over its limit, has not fallen by a fifth since that
  step), and not at all while it gets better: the measures show a step's effect only after about a second. Shedding
  in steps this fast acts before the loop saturates: with thresholds of a few tens of milliseconds the loop never
  queues long enough to delay /health or the oldest sessions' windows. Once under the thresholds with a margin, a
  smaller step of the shed sessions (`READMIT_SHARE` of those served: each readmitted robot resends its backlog at
  once, and a step sized by the shed ones would, after a flood, readmit more at once than the process serves)
  streams again every `READMIT_EVERY_S`, oldest first — so the shed sessions are always the newest ones. The oldest
  sessions keep streaming at full quality, and the refused robots resend from their oldest unacknowledged block
  (nothing accepted is lost).

**Readmission without polling.** A refused robot (shed, or not let start) whose credential was accepted is held
(`hold`: its ingest handshake, or its block's request before the body is read) up to `readmit_hold_s`, waiting on an
event: no CPU, at most one connection per session. It is let in the moment its turn comes — its shed session
readmitted (above), or room for its start: the robots refused a start get room in the order they were first refused
(`_line`, granted by `update` while there is room for one more), and a robot that has not asked yet queues behind
them. Held past `readmit_hold_s` without room, it is answered 429 with `HELD_RETRY_AFTER_S` and keeps its place
(`LINE_KEEP_S`). With `readmit_hold_s` 0 every refusal is answered at once, told to come back (`retry_after`) after
the readmission steps of the refused sessions older than its own.

**Pictures before robots.** Camera frames are degraded before any robot is refused. The frames' wait for the
embedder (the **visual queue delay**, service/visual_queue.py) is measured apart from the window queue and never sheds
a session: a slow visual pool degrades frames, not windows. Before a frame is taken, the embedding work queued ahead
of it is bounded (`shed_visual_queue_s`, halved at `FRAMES_SAMPLED`): a frame beyond it is refused with the
Retry-After at which it would be taken, frames refused earlier going first. While the process is over its limits and
the camera path holds CPU (a frame taken within `FRAMES_WITHIN_S`, or embeddings queued), or frames wait past
`shed_visual_queue_s`, `frame_level` rises a step instead of a session being shed — `FRAMES_SAMPLED` (a session with
a visual input gets a frame every `FRAME_SAMPLE_S`), then `FRAMES_DROPPED` (none) — at once, then after `SETTLE_S`;
sessions are shed only once frames are dropped and that has had `SETTLE_S` to show. Meanwhile a late window queue
does not refuse new sessions either. A session without its frame is served tactile-only, its windows marked
(service/pipeline.py); the oldest session's frames are never degraded (it is never shed), and a session whose windows
wait for a first frame (no tactile-only model) always gets one. On the way back the shed sessions come first; frames
come back a level every `READMIT_EVERY_S` once none is shed.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import math
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping

from service.errors import ServiceError
from service.live_session import Session
from service.metrics import ServiceMetrics
from service.settings import Settings
from service.visual_queue import EmbeddingQueue

log = logging.getLogger(__name__)

SAMPLE_EVERY_S = 0.05
SMOOTHING_S = 0.5
#: the window queue delay's peak decays with this time constant (s): longer than a window hop (0.5 s), so the
#: peak of one burst of windows is still held when the next comes
QUEUE_HOLD_S = 1.0
#: a session that sent nothing for this long does not count as streaming (its CPU is not in the measure)
STREAMING_WITHIN_S = 1.0
#: the Retry-After of a refusal with no refused session older than the refused one (s); one more for each
#: readmission step of those older (they come back first), up to MAX_RETRY_AFTER_S: 150 robots refused together and
#: all told 2 s would come back together every 2–3 s, each wave of handshakes costing the loop ≈ 1 ms apiece while a
#: step of two or three of them is let in
RETRY_AFTER_S = 2.0
MAX_RETRY_AFTER_S = 10.0
#: a session opened, or let start streaming, this recently counts in admission as one more streaming: robots that
#: start together ask within a second, and the measures (smoothed over SMOOTHING_S) show none of their load until it
#: has tipped the loop over (150 at once stalled it for 200 ms); past this, a session that never streamed stops
#: counting (a client that opens sessions and sends nothing must not hold admission shut)
STARTING_WITHIN_S = 2.0
#: so many sessions may start within STARTING_WITHIN_S on the measures alone (only those beyond count as load): a
#: few cannot take the loop far past its budget in the half second its measures lag, and a small fleet's robots
#: starting one after another are not held back by a measure that robots streaming faster than real time inflate
STARTING_UNCOUNTED = 8
#: while over capacity and getting worse, one more step of sessions is shed this often (s): soon enough that the
#: loop never queues a whole second of work
SHED_EVERY_S = 0.25
#: while over capacity but no worse than at the last step, the next step waits this long (s): the measures lag what
#: they measure (the lag is smoothed over SMOOTHING_S, the queue delay's peak held over QUEUE_HOLD_S, and blocks
#: of shed sessions already in the sockets still arrive), so a step's effect shows only after about a second;
#: shedding on the old evidence meanwhile would shed session after session, the oldest in the end
SETTLE_S = 1.0
#: after SETTLE_S, no further step while the pressure has fallen below this share of its value at the last step:
#: the last step is working (a backlog drains)
IMPROVED = 0.8
#: once under the thresholds with a margin, one step of shed sessions streams again this often (s): slower than
#: shedding, so a replica near its limit does not swing between shedding and readmitting every step
READMIT_EVERY_S = 2.0
#: for this long into an overload (s), the sessions served well before it (streaming, the process within its limits
#: for SETTLE_S) are not shed: the newcomers tipped it over, and the backlog their refusal leaves takes seconds to
#: drain; past it, any session but the oldest may be shed (the machine itself may have slowed down)
PROTECT_S = 10.0
#: the protected sessions' own windows may wait this many times shed_queue_s before the protection lapses: their wait
#: also grows with load that shedding them cannot remove (a flood of requests, refusals, the newcomers' frames), so
#: only a wait well over the limit says that they themselves are more than the process can serve — and only when it
#: lasts SETTLE_S: on a machine shared with other processes one window can wait 100 ms when the scheduler parks a pool
#: thread, and shedding robots served well for that costs each of them seconds (it waits to be readmitted, then
#: resends its backlog at once)
PROTECTED_QUEUE_FACTOR = 2.0
#: the share of the sessions still served one shedding step moves
STEP_SHARE = 0.25
#: one readmission step moves this share of the sessions still served (at least one): a readmitted robot resends its
#: backlog at once, so a large step is a burst
READMIT_SHARE = 0.1
#: at most one WARNING about shedding per this many seconds
LOG_EVERY_S = 10.0
#: frame levels, the first thing degraded under load (before any session is shed): every frame taken; each session's
#: frames sampled at most every FRAME_SAMPLE_S once it has a visual input; no frame taken (dropped)
FRAMES_ALL, FRAMES_SAMPLED, FRAMES_DROPPED = 0, 1, 2
#: at FRAMES_SAMPLED, a session that has a visual input gets a frame taken at most this often (s)
FRAME_SAMPLE_S = 5.0
#: frames were taken this recently (s), or embeddings are queued: the camera path holds CPU that degrading frames
#: gives back to the windows, so it is degraded before any session is shed
FRAMES_WITHIN_S = 2.0
#: the Retry-After (s) of a robot held readmit_hold_s in line and still without room: it keeps its place, so coming
#: back soon costs it one handshake and loses it nothing (the place is kept LINE_KEEP_S after its last try)
HELD_RETRY_AFTER_S = 0.5
#: a robot refused a start keeps its place in line (and a start granted while it was away stays granted) this long
#: after its last try (s): a robot told MAX_RETRY_AFTER_S comes back within half as much again
LINE_KEEP_S = 1.5 * MAX_RETRY_AFTER_S
#: the least Retry-After (s) of a refused frame: sooner, its robot's resent body costs the loop more than it gains
MIN_FRAME_RETRY_S = 0.5


class AtCapacity(ServiceError):
    """429: the replica is at capacity (a new session, or a block of one of its newest sessions)."""

    def __init__(self, detail: str, retry_after_s: float = RETRY_AFTER_S) -> None:
        super().__init__(429, detail, {"Retry-After": f"{retry_after_s:g}"})
        self.retry_after_s = retry_after_s


class CapacityGuard:
    """See the module docstring. `start()` inside the event loop; `sessions()` lists this replica's sessions in
    creation order (oldest first). `update(now)` takes one shedding decision from the current measures (the
    sampling task calls it after each sample)."""

    def __init__(
        self,
        settings: Settings,
        metrics: ServiceMetrics,
        sessions: Callable[[], Iterable[Session]] = lambda: (),
        window_waits: Callable[[float], Mapping[str, float]] = lambda now: {},
        threads_cpu: Callable[[], float] = time.process_time,
        visual: EmbeddingQueue | None = None,
        loop_cpu: Callable[[], float] = time.thread_time,
    ) -> None:
        """window_waits(now): session id → the longest its windows waited since the last call, s
        (WindowBatcher.take_waits). threads_cpu(): CPU seconds the service's threads have used, the loop's and its
        pools' (ThreadCpu.seconds; the whole process's by default). visual: the embedding queue the sessions' frames
        wait in (service/visual_queue.py; an empty one by default). loop_cpu(), called on the event-loop thread: that
        thread's CPU seconds (ThreadCpu.loop_seconds)."""
        self.settings = settings
        self.metrics = metrics
        self.lag_s = 0.0
        self.queue_s = 0.0  # window queue delay of the sessions not shed, its peak held (QUEUE_HOLD_S)
        self.protected_queue_s = 0.0  # the same of the sessions served well before an overload (not shed)
        self._window_waits = window_waits
        self.cpu_share = 0.0
        self.process_share = 0.0  # cores the service's threads used together (the loop and its pools), smoothed
        self._threads_cpu = threads_cpu
        self._loop_cpu = loop_cpu
        self.cpu_per_session = 0.0  # loop CPU per streaming session (0 until measured)
        self.process_per_session = 0.0  # the whole process's CPU per streaming session (0 until measured)
        self._streaming = 0
        self._shed: set[str] = set()
        self._sessions = sessions
        self._task: asyncio.Task | None = None
        self._last_log = 0.0
        self._last_shed = -math.inf  # time.monotonic() of the last shedding step
        # (time.monotonic(), self.pressure()) at the last step, or at the last settling time over without one
        self._reference = (-math.inf, 0.0)
        # opened_at of the newest session streaming (and not shed) when the process was within its limits for
        # SETTLE_S on end: those up to it were served well (None until measured)
        self._newest_within_limits: float | None = None
        self._within: deque[tuple[float, float]] = deque()  # (time, newest streaming opened_at) of samples within
        # session id → time.monotonic() it was readmitted, for PROTECT_S: a readmitted robot resends its backlog at
        # once, and a second within the limits before that says nothing of how it is served
        self._readmitted: dict[str, float] = {}
        self._over_since: float | None = None  # when the current overload episode began
        # since when the protected sessions' own queue delay has been over PROTECTED_QUEUE_FACTOR × shed_queue_s
        self._protected_late_since: float | None = None
        # session id → time.monotonic() its robot was let start streaming, for STARTING_WITHIN_S (load not measured yet)
        self._started: dict[str, float] = {}
        self._last_readmit = -math.inf
        # session id → time.monotonic() its robot was last refused a start (for retry_after)
        self._waiting: dict[str, float] = {}
        # when the refused robots waiting to start last had room (None while there is none), for the readmission wait
        self._room_since: float | None = None
        # session id → time.monotonic() it was let back (readmitted, or room to start), until its first block passes
        self._let_back: dict[str, float] = {}
        # robots refused a start, in the order they were first refused (session id → that time.monotonic()): room
        # goes to them in this order (`_grant_starts`), and a robot that has not asked yet queues behind them
        self._line: dict[str, float] = {}
        # session id → time.monotonic() its start was granted while its robot was not held: it starts when it is back
        self._granted: dict[str, float] = {}
        # session id → the event its held robot waits on (`hold`): one robot connection per session
        self._held: dict[str, asyncio.Event] = {}
        self._closed = False
        # ---- frames: degraded before sessions (module docstring) ----
        self.visual = EmbeddingQueue() if visual is None else visual
        self.visual_queue_s = 0.0  # the visual queue delay: frames' wait for the embedder, its peak held (QUEUE_HOLD_S)
        self.frame_level = FRAMES_ALL
        self._frame_step = -math.inf  # time.monotonic() of the last change of frame_level
        self._frame_at = -math.inf  # time.monotonic() a frame was last taken
        self._frame_taken: dict[str, float] = {}  # session id → when its last frame was taken
        # session id → time.monotonic() its frame was first refused for the embedding queue, until one is taken: the
        # order frames are taken in once there is room (arrival)
        self._frames_waiting: dict[str, float] = {}

    def start(self) -> None:
        self._task = asyncio.create_task(self._sample(), name="capacity-guard")

    async def close(self) -> None:
        self.release_held()
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task

    # ---- the measures ----------------------------------------------------------------------------
    async def _sample(self) -> None:
        weight = 1 - math.exp(-SAMPLE_EVERY_S / SMOOTHING_S)
        wall, cpu = time.monotonic(), self._loop_cpu()  # this runs on the loop thread: its CPU clock
        process_cpu = self._threads_cpu()
        while True:
            await asyncio.sleep(SAMPLE_EVERY_S)
            now, now_cpu, now_process = time.monotonic(), self._loop_cpu(), self._threads_cpu()
            elapsed = now - wall
            lag = max(0.0, elapsed - SAMPLE_EVERY_S)
            share = (now_cpu - cpu) / elapsed if elapsed > 0 else 0.0
            # (a pool thread that ended takes its time out of the sum)
            process = max(0.0, now_process - process_cpu) / elapsed if elapsed > 0 else 0.0
            wall, cpu, process_cpu = now, now_cpu, now_process
            # a late timer means the loop was busy for all of it: weigh it by how long it stood
            w = min(1.0, weight * elapsed / SAMPLE_EVERY_S)
            self.lag_s += w * (lag - self.lag_s)
            self.cpu_share += w * (share - self.cpu_share)
            self.process_share += w * (process - self.process_share)
            decay = math.exp(-elapsed / QUEUE_HOLD_S)
            self._hold_queue_delays(self._window_waits(now), decay, now)
            self.visual_queue_s = max(self.visual_queue_s * decay, self.visual.wait_s(now))
            self.metrics.visual_queue.set(self.visual_queue_s)
            self.metrics.loop_lag.set(self.lag_s)
            self.metrics.window_queue.set(self.queue_s)
            self.metrics.protected_window_queue.set(self.protected_queue_s)
            self.metrics.cpu_share.set(self.cpu_share)
            self.metrics.process_cpu_share.set(self.process_share)
            self.update(now)
            self.metrics.frame_level.set(self.frame_level)

    def _hold_queue_delays(self, waits: Mapping[str, float], decay: float, now: float) -> None:
        """Take the windows' latest waits (session id → s) into the held peaks: that of every session served, and
        that of the ones served well (protected); each peak decays by `decay` since the last sample."""
        served = [(sid, w) for sid, w in waits.items() if sid not in self._shed]
        # who is protected is asked only when some window waited: most samples of a quiet replica have none
        protected = {s.id for s in self._sessions() if self._served_well(s, now)} if served else set()
        self.queue_s = max([self.queue_s * decay, *(w for _, w in served)])
        self.protected_queue_s = max([self.protected_queue_s * decay, *(w for sid, w in served if sid in protected)])

    def _served_well(self, session: Session, now: float) -> bool:
        """Streaming before the process was last within its limits for SETTLE_S, and not readmitted within PROTECT_S."""
        boundary = self._newest_within_limits
        readmitted = self._readmitted.get(session.id)
        return (
            boundary is not None
            and session.opened_at <= boundary
            and (readmitted is None or now - readmitted >= PROTECT_S)
        )

    def update(self, now: float) -> None:
        """One shedding decision at `now` (time.monotonic(), s) from the current measures: shed a step, readmit
        a step, or nothing."""
        streaming = self.streaming(now)
        self._streaming = len(streaming)
        if self._started:
            self._started = {sid: t for sid, t in self._started.items() if now - t < STARTING_WITHIN_S}
        if self._shed or self._readmitted or self._let_back:
            ids = {s.id for s in self._sessions()}  # ended sessions leave
            self._shed &= ids
            self._readmitted = {sid: t for sid, t in self._readmitted.items() if sid in ids and now - t < PROTECT_S}
            self._let_back = {sid: t for sid, t in self._let_back.items() if sid in ids}
        # the sessions just let start stream, but their load is not in the smoothed share yet: counted, they would
        # lower the cost per session and make room for more of them
        measured = [s for s in streaming if s.id not in self._started] or streaming
        if measured:
            self.cpu_per_session = self.cpu_share / len(measured)
            self.process_per_session = self.process_share / len(measured)
        if self.protected_queue_s <= PROTECTED_QUEUE_FACTOR * self.settings.shed_queue_s:
            self._protected_late_since = None
        elif self._protected_late_since is None:
            self._protected_late_since = now
        self._track_room(now)
        if self._line or self._granted:
            self._grant_starts(now)
        if self._over():
            self._within.clear()  # within its limits again only after SETTLE_S more
            if self._over_since is None:
                self._over_since = now
            if self._frames_first(now):
                return  # frames give back their CPU before any robot is refused
            pressure, (ref_t, ref_p) = self.pressure(), self._reference
            if now - self._last_shed >= SHED_EVERY_S and pressure > ref_p:  # worse
                self._shed_newest(streaming, now)
                self._reference = (now, pressure)
            elif now - ref_t >= SETTLE_S:
                if pressure > IMPROVED * ref_p:  # no better
                    self._shed_newest(streaming, now)
                self._reference = (now, pressure)
            return
        self._reference = (now, 0.0)  # the next time over is worse: a step at once
        if self.visual_queue_s > self.settings.shed_visual_queue_s:
            self._frames_first(now)  # a slow visual pool degrades frames, never the robots' windows
        self._record_within_limits(streaming, now)
        if self._shed and self._calm() and now - max(self._last_shed, self._last_readmit) >= READMIT_EVERY_S:
            self._readmit_oldest(streaming, now)
        elif not self._shed:
            self._restore_frames(now)  # the robots back first, then their frames

    # ---- frames: degraded before sessions ------------------------------------------------------------
    def _frames_flow(self, now: float) -> bool:
        """The camera path holds CPU now: a frame was taken within FRAMES_WITHIN_S, or embeddings are queued."""
        return now - self._frame_at < FRAMES_WITHIN_S or self.visual.jobs > 0

    def _frames_first(self, now: float) -> bool:
        """Over capacity while the camera path holds CPU, or frames waiting for the embedder past
        shed_visual_queue_s: frames are degraded one level (the first step at once, the next after SETTLE_S, when the
        last one's effect shows). True while that stands in for shedding sessions: frames still have a level to give
        or the last one's effect has not shown yet."""
        if not self._frames_flow(now) and self.visual_queue_s <= self.settings.shed_visual_queue_s:
            return False
        if sum(1 for _ in itertools.islice(self._sessions(), 2)) < 2:
            return False  # the oldest session's frames are never degraded, as it is never shed: none to degrade
        if self.frame_level < FRAMES_DROPPED:
            if now - self._frame_step >= SETTLE_S:
                self.frame_level += 1
                self._frame_step = now
                self._reference = (now, self.pressure())  # sessions, if it comes to them, from this evidence
                self.metrics.frame_level.set(self.frame_level)
                if now - self._last_log > LOG_EVERY_S:
                    self._last_log = now
                    log.warning(
                        "at capacity (event loop CPU %.2f of %.2f, lag %.0f ms, windows queued %.0f ms, frames queued "
                        "%.0f ms for the embedder): camera frames %s; windows without a visual input are estimated "
                        "tactile-only",
                        self.cpu_share,
                        self.settings.cpu_budget,
                        self.lag_s * 1e3,
                        self.queue_s * 1e3,
                        self.visual_queue_s * 1e3,
                        "sampled less often" if self.frame_level == FRAMES_SAMPLED else "dropped",
                    )
            return True
        return now - self._frame_step < SETTLE_S

    def _restore_frames(self, now: float) -> None:
        """Calm, no session shed, and frames' own wait under half its limit: frames one level back every
        READMIT_EVERY_S."""
        if (
            self.frame_level > FRAMES_ALL
            and self._calm()
            and self.visual_queue_s < 0.5 * self.settings.shed_visual_queue_s
            and now - self._frame_step >= READMIT_EVERY_S
        ):
            self.frame_level -= 1
            self._frame_step = now
            self.metrics.frame_level.set(self.frame_level)

    def _frame_budget_s(self, level: int | None = None) -> float:
        """Embedding work (s) a frame may find queued ahead of it at frame `level` (the current one by default)."""
        level = self.frame_level if level is None else level
        if level >= FRAMES_DROPPED:
            return 0.0
        return self.settings.shed_visual_queue_s / (2**level)

    def _is_oldest(self, session: Session) -> bool:
        return next(iter(self._sessions()), None) is session

    def _refuse_frame_for_load(self, session: Session, now: float) -> None:
        """The frame level, and the embedding queue bounded in time: ServiceError 429 with the Retry-After at which a
        frame of this session would be taken (frames waiting are taken in the order they were first refused). A
        session whose windows wait for a first frame (no tactile-only model) always gets one: refusing it would stop
        its windows, not degrade them."""
        level, visual = self.frame_level, self.visual
        if level == FRAMES_ALL and visual.ahead_s() <= self._frame_budget_s() and not self._frames_waiting:
            self._frame_taken_now(session, now)
            return
        if level > FRAMES_ALL and self._is_oldest(session):
            level = FRAMES_ALL  # the oldest session is never shed, nor are its frames degraded: only bounded
        waiting_for_frame = getattr(session, "waiting_for_frame", None)
        if waiting_for_frame is not None and waiting_for_frame():
            self._frame_taken_now(session, now)
            return
        if self._frames_waiting:  # robots that stopped asking are not waited for
            horizon = now - 2 * MAX_RETRY_AFTER_S
            self._frames_waiting = {sid: t for sid, t in self._frames_waiting.items() if t > horizon}
        # frames waiting are in the order they were first refused (insertion order): those before this one go first
        line = list(self._frames_waiting)
        ahead = line.index(session.id) if session.id in self._frames_waiting else len(line)
        why = None
        retry = 0.0
        if level >= FRAMES_DROPPED:
            why = "camera frames are dropped until it catches up"
            retry = READMIT_EVERY_S * level
        elif level == FRAMES_SAMPLED and getattr(session, "visual", None) is not None:
            since = now - self._frame_taken.get(session.id, -math.inf)
            if since < FRAME_SAMPLE_S:
                why = f"camera frames are sampled once every {FRAME_SAMPLE_S:g} s per robot"
                retry = FRAME_SAMPLE_S - since
        if why is None:
            budget = self._frame_budget_s(level)
            if visual.ahead_s() + ahead * visual.embed_s <= budget or visual.jobs == 0:
                self._frame_taken_now(session, now)
                return
            why = f"{visual.ahead_s() * 1e3:.0f} ms of embeddings are queued (limit {budget * 1e3:.0f} ms)" + (
                f", and the frames of {ahead} robot(s) refused before this one go first" if ahead else ""
            )
            retry = visual.drain_s(budget) + (ahead + 1) * visual.embed_s
        self._frames_waiting.setdefault(session.id, now)
        retry = min(MAX_RETRY_AFTER_S, max(MIN_FRAME_RETRY_S, math.ceil(retry * 10) / 10))
        raise AtCapacity(
            f"this replica is at capacity for camera frames: {why}; windows are estimated without them "
            "(tactile-only, marked) meanwhile; send the newest frame later",
            retry,
        )

    def _frame_taken_now(self, session: Session, now: float) -> None:
        self._frame_at = now
        self._frame_taken[session.id] = now
        self._frames_waiting.pop(session.id, None)
        if len(self._frame_taken) > 4 * max(1, len(self._started) + self._streaming) + 64:
            ids = {s.id for s in self._sessions()}  # ended sessions leave
            self._frame_taken = {sid: t for sid, t in self._frame_taken.items() if sid in ids}

    # ---- readmission: how soon a refused robot is back once there is room ---------------------------
    def _track_room(self, now: float) -> None:
        """Robots refused a start wait: since when there has been room for one more (None while there is none)."""
        if not self._waiting:
            self._room_since = None
            return
        if self._why_no_room(now) is None:
            if self._room_since is None:
                self._room_since = now
        else:
            self._room_since = None

    def _came_back(self, session: Session, now: float) -> None:
        """A robot let back (readmitted, or let start after a refusal) streams again: observe how long it took from
        the moment there was room for it."""
        back = self._let_back.pop(session.id, None)
        if back is not None:
            self.metrics.readmit_seconds.observe(max(0.0, now - back))

    def _record_within_limits(self, streaming: list[Session], now: float) -> None:
        """A sample within the limits: the sessions streaming a SETTLE_S ago, the process within its limits since,
        were served well (they become the protected ones); an overload episode ends after SETTLE_S within them."""
        self._within.append((now, max((s.opened_at for s in streaming if s.id not in self._shed), default=-math.inf)))
        while len(self._within) > 1 and self._within[1][0] <= now - SETTLE_S:
            self._within.popleft()
        since, newest = self._within[0]
        if since <= now - SETTLE_S:
            if newest == -math.inf:  # none streaming then: no session was served well, and none is a newcomer
                self._newest_within_limits = None
            else:  # a session shed since (not streaming) was still served well before
                self._newest_within_limits = max(newest, self._newest_within_limits or -math.inf)
            self._over_since = None

    def _over(self) -> bool:
        """The loop is over its CPU budget, or (while the lateness is the process's own) late by more than shed_lag_s
        or its windows queued longer than shed_queue_s."""
        return self.cpu_share > self.settings.cpu_budget or self._late(1.0)

    def pressure(self) -> float:
        """How far over its limits the process is: the largest of loop CPU ÷ budget, lag ÷ shed_lag_s and queue delay
        ÷ shed_queue_s (above 1: over)."""
        s = self.settings
        return max(self.cpu_share / s.cpu_budget, self.lag_s / s.shed_lag_s, self.queue_s / s.shed_queue_s)

    def _calm(self) -> bool:
        """Under the shedding thresholds with a margin (90 % of the budget, half the shed lag and queue delay): room
        for a step back."""
        return self.cpu_share < 0.9 * self.settings.cpu_budget and not self._late(0.5)

    def _late(self, share: float) -> bool:
        """The process is busy and its loop lag or window queue delay is above `share` × its shedding limit."""
        s = self.settings
        return self._busy() and (self.lag_s > share * s.shed_lag_s or self.queue_s > share * s.shed_queue_s)

    @staticmethod
    def _step(n: int, share: float) -> int:
        """Sessions one step moves: `share` of n, at least one."""
        return max(1, math.ceil(share * n))

    def _shed_newest(self, streaming: list[Session], now: float) -> None:
        """Refuse the blocks of one step of the newest streaming sessions not yet shed; the oldest always streams."""
        candidates = [s for s in streaming[1:] if s.id not in self._shed]
        boundary = self._newest_within_limits
        early = self._over_since is not None and now - self._over_since < PROTECT_S
        late = self._protected_late_since
        if boundary is not None and early and (late is None or now - late < SETTLE_S):
            # early in an overload, while their own windows are on time (they are served first), or have been late
            # for less than SETTLE_S: the sessions served well before it are not what tipped it over (the newcomers,
            # the load of their refusals, or other processes on the machine are)
            candidates = [s for s in candidates if not self._served_well(s, now)]
        if not candidates:
            return  # one session is never shed for being alone: its own queue bounds it
        # at least a step (of those still served: a step of all would overshoot into the oldest after a burst);
        # more when the measured CPU per session says more do not fit, and every session that began streaming
        # since the process was last within its limits (what tipped it over: robots that start together)
        served = len(candidates) + 1
        newcomers = 0 if boundary is None else sum(not self._served_well(s, now) for s in candidates)
        count = max(self._step(served, STEP_SHARE), served - self.sessions_that_fit(), newcomers)
        newest = [s.id for s in candidates[-count:]]
        self._shed.update(newest)
        self._last_shed = now
        self.metrics.sessions_shed.inc(len(newest))
        if now - self._last_log > LOG_EVERY_S:
            self._last_log = now
            log.warning(
                "at capacity (event loop CPU %.2f of %.2f, lag %.0f ms, windows queued %.0f ms): refusing the blocks "
                "of the %d newest of %d sessions until it catches up",
                self.cpu_share,
                self.settings.cpu_budget,
                self.lag_s * 1e3,
                self.queue_s * 1e3,
                len(self._shed),
                len(streaming) + len(self._shed) - len(newest),
            )

    def _readmit_oldest(self, streaming: list[Session], now: float) -> None:
        """Let one step of the shed sessions stream again, oldest first (the reverse of the order they were shed)."""
        shed = [s.id for s in self._sessions() if s.id in self._shed]  # creation order: oldest first
        served = sum(s.id not in self._shed for s in streaming)
        back = shed[: self._step(served, READMIT_SHARE)]
        self._shed.difference_update(back)
        self._readmitted.update(dict.fromkeys(back, now))
        self._let_back.update(dict.fromkeys(back, now))
        self._last_readmit = now
        self._wake(back)

    @property
    def shedding(self) -> int:
        """Sessions whose blocks are refused now."""
        return len(self._shed)

    def streaming(self, now: float) -> list[Session]:
        """Sessions that sent something within STREAMING_WITHIN_S, oldest first."""
        return [s for s in self._sessions() if now - s.last_activity < STREAMING_WITHIN_S and s.last_seq >= 0]

    def starting(self, now: float) -> int:
        """Admitted load that no measure shows yet: the sessions whose robot was let start streaming within
        STARTING_WITHIN_S, and the sessions opened within it that have not, beyond the first STARTING_UNCOUNTED
        (so few cannot take the loop far past its budget before the measures show them)."""
        opened = sum(
            1
            for s in self._sessions()
            if s.last_seq < 0 and s.id not in self._started and now - s.opened_at < STARTING_WITHIN_S
        )
        began = sum(1 for t in self._started.values() if now - t < STARTING_WITHIN_S)
        return max(0, opened + began - STARTING_UNCOUNTED)

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
        why = self._why_no_room(time.monotonic())
        if why is not None:
            self.metrics.sessions_refused.labels(reason="capacity").inc()
            raise AtCapacity(f"this replica is at capacity: {why}; try later or another replica")

    def _why_no_room(self, now: float) -> str | None:
        """Why one more streaming session would not be served well now, or None when it would."""
        budget = self.settings.cpu_budget
        if self._shed:
            return f"it refuses the blocks of {len(self._shed)} of its sessions to keep up with the others"
        if self._busy() and self.lag_s > self.settings.session_lag_s:
            return (
                f"its event loop runs {self.lag_s * 1e3:.0f} ms late (limit {self.settings.session_lag_s * 1e3:.0f} ms)"
            )
        if self._busy() and self.queue_s > self.settings.session_queue_s and not self._frames_can_give(now):
            return (
                f"its windows wait {self.queue_s * 1e3:.0f} ms for estimation "
                f"(limit {self.settings.session_queue_s * 1e3:.0f} ms)"
            )
        if self._streaming >= 2 and self.cpu_share > budget:
            return f"its event loop uses {self.cpu_share:.2f} of a core, over its budget of {budget:g}"
        if self._streaming < 4:  # too few to measure a session's cost by
            return None
        starting = self.starting(now)
        # the loop, and its threads together: the window and frame pools share its GIL, and a robot streaming with a
        # camera costs them half as much again as the loop (its windows, its frames' decoding and embedding)
        for what, share, per_session in (
            ("its event loop", self.cpu_share, self.cpu_per_session),
            ("its threads together", self.process_share, self.process_per_session),
        ):
            if share + (starting + 1) * per_session > budget:
                return (
                    f"one more session ({per_session:.3f} of a core each) would take {what} over the budget of "
                    f"{budget:g} (now {share:.2f}"
                    + (f", with {starting} session(s) admitted and not measured yet" if starting else "")
                    + ")"
                )
        return None

    def _frames_can_give(self, now: float) -> bool:
        """The camera path holds CPU and frames are not dropped yet: a late window is answered by degrading frames
        first (the robots' windows are what stays), not by refusing robots."""
        return self._frames_flow(now) and self.frame_level < FRAMES_DROPPED

    def admit_block(self, session: Session) -> None:
        """Raise ServiceError 429 (Retry-After) when `session` is among those shed while the process is over
        capacity, or has not streamed yet while one more streaming session would not be served well (robots whose
        sessions were opened earlier may start together): its blocks, and its ingest socket's handshake; nothing of
        the block is taken."""
        self._refuse_if_shed(session, "resend from the oldest unacknowledged block later")
        self._refuse_until_started(session, "it starts when there is room: send its first block later", start=True)
        if self._let_back:
            self._came_back(session, time.monotonic())

    def admit_frame(self, session: Session) -> None:
        """Raise ServiceError 429 (Retry-After) when `session` is among those shed, or waits to start: its frames
        wait with its blocks."""
        self._refuse_if_shed(session, "send the newest frame later")
        self._refuse_until_started(session, "its frames wait with its first block: send the newest frame later")
        self._refuse_frame_for_load(session, time.monotonic())

    def _refuse_until_started(self, session: Session, then: str, start: bool = False) -> None:
        """Refuse a session whose robot has not streamed yet while there is no room for one more streaming session;
        `start`: when there is, it starts (counted in `starting` until the measures show its load)."""
        if session.last_seq >= 0:
            return
        if session.id in self._started:  # let start (its turn came while it was away: it is back)
            if start:
                self._granted.pop(session.id, None)
            return
        now = time.monotonic()
        why = None if session.id in self._granted else self._why_no_start(session, now)
        if why is not None:
            session.heard()  # its robot is there, waiting for room: not an abandoned session
            self._waiting[session.id] = now
            self._line.setdefault(session.id, now)
            raise AtCapacity(
                f"this replica is at capacity: {why}; session {session.id} has not streamed yet: {then}",
                self.retry_after(session, now),
            )
        if start:
            self._started[session.id] = now
            self._granted.pop(session.id, None)
            self._line.pop(session.id, None)
            refused = self._waiting.pop(session.id, None)
            if refused is not None and session.id not in self._let_back:
                # there was room for it since max(its refusal, the room's return)
                self._let_back[session.id] = self._room_for(refused, now)

    def _why_no_start(self, session: Session, now: float) -> str | None:
        """Why the robot of `session`, which has not streamed yet, may not start now (None: it may): no room for one
        more streaming session, or robots refused before it wait in line (they start first, in arrival order)."""
        # with nothing streaming there is no one to keep at full speed (and nothing measured): it starts
        why = self._why_no_room(now) if self._streaming else None
        if why is not None:
            return why
        ahead = next(iter(self._line), session.id) != session.id
        if ahead:
            before = len(self._line) if session.id not in self._line else list(self._line).index(session.id)
            return f"{before} robot(s) refused a start before this one start first, in the order they came"
        return None

    def _room_for(self, refused: float, now: float) -> float:
        """When there was room for a robot last refused at `refused`: since max(its refusal, the room's return)."""
        return max(refused, self._room_since if self._room_since is not None else now)

    def _grant_starts(self, now: float) -> None:
        """While there is room for one more streaming session, the robot first in line may start (`_started`: its load
        counted until the measures show it): its held connection is let in at once, or, away between tries, it starts
        when it is back. Robots that stopped trying leave the line after LINE_KEEP_S."""
        ids = {s.id: s for s in self._sessions()}
        self._line = {
            sid: t
            for sid, t in self._line.items()
            if sid in ids
            and ids[sid].last_seq < 0
            and (sid in self._held or now - self._waiting.get(sid, t) < LINE_KEEP_S)
        }
        self._granted = {sid: t for sid, t in self._granted.items() if sid in ids and now - t < LINE_KEEP_S}
        granted = []
        while self._line:
            sid = next(iter(self._line))
            if self._streaming and self._why_no_room(now) is not None:
                break
            refused = self._line.pop(sid)
            self._started[sid] = now
            self._let_back[sid] = self._room_for(self._waiting.pop(sid, refused), now)
            if sid not in self._held:
                self._granted[sid] = now
            granted.append(sid)
        self._wake(granted)

    # ---- holding refused robots: readmitted the moment there is room, no polling ---------------------------------
    def _wake(self, ids: Iterable[str]) -> None:
        for sid in ids:
            event = self._held.get(sid)
            if event is not None:
                event.set()

    def release_held(self) -> None:
        """Let every held robot go (the process shuts down): each is answered by what its route checks next."""
        self._closed = True
        self._wake(list(self._held))

    async def hold(self, session: Session, hold_s: float) -> None:
        """`admit_block(session)`, and while it refuses for capacity, hold the robot up to `hold_s` seconds: the
        caller (an ingest socket's handshake, a block's request) waits on an event, costing no CPU, until the robot's
        turn comes — its shed session readmitted, or room for its start, in arrival order — and is let in at once. At
        most one robot connection per session waits (a newer one takes its place: the older is answered 429 at once),
        so the line never holds more than the replica's sessions. AtCapacity (429 + Retry-After) when `hold_s` is 0,
        when the hold ends without room (a short Retry-After: it keeps its place), or when a newer connection took its
        place. The credential must have been checked before: nothing is held for an unknown client."""
        try:
            self.admit_block(session)
            return
        except AtCapacity as refused:
            if hold_s <= 0 or self._closed:
                raise
            last = refused
        sid = session.id
        mine = asyncio.Event()
        self._wake([sid])  # an older connection of this robot, held: answered now, this one waits in its place
        self._held[sid] = mine
        self.metrics.robots_held.set(len(self._held))
        deadline = time.monotonic() + hold_s
        try:
            while True:
                left = deadline - time.monotonic()
                if left > 0:
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(mine.wait(), left)
                mine.clear()
                if self._held.get(sid) is not mine:
                    raise AtCapacity(
                        f"{last.detail}; a newer connection of session {sid} waits in this one's place",
                        HELD_RETRY_AFTER_S,
                    )
                if self._closed or getattr(session, "closed", False):
                    return  # the caller's next checks answer (shutting down: 503; the session ended: 404 / 410)
                try:
                    self.admit_block(session)
                    return
                except AtCapacity as refused:
                    last = refused
                if time.monotonic() >= deadline:
                    raise AtCapacity(
                        f"{last.detail} (held {hold_s:g} s in line; its place is kept: come back soon)",
                        HELD_RETRY_AFTER_S,
                    )
        finally:
            if self._held.get(sid) is mine:
                del self._held[sid]
            self.metrics.robots_held.set(len(self._held))

    def _refuse_if_shed(self, session: Session, then: str) -> None:
        if session.id in self._shed:
            session.heard()  # its robot retries as told: not an idle session (nor a streaming one)
            raise AtCapacity(
                f"this replica is at capacity (event loop CPU {self.cpu_share:.2f} of {self.settings.cpu_budget:g}, "
                f"loop lag {self.lag_s * 1e3:.0f} ms, windows queued {self.queue_s * 1e3:.0f} ms) and session "
                f"{session.id} is among its newest; {then}",
                self.retry_after(session, time.monotonic()),
            )

    def retry_after(self, session: Session, now: float) -> float:
        """Seconds the robot of a refused session should wait (s): RETRY_AFTER_S, and as much again for each
        readmission step of the refused sessions older than it, up to MAX_RETRY_AFTER_S. Refused: shed, or waiting
        to start (its robot refused within the longest Retry-After and its spread). Room comes back oldest first and
        about one step per READMIT_EVERY_S, so a robot told to come back sooner would only be refused again."""
        self._waiting = {sid: t for sid, t in self._waiting.items() if now - t < 1.5 * MAX_RETRY_AFTER_S}
        ahead = sum(
            1
            for s in self._sessions()
            if s.opened_at < session.opened_at and (s.id in self._shed or s.id in self._waiting)
        )
        step = self._step(max(1, self._streaming), READMIT_SHARE)
        return min(MAX_RETRY_AFTER_S, RETRY_AFTER_S * (1 + ahead // step))
