"""Refuse early, answer always, on a real uvicorn: admission by what the process can serve (shedding in steps, newest
first, back oldest first), and probes answered before routing on the service's port and from a thread of their own on
the probe port. Behaviour only (what is refused, in what order, how it is explained); speeds are measured by
`python -m benchmarks.admission`."""

from __future__ import annotations

import asyncio
import json
import logging
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from types import SimpleNamespace

import httpx
import pytest
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from drivers.blocks import encode_binary
from service.capacity import (
    MAX_RETRY_AFTER_S,
    PROTECT_S,
    READMIT_EVERY_S,
    READMIT_SHARE,
    RETRY_AFTER_S,
    SAMPLE_EVERY_S,
    SETTLE_S,
    SHED_EVERY_S,
    STARTING_UNCOUNTED,
    STARTING_WITHIN_S,
    STEP_SHARE,
    AtCapacity,
    CapacityGuard,
)
from service.metrics import ServiceMetrics
from service.settings import Settings
from service.thread_cpu import ThreadCpu

WORKER_THREADS = 40  # anyio's default thread limiter: the pool FastAPI runs plain-def dependencies and routes in


@pytest.fixture(scope="module")
def over_budget(kit, base_settings):
    """A replica whose event-loop CPU budget is below what even an idle loop uses: it is always over capacity (its
    lag limits out of reach: the machine's own load must not decide what this test sees)."""
    settings = base_settings.model_copy(
        update={
            "instance_id": "tight",
            "cpu_budget": 1e-6,
            "session_lag_s": 600,
            "shed_lag_s": 600,
            "session_queue_s": 600,
            "shed_queue_s": 600,
            "readmit_hold_s": 0,  # refusals answered at once (tests/service/test_service_readmission.py: held)
        }
    )
    with kit.running(settings, cpu_meter=ThreadCpu()) as srv:
        yield srv


def test_over_capacity_new_sessions_and_the_newest_sessions_blocks_are_refused_with_a_reason(
    kit, over_budget, library_dir
):
    blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_002", 1.0))
    with httpx.Client(base_url=over_budget.url, timeout=10) as client:
        oldest, newest = kit.create_session(client, "oldest"), kit.create_session(client, "newest")
        waiting = kit.create_session(client, "waiting")  # opened before the others stream; its robot starts later

        def refused_session() -> httpx.Response | None:
            for session in (oldest, newest):  # both stream, so both count as load
                kit.post_block(client, session, blocks[0])
            r = client.post("/sessions", json={"name": "one more"}, headers=kit.FLEET)
            return r if r.status_code == 429 else None

        r = kit.wait_for(refused_session, timeout_s=60)  # a hang guard: on a busy host requests take seconds
        detail = r.json()["detail"]
        assert "at capacity" in detail and ("over its budget" in detail or "refuses the blocks of 1" in detail)
        assert float(r.headers["retry-after"]) > 0
        # the newest session's blocks are shed (nothing taken), the oldest streams on
        shed = kit.wait_for(lambda: (r := kit.post_block(client, newest, blocks[1])).status_code == 429 and r)
        assert "newest" in shed.json()["detail"] and float(shed.headers["retry-after"]) > 0
        for block in blocks[1:10]:
            assert kit.post_block(client, oldest, block).status_code == 202
        assert kit.session_status(client, newest)["counters"]["blocks_refused"] >= 1
        # its camera frames too, before they are decoded
        frame = client.post(
            f"/sessions/{newest['session_id']}/frames",
            content=kit.png(),
            headers={"Authorization": f"Bearer {newest['robot_token']}", "Content-Type": "image/png"},
        )
        assert frame.status_code == 429 and "newest frame later" in frame.json()["detail"]
        assert float(frame.headers["retry-after"]) > 0
        assert kit.session_status(client, newest)["counters"]["frames_refused"] == 1
        # a robot that has not streamed yet starts when there is room: its first block and frames wait
        first = kit.post_block(client, waiting, blocks[0])
        assert first.status_code == 429 and "has not streamed yet" in first.json()["detail"]
        assert float(first.headers["retry-after"]) > 0
        frame = client.post(
            f"/sessions/{waiting['session_id']}/frames",
            content=kit.png(),
            headers={"Authorization": f"Bearer {waiting['robot_token']}", "Content-Type": "image/png"},
        )
        assert frame.status_code == 429 and "frames wait with its first block" in frame.json()["detail"]
        assert kit.session_status(client, waiting)["counters"]["blocks_refused"] == 1
        # over WebSocket: the handshake refused before the upgrade (429, the reason, Retry-After)
        with pytest.raises(InvalidStatus) as refused:
            connect(kit.socket_url(over_budget, newest, "ingest"))
        answer = refused.value.response
        assert answer.status_code == 429 and float(answer.headers["Retry-After"]) > 0
        assert "capacity" in json.loads(answer.body)["detail"]
        metrics = client.get("/metrics", headers=kit.SCRAPER).text
        assert 'hapticlink_sessions_refused_total{reason="capacity"}' in metrics
        assert "hapticlink_loop_lag_seconds" in metrics and "hapticlink_loop_cpu_share" in metrics


def test_the_first_session_is_always_admitted(kit, base_settings):
    """Nothing to shed for: a replica without sessions admits one even over its budget."""
    settings = base_settings.model_copy(update={"instance_id": "tight-empty", "cpu_budget": 1e-6})
    with kit.running(settings, cpu_meter=ThreadCpu()) as srv, httpx.Client(base_url=srv.url, timeout=10) as client:
        guard = srv.app.state.service.capacity
        kit.wait_for(lambda: guard.cpu_share > settings.cpu_budget, timeout_s=10)
        assert client.post("/sessions", json={"name": "first"}, headers=kit.FLEET).status_code == 201


def test_probes_answer_on_their_own_port_as_on_the_service_port(kit, base_settings):
    settings = base_settings.model_copy(update={"instance_id": "probed", "probe_port": 0})
    with kit.running(settings) as srv, httpx.Client(timeout=10) as client:
        port = srv.app.state.service.probes.port
        assert port and port != srv.port
        for path in ("/health", "/ready"):
            own, main = client.get(f"http://127.0.0.1:{port}{path}"), client.get(f"{srv.url}{path}")
            assert own.status_code == main.status_code == 200
            assert own.json() == main.json() and own.headers["content-type"] == "application/json"
            for url in (f"http://127.0.0.1:{port}{path}", f"{srv.url}{path}"):  # HEAD: the same answer, no body
                head = client.head(url)
                assert head.status_code == 200 and head.content == b"", url
                assert int(head.headers["content-length"]) == len(client.get(url).content), url
        assert json.loads(client.get(f"http://127.0.0.1:{port}/ready").text)["ready"] is True
        assert client.get(f"http://127.0.0.1:{port}/sessions").status_code == 404


# ---- shedding in steps: newest first, back oldest first -------------------------------------------------------
def _guard(n: int) -> tuple[CapacityGuard, list[SimpleNamespace]]:
    """A guard over n stub sessions s0 (oldest) … s{n-1}, all streaming, with default thresholds."""
    sessions = [
        _Robot(id=f"s{i}", opened_at=float(i), last_activity=0.0, last_contact=0.0, last_seq=0) for i in range(n)
    ]
    return CapacityGuard(Settings(), ServiceMetrics(), lambda: sessions), sessions


def _update(guard: CapacityGuard, sessions: list[SimpleNamespace], now: float) -> None:
    """The robots not shed have just sent a block (a shed one's blocks are refused: it does not stream); then the
    guard decides."""
    shed = set(_shed_ids(guard, sessions))
    for s in sessions:
        if s.id not in shed:
            s.last_activity = now
    guard.update(now)


def _shed_ids(guard: CapacityGuard, sessions: list[SimpleNamespace]) -> list[str]:
    shed = []
    for s in sessions:
        try:
            guard.admit_block(s)  # type: ignore[arg-type]
        except AtCapacity:
            shed.append(s.id)
    return shed


def test_over_the_lag_limit_a_quarter_is_shed_per_step_newest_first_and_comes_back_oldest_first_in_smaller_steps():
    guard, sessions = _guard(8)
    # busy (loop over half its budget) and late beyond shed_lag_s: the process's own lag
    guard.cpu_share, guard.lag_s = 0.6, 2 * guard.settings.shed_lag_s
    _update(guard, sessions, 0.0)
    sessions[7].last_contact = sessions[7].last_activity = -100.0
    assert _shed_ids(guard, sessions) == ["s6", "s7"]  # a quarter of 8, the newest
    # refused, its robot was heard (the reaper leaves it alone) but did not stream (the guard does not count it)
    assert sessions[7].last_contact > 0 and sessions[7].last_activity == -100.0
    _update(guard, sessions, 0.1)  # within the step's interval: nothing more
    assert _shed_ids(guard, sessions) == ["s6", "s7"]
    _update(guard, sessions, SHED_EVERY_S)  # no worse than at the last step: its effect has not shown yet
    assert _shed_ids(guard, sessions) == ["s6", "s7"]
    guard.lag_s *= 1.5  # worse: the next step comes at once
    _update(guard, sessions, 2 * SHED_EVERY_S)
    assert _shed_ids(guard, sessions) == ["s4", "s5", "s6", "s7"]
    with pytest.raises(AtCapacity, match="refuses the blocks of 4 of its sessions"):
        guard.admit_session(len(sessions))  # no new session while any is shed
    _update(guard, sessions, 2 * SHED_EVERY_S + SETTLE_S / 2)  # still over, not worse: waits for SETTLE_S
    assert len(_shed_ids(guard, sessions)) == 4
    t = 2 * SHED_EVERY_S
    for _ in range(3):  # a quarter of those still served, at least one: s3, s2, then s1
        t += SETTLE_S
        _update(guard, sessions, t)
    assert _shed_ids(guard, sessions) == [f"s{i}" for i in range(1, 8)]  # never the oldest
    # caught up: a tenth (at least one) comes back every READMIT_EVERY_S, oldest first — smaller steps than
    # shedding, since each readmitted robot resends its backlog at once
    assert READMIT_SHARE < STEP_SHARE
    guard.lag_s = 0.0
    _update(guard, sessions, t + READMIT_EVERY_S / 2)
    assert len(_shed_ids(guard, sessions)) == 7
    _update(guard, sessions, t + READMIT_EVERY_S)
    assert _shed_ids(guard, sessions) == ["s2", "s3", "s4", "s5", "s6", "s7"]
    _update(guard, sessions, t + 2 * READMIT_EVERY_S)
    assert _shed_ids(guard, sessions) == ["s3", "s4", "s5", "s6", "s7"]
    # over again: the sessions readmitted since the process was last a full SETTLE_S within its limits (s1, s2) are
    # newcomers, and shed together
    guard.lag_s = 2 * guard.settings.shed_lag_s
    _update(guard, sessions, t + 2 * READMIT_EVERY_S + SHED_EVERY_S)
    assert _shed_ids(guard, sessions) == [f"s{i}" for i in range(1, 8)]
    with pytest.raises(AtCapacity, match="among its newest; send the newest frame later"):
        guard.admit_frame(sessions[2])  # type: ignore[arg-type]  # a shed session's frames wait with its blocks
    guard.admit_frame(sessions[0])  # type: ignore[arg-type]


def test_while_the_last_step_works_no_further_session_is_shed():
    """The measures lag what they measure: after a burst, the lag and queue delay stay over their limits for a
    second or more while they fall. Shedding on that old evidence would shed session after session, the oldest in
    the end; while the pressure falls, nothing more is shed."""
    guard, sessions = _guard(8)
    guard.cpu_share, guard.queue_s = 0.6, 40 * guard.settings.shed_queue_s  # a stall's windows: 2 s queued
    _update(guard, sessions, 0.0)
    assert _shed_ids(guard, sessions) == ["s6", "s7"]
    t = 0.0
    for _ in range(4):  # falling by more than a fifth each settling time, still over the limit
        t += SETTLE_S
        guard.queue_s *= 0.5
        _update(guard, sessions, t)
    assert guard.queue_s > guard.settings.shed_queue_s
    assert _shed_ids(guard, sessions) == ["s6", "s7"]
    t += SETTLE_S  # stuck at the same level: the next step
    _update(guard, sessions, t)
    assert _shed_ids(guard, sessions) == ["s4", "s5", "s6", "s7"]


def test_newcomers_are_shed_together_and_the_sessions_served_well_before_are_protected_for_a_while():
    """Robots that start together tip the process over together: the first step sheds every session that began
    streaming since the process was last a full SETTLE_S within its limits, not a quarter of them at a time. The
    sessions it served well before are not shed for PROTECT_S into the overload (the backlog the newcomers leave
    takes seconds to drain); past it, they may be (the machine itself may have slowed down)."""
    guard, sessions = _guard(8)
    for s in sessions[4:]:
        s.last_seq = -1  # s4 … s7 have not streamed yet
    guard.cpu_share = 0.3
    for t in (0.0, SETTLE_S / 2, SETTLE_S):
        _update(guard, sessions, t)  # within its limits for SETTLE_S: s0 … s3 stream
    for s in sessions[4:]:
        s.last_seq = 0
    guard.cpu_share, guard.lag_s = 0.6, 3 * guard.settings.shed_lag_s
    t = SETTLE_S + SAMPLE_EVERY_S
    _update(guard, sessions, t)
    assert _shed_ids(guard, sessions) == ["s4", "s5", "s6", "s7"]
    start = t
    while t < start + PROTECT_S - SETTLE_S:  # still over, no better: s1 … s3 stay
        t += SETTLE_S
        _update(guard, sessions, t)
    assert _shed_ids(guard, sessions) == ["s4", "s5", "s6", "s7"]
    _update(guard, sessions, start + PROTECT_S)
    assert _shed_ids(guard, sessions) == ["s3", "s4", "s5", "s6", "s7"]


def _served_well_then_over(n: int) -> tuple[CapacityGuard, list[SimpleNamespace], float]:
    """n sessions, all streaming within the limits for SETTLE_S (all served well), then the loop over its budget and
    late (not a queue): none is shed. Returns the guard, the sessions and the time of that update."""
    guard, sessions = _guard(n)
    guard.cpu_share = 0.3
    for t in (0.0, SETTLE_S / 2, SETTLE_S):
        _update(guard, sessions, t)
    guard.cpu_share, guard.lag_s = 0.6, 3 * guard.settings.shed_lag_s
    t = SETTLE_S + SAMPLE_EVERY_S
    _update(guard, sessions, t)
    assert _shed_ids(guard, sessions) == []
    return guard, sessions, t


def test_the_sessions_served_well_are_not_protected_once_their_own_windows_are_late_for_a_second():
    """Robots that ramp up together can look served well for a second and then overload the replica themselves:
    once the windows of the sessions still served have waited past twice shed_queue_s for SETTLE_S, the protection
    lapses."""
    guard, sessions, t = _served_well_then_over(8)
    guard.queue_s = 4 * guard.settings.shed_queue_s  # some session's windows late (and worse): but not theirs
    t += SHED_EVERY_S
    _update(guard, sessions, t)
    assert _shed_ids(guard, sessions) == []
    guard.protected_queue_s = guard.queue_s  # their own windows late: not yet a second
    guard.queue_s *= 1.5
    t += SHED_EVERY_S
    late = t
    _update(guard, sessions, t)
    assert _shed_ids(guard, sessions) == []
    while t < late + SETTLE_S:  # late all along, and no better: after SETTLE_S a step, newest first
        t += SAMPLE_EVERY_S
        _update(guard, sessions, t)
    assert _shed_ids(guard, sessions) == ["s6", "s7"]


def test_one_late_window_of_the_sessions_served_well_sheds_none_of_them():
    """On a machine shared with other processes the scheduler can park a pool thread: one of the protected sessions'
    windows waits 112 ms (past twice shed_queue_s), and 250 ms later they are on time again. Shedding a quarter of
    them for it cost each shed robot seconds (readmitted 2 s later, it resends its backlog at once; the hostile
    probe's well-behaved end-to-end p99 7.4 s); nothing is shed, and the episode ends."""
    guard, sessions = _guard(20)
    guard.cpu_share = 0.4
    for t in (0.0, SETTLE_S / 2, SETTLE_S):
        _update(guard, sessions, t)  # all twenty served well
    guard.cpu_share, guard.lag_s = 0.47, 0.011  # the hostile probe's run, at the sample that shed five of them
    guard.queue_s = guard.protected_queue_s = 0.112
    t += SAMPLE_EVERY_S
    _update(guard, sessions, t)
    assert _shed_ids(guard, sessions) == []
    guard.queue_s = guard.protected_queue_s = 0.085  # decaying: back under twice the limit
    for _ in range(int(2 * SETTLE_S / SAMPLE_EVERY_S)):
        t += SAMPLE_EVERY_S
        guard.queue_s = guard.protected_queue_s = 0.8 * guard.queue_s
        _update(guard, sessions, t)
    assert _shed_ids(guard, sessions) == []
    assert guard._over_since is None  # the overload episode is over


def test_windows_queued_past_the_limit_shed_the_newest_and_refuse_new_sessions_while_the_loop_is_punctual():
    """The loop keeps up with every block while the window pool, sharing its GIL, falls behind: the operators'
    views lag although the loop is punctual. The window queue delay sheds as the lag does, and says so."""
    guard, sessions = _guard(8)
    limit = guard.settings.shed_queue_s
    guard.cpu_share, guard.lag_s, guard.queue_s = 0.6, 0.0, 0.9 * limit  # busy, punctual, queue under the limit
    _update(guard, sessions, 0.0)
    assert _shed_ids(guard, sessions) == []
    with pytest.raises(AtCapacity, match=r"its windows wait \d+ ms for estimation"):
        guard.admit_session(len(sessions))  # above session_queue_s already: no new session
    guard.queue_s = 2 * limit
    _update(guard, sessions, 1.0)
    assert _shed_ids(guard, sessions) == ["s6", "s7"]
    with pytest.raises(AtCapacity, match=r"windows queued \d+ ms"):
        guard.admit_block(sessions[-1])  # type: ignore[arg-type]
    # under half the limit again: one step comes back after READMIT_EVERY_S, the older first
    guard.queue_s = 0.4 * limit
    _update(guard, sessions, 1.0 + READMIT_EVERY_S)
    assert _shed_ids(guard, sessions) == ["s7"]


def _ready_session(sid: str, opened_at: float, in_job: bool = False) -> SimpleNamespace:
    """A session stub as the batcher sees it: nothing pending (its job is None)."""
    return SimpleNamespace(
        id=sid,
        opened_at=opened_at,
        in_job=in_job,
        take_job=lambda max_windows=None: None,
        waiting_for_frame=lambda: False,
        waiting_for_taps=lambda: False,
    )


def test_the_batcher_reports_each_sessions_longest_wait_for_a_job_since_it_was_last_asked():
    """Ready sessions wait for a job; per session, the longest wait, still waiting or taken since the last call, is
    what admission reads (then the record starts again)."""
    from service.batcher import WindowBatcher

    batcher = WindowBatcher(ThreadPoolExecutor(1), max_jobs=1, spill_after_s=0)
    assert batcher.take_waits(time.monotonic()) == {}
    a = _ready_session("a", 0.0)
    b = _ready_session("b", 1.0, in_job=True)  # in a job: stays ready, its wait goes on
    batcher.notify(a)  # type: ignore[arg-type]
    t_a = time.monotonic()
    batcher.notify(b)  # type: ignore[arg-type]
    batcher.notify(a)  # type: ignore[arg-type]  # ready again before its job: it keeps its place and its time
    waits = batcher.take_waits(t_a + 0.5)  # both have waited about half a second (as of t_a + 0.5)
    assert waits.keys() == {"a", "b"} and 0.5 <= waits["a"] < 0.6 and 0.49 <= waits["b"] <= 0.5
    time.sleep(0.05)
    asyncio.run(batcher._gather())  # takes a (no job: nothing pending), leaves b
    waits = batcher.take_waits(t_a)
    assert 0.05 <= waits["a"] < 0.5  # a waited ≈ 0.05 s before it was taken
    assert waits["b"] <= 0.0  # b only since t_a
    assert batcher.take_waits(t_a).keys() == {"b"}  # the record restarted: a is served, b still waits


def test_the_batcher_serves_the_oldest_sessions_first():
    """A newer session's backlog does not queue ahead of an older session's windows."""
    from service.batcher import WindowBatcher

    batcher = WindowBatcher(ThreadPoolExecutor(1), max_jobs=1, spill_after_s=0, max_sessions_per_job=2)
    taken: list[str] = []
    sessions = [_ready_session(sid, opened) for sid, opened in (("new", 3.0), ("old", 1.0), ("mid", 2.0))]
    for s in sessions:
        # records the order; a job of one window
        s.take_job = lambda max_windows=None, sid=s.id: taken.append(sid) or SimpleNamespace(windows=1)
        batcher.notify(s)  # type: ignore[arg-type]  # ready in the order new, old, mid
    batch = asyncio.run(batcher._gather())
    assert taken == ["old", "mid"] == [s.id for s, _ in batch]  # the oldest two, whatever order they became ready in
    assert batcher.take_waits(time.monotonic()).keys() == {"old", "mid", "new"}


def test_a_job_holds_at_most_max_windows_per_job_windows_the_oldest_sessions_first():
    """A robot back from an outage resends seconds of blocks at once: a job takes only what fits its windows, so a
    pool thread is never held long by backlogs while the oldest sessions' windows wait for it."""
    from service.batcher import WindowBatcher

    batcher = WindowBatcher(
        ThreadPoolExecutor(1), max_jobs=1, spill_after_s=0, max_sessions_per_job=8, max_windows_per_job=3
    )
    asked: list[tuple[str, int | None]] = []
    for sid, opened in (("new", 3.0), ("old", 1.0), ("mid", 2.0)):
        s = _ready_session(sid, opened)
        # two windows pending each; a job takes at most what it is asked for
        s.take_job = lambda max_windows=None, sid=sid: (
            asked.append((sid, max_windows)) or SimpleNamespace(windows=min(2, max_windows or 2))
        )
        batcher.notify(s)  # type: ignore[arg-type]
    batch = asyncio.run(batcher._gather())
    assert asked == [("old", 3), ("mid", 1)] and [j.windows for _, j in batch] == [2, 1]


#: how long each job of _run_jobs holds its pool thread (s): long beside what a busy host adds to a timer or a thread
#: hand-off, so that "before a's job ended" and "after it" stay apart however busy the host is
HOLD_S = 1.0


def _run_jobs(monkeypatch, max_jobs: int, spill_after_s: float) -> list[tuple[str, float, float]]:
    """Two sessions, b ready just after a, each with one window, through a batcher whose jobs hold their thread
    for HOLD_S: (session id, seconds after b was ready its job started, seconds after a's job started), in the order
    the jobs started."""
    from service import batcher as batcher_module
    from service.batcher import WindowBatcher
    from service.pipeline import SessionResult

    started: list[tuple[str, float]] = []  # (session id, time.monotonic() its job started)
    ready_b = [0.0]

    def estimate(runtime, jobs):
        started.append((jobs[0].sid, time.monotonic()))
        time.sleep(HOLD_S)
        return [SessionResult([], job.windows, None) for job in jobs]

    monkeypatch.setattr(batcher_module, "estimate_batch", estimate)

    def stub(sid: str, opened_at: float) -> SimpleNamespace:
        jobs = [SimpleNamespace(sid=sid, windows=1)]

        async def apply_result(result):
            return None

        return SimpleNamespace(
            id=sid,
            opened_at=opened_at,
            in_job=False,
            runtime=None,
            take_job=lambda max_windows=None: jobs.pop() if jobs else None,
            has_work=lambda: bool(jobs),
            apply_result=apply_result,
            waiting_for_frame=lambda: False,
            waiting_for_taps=lambda: False,
        )

    async def scenario() -> None:
        batcher = WindowBatcher(ThreadPoolExecutor(2), max_jobs=max_jobs, spill_after_s=spill_after_s)
        batcher.start()
        batcher.notify(stub("a", 0.0))  # type: ignore[arg-type]
        while not started:  # a's job is running
            await asyncio.sleep(0.005)
        ready_b[0] = time.monotonic()
        batcher.notify(stub("b", 1.0))  # type: ignore[arg-type]
        deadline = time.monotonic() + 30  # a hang guard: both jobs start
        while len(started) < 2 and time.monotonic() < deadline:
            await asyncio.sleep(0.005)
        await batcher.close()

    asyncio.run(scenario())
    a_started = started[0][1]
    return [(sid, t - ready_b[0], t - a_started) for sid, t in started]


def test_a_second_job_starts_only_once_a_session_has_waited_spill_after_s(monkeypatch):
    """Two jobs at once slow each other down through the GIL: b's job waits for a's to end, unless b has waited
    spill_after_s, when the second thread takes it."""
    (a, _, _), (b, waited, into_a) = _run_jobs(monkeypatch, max_jobs=2, spill_after_s=0.1)
    assert (a, b) == ("a", "b") and waited >= 0.1 and into_a < HOLD_S  # spilled while a's job held its thread
    (_, _, _), (_, waited, into_a) = _run_jobs(monkeypatch, max_jobs=2, spill_after_s=0.0)
    assert waited < HOLD_S / 2 and into_a < HOLD_S  # 0: the free thread takes it at once, a's job still running
    (_, _, _), (_, _, into_a) = _run_jobs(monkeypatch, max_jobs=1, spill_after_s=0.0)
    assert into_a >= HOLD_S  # one thread: after a's job, whatever the spill


def test_queue_delays_leave_shed_sessions_out_and_hold_the_protected_sessions_apart():
    """The windows a shed session admitted before it was shed are served last; refusing more cannot shorten their
    wait, so it does not count. The protected sessions' own wait is held apart: the newcomers' windows may wait
    while theirs, served first, are on time."""
    waits: dict[str, float] = {}
    sessions = [SimpleNamespace(id=f"s{i}", opened_at=float(i), last_activity=0.0, last_seq=0) for i in range(6)]
    guard = CapacityGuard(Settings(), ServiceMetrics(), lambda: sessions, lambda now: dict(waits))
    guard._newest_within_limits = 2.0  # s0 … s2 served well before
    guard._shed = {"s5"}
    waits.update(s1=0.01, s4=0.3, s5=5.0)
    guard._hold_queue_delays(guard._window_waits(0.0), 1.0, 0.0)
    assert (guard.queue_s, guard.protected_queue_s) == (0.3, 0.01)
    waits.clear()
    waits.update(s0=0.002)
    guard._hold_queue_delays(guard._window_waits(0.0), 0.5, 0.0)  # the peaks decay, a new wait lower still
    assert (guard.queue_s, guard.protected_queue_s) == (0.15, 0.005)


@pytest.mark.parametrize("measure", ["lag_s", "queue_s"])
def test_lateness_that_is_not_the_processs_own_sheds_nothing(measure):
    """Timers run late, and a window pool falls behind, on a machine busy with other processes (this one mostly
    idle): refusing then would refuse the wrong thing."""
    guard, sessions = _guard(8)
    guard.cpu_share, guard.process_share = 0.1, 0.2
    setattr(guard, measure, 1.0)
    for t in (0.0, 0.25, 0.5):
        _update(guard, sessions, t)
    assert _shed_ids(guard, sessions) == []
    guard.admit_session(len(sessions))


def test_shed_robots_are_closed_4429_with_the_reason_and_come_back_oldest_first(
    kit, base_settings, library_dir, caplog
):
    """Real WebSockets: over capacity, every session but the oldest is closed 4429 (reason, Retry-After) on its next
    block; once the loop has caught up they stream again one step at a time, the older shed session first. What
    clients cause is never an ERROR, and no log line carries a token."""
    caplog.set_level(logging.INFO)
    blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_002", 2.0))
    # refusals answered at once (held in line: tests/service/test_service_readmission.py)
    settings = base_settings.model_copy(update={"instance_id": "shedding", "readmit_hold_s": 0})
    with kit.running(settings, cpu_meter=ThreadCpu()) as srv, httpx.Client(base_url=srv.url, timeout=10) as client:
        guard = srv.app.state.service.capacity
        sessions = [kit.create_session(client, f"robot{i}") for i in range(3)]
        sent = [0, 0, 0]

        def send(i: int, ws=None) -> int | str:
            """Send robot i's next block (on `ws`, or a fresh socket): the ack's seq, the close code and reason, or
            the refused handshake's status, Retry-After and detail."""
            try:
                with connect(kit.socket_url(srv, sessions[i], "ingest")) if ws is None else ws as ws:
                    ws.send(encode_binary(blocks[sent[i]]))
                    try:
                        ack = json.loads(ws.recv(timeout=10))
                    except ConnectionClosed as closed:
                        assert closed.rcvd is not None
                        return f"{closed.rcvd.code} {closed.rcvd.reason}"
            except InvalidStatus as refused:
                answer = refused.response
                return f"HTTP {answer.status_code} Retry-After {answer.headers['Retry-After']}: {answer.body.decode()}"
            sent[i] += 1
            return ack["seq"]

        for i in range(3):
            assert send(i) == 0  # all three stream
        open_socket = connect(kit.socket_url(srv, sessions[2], "ingest"))  # robot 2 is connected when it is shed
        guard.settings = settings.model_copy(update={"cpu_budget": 1e-6})  # over capacity from now on
        assert kit.wait_for(lambda: guard.shedding == 2, timeout_s=10)
        closed = send(2, open_socket)  # its next block: closed 4429, with the reason
        assert isinstance(closed, str) and closed.startswith("4429") and "Retry-After" in closed
        for i in (1, 2):  # reconnecting: refused at the handshake, before the upgrade, with when to come back
            refused = send(i)
            # robot 2 after robot 1, which is older and comes back first: a step (one session) later
            assert (
                isinstance(refused, str)
                and refused.startswith(f"HTTP 429 Retry-After {2 * i}:")
                and "newest" in refused
            )
        assert send(0) == 1  # the oldest streams on
        guard.settings = settings.model_copy(update={"cpu_budget": 1.0})  # caught up
        kit.wait_for(lambda: guard.shedding == 1, timeout_s=10)
        assert send(1) == 1 and isinstance(send(2), str)  # the older shed session is back first
        kit.wait_for(lambda: guard.shedding == 0, timeout_s=10)
        assert send(2) == 1
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert "at capacity" in caplog.text  # one WARNING says why
    assert not any(s[key] in caplog.text for s in sessions for key in ("robot_token", "operator_token"))


# ---- probes answered before routing ------------------------------------------------------------------------------
def test_probes_and_session_reads_answer_while_every_worker_thread_is_held(kit, base_settings):
    """FastAPI runs plain-`def` dependencies and routes in anyio's thread pool (40 threads): with every one of them
    held by a deliberately slow handler, /health and /ready (answered before routing) and a session's status (only
    `async` dependencies) still answer, while one more request needing a worker thread waits."""
    release, entered = threading.Event(), threading.Semaphore(0)
    held: list[int] = []

    def slow() -> dict:  # a plain def: FastAPI runs it on a worker thread
        held.append(1)
        entered.release()
        release.wait(30)
        return {}

    server = kit.ServerThread(base_settings.model_copy(update={"instance_id": "held"}))
    server.app.add_api_route("/slow", slow)
    server.start()
    pool = ThreadPoolExecutor(WORKER_THREADS + 1)
    waiting: list[Future] = []
    try:
        with httpx.Client(base_url=server.url, timeout=10) as client:
            session = kit.create_session(client, "reader")
            waiting += [pool.submit(httpx.get, f"{server.url}/slow", timeout=60) for _ in range(WORKER_THREADS + 1)]
            for _ in range(WORKER_THREADS):
                assert entered.acquire(timeout=30)
            assert client.get("/health").json() == {"status": "ok", "instance": "held"}
            assert client.get("/ready").json()["ready"] is True
            assert kit.session_status(client, session)["session_id"] == session["session_id"]
            assert len(held) == WORKER_THREADS  # the pool was full all along: one more request still waits for it
    finally:
        release.set()
        for future in waiting:
            assert future.result(timeout=60).status_code == 200
        pool.shutdown()
        server.stop()


def test_readmitted_sessions_are_newcomers_until_protect_s_has_passed():
    """A readmitted robot resends its backlog at once: a second within the limits before it says nothing of how it
    is served. Until PROTECT_S after its readmission it is a newcomer: shed with the others, and its windows' wait is
    not the protected sessions' wait."""
    guard, sessions = _guard(4)
    guard.cpu_share = 0.3
    guard._shed = {"s3"}
    guard._readmit_oldest(guard.streaming(0.0), 0.0)  # s3 streams again
    for t in (0.0, SETTLE_S / 2, SETTLE_S):
        _update(guard, sessions, t)  # all four stream within the limits for SETTLE_S
    assert guard._newest_within_limits == 3.0
    assert [guard._served_well(s, SETTLE_S) for s in sessions] == [True, True, True, False]
    assert [guard._served_well(s, PROTECT_S) for s in sessions] == [True] * 4
    guard._window_waits = lambda now: {"s1": 0.01, "s3": 1.0}
    guard._hold_queue_delays(guard._window_waits(SETTLE_S), 1.0, SETTLE_S)
    assert (guard.queue_s, guard.protected_queue_s) == (1.0, 0.01)
    guard.cpu_share = 0.6  # over: the backlog of s3 tipped it over; s1 and s2 stay protected
    _update(guard, sessions, SETTLE_S + SAMPLE_EVERY_S)
    assert _shed_ids(guard, sessions) == ["s3"]


def _retry_after(guard: CapacityGuard, session: SimpleNamespace) -> float:
    """The Retry-After (s) of the refusal of `session`'s next block."""
    with pytest.raises(AtCapacity) as refused:
        guard.admit_block(session)  # type: ignore[arg-type]
    return float(refused.value.headers["Retry-After"])


def test_a_refused_robot_is_told_to_come_back_after_the_steps_that_readmit_those_older_than_it():
    """Room comes back oldest first, a step at a time: 150 robots refused together and all told 2 s would come back
    together every 2–3 s, a wave of refused handshakes each time. Each is told RETRY_AFTER_S more for every step of
    refused sessions older than it, up to MAX_RETRY_AFTER_S: the shed ones, and those waiting to start."""
    sessions = [_Robot(id=f"s{i}", opened_at=float(i), last_activity=0.0, last_seq=0) for i in range(40)]
    guard = CapacityGuard(Settings(), ServiceMetrics(), lambda: sessions)
    _update(guard, sessions[:10], 5.0)  # ten stream within the limits: a readmission step is one session
    guard._shed = {s.id for s in sessions[10:30]}
    assert [_retry_after(guard, s) for s in sessions[10:16]] == [
        RETRY_AFTER_S * k for k in (1, 2, 3, 4, MAX_RETRY_AFTER_S / RETRY_AFTER_S, MAX_RETRY_AFTER_S / RETRY_AFTER_S)
    ]
    guard._shed = {s.id for s in sessions[10:12]}
    for s in sessions[12:]:
        s.last_seq = -1  # not streamed yet: they wait to start
    guard.queue_s = 4 * guard.settings.session_queue_s
    guard.cpu_share = 0.6  # busy, its windows late: no room to start
    assert _retry_after(guard, sessions[12]) == 3 * RETRY_AFTER_S  # behind the two shed
    assert _retry_after(guard, sessions[13]) == 4 * RETRY_AFTER_S  # and the one refused a start before it
    assert _retry_after(guard, sessions[11]) == 2 * RETRY_AFTER_S  # older than those waiting: behind one


def test_after_a_flood_readmission_steps_are_a_tenth_of_the_sessions_served_not_of_those_shed():
    """150 shed beside 20 served: a step of a tenth of all would readmit 17 robots, each resending its backlog at
    once — more than the process serves, and it tips over again; a tenth of those served readmits 2."""
    guard, sessions = _guard(170)
    guard._shed = {s.id for s in sessions[20:]}
    _update(guard, sessions, 0.0)  # calm: a step comes back
    assert _shed_ids(guard, sessions) == [f"s{i}" for i in range(22, 170)]


def test_the_protected_sessions_own_windows_may_wait_up_to_twice_the_limit_and_stay_served_well_once_shed():
    """Load that shedding them cannot remove (a flood of requests, the newcomers' refusals) also delays the protected
    sessions' windows: only a wait well over the limit lifts their protection. And a served-well session shed since
    (so not streaming now) was served well all the same: the boundary does not move back."""
    guard, sessions = _guard(8)
    for s in sessions[4:]:
        s.last_seq = -1
    guard.cpu_share = 0.3
    for t in (0.0, SETTLE_S / 2, SETTLE_S):
        _update(guard, sessions, t)  # s0 … s3 served well
    for s in sessions[4:]:
        s.last_seq = 0
    guard.cpu_share, guard.lag_s = 0.6, 3 * guard.settings.shed_lag_s
    guard.protected_queue_s = 1.5 * guard.settings.shed_queue_s
    _update(guard, sessions, SETTLE_S + SAMPLE_EVERY_S)
    assert _shed_ids(guard, sessions) == ["s4", "s5", "s6", "s7"]  # the newcomers only
    guard._shed.add("s3")  # say s3 was shed as well, then the process is calm for a while
    guard.cpu_share, guard.lag_s, guard.protected_queue_s = 0.3, 0.0, 0.0
    for t in (3.0, 3.5, 4.0, 4.5):
        _update(guard, sessions, t)
    assert guard._newest_within_limits == 3.0  # s3 does not stream, yet was served well


def test_the_sampler_publishes_both_queue_delays_as_gauges():
    """Ops see the protected sessions' own queue delay beside everybody's (the one the protection reads)."""
    sessions = [SimpleNamespace(id=f"s{i}", opened_at=float(i), last_activity=0.0, last_seq=-1) for i in range(3)]
    metrics = ServiceMetrics()
    guard = CapacityGuard(Settings(), metrics, lambda: sessions, lambda now: {"s0": 0.02, "s2": 0.3})
    guard._newest_within_limits = 1.0  # s0 and s1 served well

    async def main():
        guard.start()
        await asyncio.sleep(3 * SAMPLE_EVERY_S)
        await guard.close()

    asyncio.run(main())
    read = metrics.registry.get_sample_value
    assert read("hapticlink_window_queue_seconds") == pytest.approx(0.3, rel=0.1)
    assert read("hapticlink_protected_window_queue_seconds") == pytest.approx(0.02, rel=0.1)


class _Robot(SimpleNamespace):
    """A stub session with Session's touch() and heard()."""

    def touch(self) -> None:
        self.last_activity = self.last_contact = time.monotonic()

    def heard(self) -> None:
        self.last_contact = time.monotonic()


def _waiting(name: str, opened_at: float) -> _Robot:
    """A session opened at `opened_at` (time.monotonic()) whose robot has sent nothing yet."""
    return _Robot(id=name, opened_at=opened_at, last_activity=opened_at, last_contact=opened_at, last_seq=-1)


def test_sessions_opened_and_not_streaming_yet_count_as_load_when_a_session_is_asked_for():
    """Robots that start together open their sessions within a second, before any streams: each asks while the
    measures show none of the others' load. Those opened within STARTING_WITHIN_S, beyond the first
    STARTING_UNCOUNTED, count as streaming."""
    guard, sessions = _guard(8)
    now = time.monotonic()
    guard.cpu_share = 0.41  # 0.05125 a session: 0.41 + 8 more fits the budget of 0.85, 9 more does not
    _update(guard, sessions, now)
    for i in range(STARTING_UNCOUNTED + 8):
        guard.admit_session(len(sessions))
        sessions.append(_waiting(f"new{i}", time.monotonic()))
    with pytest.raises(AtCapacity, match=r"with 8 session\(s\) admitted and not measured yet"):
        guard.admit_session(len(sessions))
    for s in sessions[8:]:  # opened long enough ago and never streamed: no longer counted (nor holding admission)
        s.opened_at -= STARTING_WITHIN_S
    guard.admit_session(len(sessions))


def test_a_robot_that_has_not_streamed_starts_only_while_there_is_room_its_frames_waiting_with_it():
    """Sessions opened earlier may start streaming together (150 robots at once stalled the loop for 200 ms). A robot
    that has not streamed starts (its ingest socket, its first block) only while one more streaming session would be
    served well; refused, its robot is there (not an abandoned session), and its frames wait with it. Once it
    starts, its load is not taken for measured until STARTING_WITHIN_S has passed."""
    guard, sessions = _guard(8)
    now = time.monotonic()
    guard.cpu_share = guard.process_share = 0.8  # 0.1 a session: one more would take the loop over its budget of 0.85
    _update(guard, sessions, now)
    robot = _waiting("w", now - 60)
    sessions.append(robot)
    with pytest.raises(AtCapacity, match=r"has not streamed yet: it starts when there is room") as refused:
        guard.admit_block(robot)  # type: ignore[arg-type]
    assert "one more session (0.100 of a core each)" in str(refused.value)
    assert robot.last_contact > now - 1  # heard: the reaper counts from its robot's last try
    with pytest.raises(AtCapacity, match="its frames wait with its first block"):
        guard.admit_frame(robot)  # type: ignore[arg-type]
    guard.cpu_share = 0.4  # the loop has room, its threads together do not (0.1 a session)
    _update(guard, sessions, now + SAMPLE_EVERY_S)
    with pytest.raises(AtCapacity, match=r"would take its threads together over the budget of 0.85 \(now 0.80\)"):
        guard.admit_block(robot)  # type: ignore[arg-type]
    guard.process_share = 0.6
    _update(guard, sessions, now + SAMPLE_EVERY_S)
    guard.admit_frame(robot)  # type: ignore[arg-type]
    guard.admit_block(robot)  # type: ignore[arg-type]
    robot.last_seq = 0  # it streams; its load is not in the smoothed share yet: the cost per session holds
    _update(guard, sessions, now + 2 * SAMPLE_EVERY_S)
    assert guard.cpu_per_session == pytest.approx(0.4 / 8)
    _update(guard, sessions, now + STARTING_WITHIN_S + SAMPLE_EVERY_S)  # measured since
    assert guard.cpu_per_session == pytest.approx(0.4 / 9)
