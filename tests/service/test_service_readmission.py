"""Readmission without polling: a robot refused for capacity (its session shed, or no room yet for its start) waits in
line, its credential checked first, costing no CPU, one wait per session, and is let in the moment its turn comes, in
the order the robots came; a robot whose own session is saturated keeps its connection while the pool drains it.
Nothing acknowledged is lost.

Real uvicorn on loopback and real WebSocket clients where a robot meets it; the capacity meter is the service's own
(`ThreadCpu()`) with the load set through `cpu_budget`, so the test, not the host's idleness, decides when capacity
goes and returns. The guard's line with stub sessions, as tests/service/test_service_admission.py does."""

from __future__ import annotations

import asyncio
import json
import threading
import time
from types import SimpleNamespace

import httpx
import pytest
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from drivers.blocks import encode_binary
from drivers.protocol import Close
from drivers.robot import RobotClient
from service.capacity import HELD_RETRY_AFTER_S, SAMPLE_EVERY_S, AtCapacity, CapacityGuard
from service.metrics import ServiceMetrics
from service.settings import Settings
from service.thread_cpu import ThreadCpu


class _Robot(SimpleNamespace):
    """A stub session with Session's heard()."""

    def heard(self) -> None:
        self.last_contact = time.monotonic()


def _waiting(name: str, opened_at: float) -> _Robot:
    """A session opened at `opened_at` (time.monotonic()) whose robot has sent nothing yet."""
    return _Robot(id=name, opened_at=opened_at, last_activity=opened_at, last_contact=opened_at, last_seq=-1)


def _guard(n: int) -> tuple[CapacityGuard, list[_Robot]]:
    """A guard over n stub sessions s0 (oldest) … s{n-1}, all streaming, with default thresholds."""
    sessions = [
        _Robot(id=f"s{i}", opened_at=float(i), last_activity=0.0, last_contact=0.0, last_seq=0) for i in range(n)
    ]
    return CapacityGuard(Settings(), ServiceMetrics(), lambda: sessions), sessions


def _update(guard: CapacityGuard, sessions: list[_Robot], now: float) -> None:
    """The robots that streamed have just sent a block; then the guard decides."""
    for s in sessions:
        if s.last_seq >= 0 and s.id not in guard._shed:
            s.last_activity = now
    guard.update(now)


class HeldRobot(threading.Thread):
    """A robot that opens its ingest socket once (a long handshake timeout: it never polls) and, once in, sends its
    next blocks; records when its handshake completed and every acknowledgement."""

    def __init__(self, url: str, payloads: list[bytes], done: list[str]) -> None:
        super().__init__(daemon=True)
        self.url, self.payloads, self.done = url, payloads, done
        self.acks: list[dict] = []
        self.in_at: float | None = None
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            with connect(self.url, open_timeout=60) as ws:
                self.in_at = time.monotonic()
                self.done.append(self.name)
                for payload in self.payloads:
                    ws.send(payload)
                    self.acks.append(json.loads(ws.recv(timeout=30)))
        except BaseException as exc:  # noqa: BLE001 - reported by the test
            self.error = exc


def test_shed_robots_wait_in_line_on_one_connection_and_are_let_in_in_arrival_order_when_capacity_returns(
    kit, base_settings, library_dir
):
    """Over capacity the newest robots are shed; reconnecting, each is held at the handshake (its token accepted
    first) instead of answered 429 — no retry, no Retry-After to sit out. When capacity returns (the test sets the
    budget: the host's idleness decides nothing) they are let in one readmission step at a time in the order they
    came, each on its first connection, and every block sent is acknowledged and estimated: nothing is lost."""
    blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_002", 2.0))
    settings = base_settings.model_copy(update={"instance_id": "held", "readmit_hold_s": 30.0})
    with kit.running(settings, cpu_meter=ThreadCpu()) as srv, httpx.Client(base_url=srv.url, timeout=10) as client:
        guard, sessions = kit.overload(client, srv, settings, blocks[0], robots=3)  # all three stream, then too many
        assert kit.wait_for(lambda: guard.shedding == 2, timeout_s=10)
        # a wrong token is refused at once, never held: the credential comes first
        bad = kit.socket_url(srv, sessions[1], "ingest").replace(sessions[1]["robot_token"], "x" * 43)
        with connect(bad, open_timeout=10) as ws, pytest.raises(ConnectionClosed):  # not held 30 s: refused now
            ws.recv(timeout=10)
        assert ws.close_code == Close.POLICY
        done: list[str] = []
        robots = {}
        for i in (1, 2):  # robot 1 came first (older session), robot 2 after it
            robots[i] = HeldRobot(
                kit.socket_url(srv, sessions[i], "ingest"), [encode_binary(b) for b in blocks[1:]], done
            )
            robots[i].name = f"robot{i}"
            robots[i].start()
            assert kit.wait_for(lambda i=i: sessions[i]["session_id"] in guard._held, timeout_s=10)
        assert "hapticlink_robots_held 2.0" in client.get("/metrics", headers=kit.SCRAPER).text
        time.sleep(3 * SAMPLE_EVERY_S)  # over capacity, nobody is let in
        assert done == [] and all(r.error is None for r in robots.values())
        guard.settings = settings.model_copy(update={"cpu_budget": 1.0})  # capacity returns
        for r in robots.values():
            r.join(timeout=60)
        assert [r.error for r in robots.values()] == [None, None]
        assert done == ["robot1", "robot2"]  # in the order they came, each on its one held connection
        for r in robots.values():
            assert [a["seq"] for a in r.acks] == [b.seq for b in blocks[1:]] and all(a["ok"] for a in r.acks)
        # each robot's wait from its readmission to its next block accepted is measured
        metrics = client.get("/metrics", headers=kit.SCRAPER).text
        assert "hapticlink_readmit_seconds_count 2.0" in metrics
        assert "hapticlink_robots_held 0.0" in metrics
        # nothing acknowledged was lost: every block's windows are estimated (2 s of blocks: 4 windows a session)
        for s in sessions[1:]:
            status = kit.wait_for(lambda s=s: (st := kit.session_status(client, s))["counters"]["windows"] >= 4 and st)
            assert status["counters"]["windows"] == 4 and status["last_seq"] == blocks[-1].seq
            assert status["counters"]["blocks_refused"] == 0


def test_a_robot_held_past_readmit_hold_s_is_told_to_come_back_soon_and_keeps_its_place(
    kit, base_settings, library_dir
):
    """No room within the hold: 429 with a short Retry-After (its place is kept, coming back costs a handshake)."""
    blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_002", 1.0))
    settings = base_settings.model_copy(update={"instance_id": "held-out", "readmit_hold_s": 0.5})
    with kit.running(settings, cpu_meter=ThreadCpu()) as srv, httpx.Client(base_url=srv.url, timeout=10) as client:
        guard, sessions = kit.overload(client, srv, settings, blocks[0], robots=2)
        assert kit.wait_for(lambda: guard.shedding == 1, timeout_s=10)
        with pytest.raises(InvalidStatus) as refused:
            connect(kit.socket_url(srv, sessions[1], "ingest"), open_timeout=30)
        answer = refused.value.response
        assert answer.status_code == 429 and float(answer.headers["Retry-After"]) == HELD_RETRY_AFTER_S
        assert "held 0.5 s in line" in answer.body.decode()
        r = kit.post_block(client, sessions[1], blocks[1])  # HTTP blocks wait in the same line
        assert r.status_code == 429 and float(r.headers["retry-after"]) == HELD_RETRY_AFTER_S
        assert kit.session_status(client, sessions[1])["last_seq"] == blocks[0].seq  # nothing of it was taken


# ---- the line, with stub sessions ----------------------------------------------------------------------------------
def test_robots_refused_a_start_are_granted_room_in_the_order_they_came_and_newcomers_queue_behind_them():
    """Room goes to the robots refused a start in the order they were first refused (not the order their sessions
    were opened); a robot that has not asked yet does not pass them, room or not; one granted while away between tries
    starts when it is back."""
    guard, sessions = _guard(8)
    now = time.monotonic()
    guard.cpu_share = guard.process_share = 0.8  # 0.1 a session: no room for one more
    _update(guard, sessions, now)
    late, early, newcomer = _waiting("late", now - 30), _waiting("early", now - 10), _waiting("new", now - 60)
    sessions += [late, early, newcomer]
    for robot in (early, late):  # early asks first, though its session was opened after late's
        with pytest.raises(AtCapacity, match="has not streamed yet"):
            guard.admit_block(robot)  # type: ignore[arg-type]
    assert list(guard._line) == ["early", "late"]
    guard.cpu_share = guard.process_share = 0.5  # room again
    with pytest.raises(AtCapacity, match=r"2 robot\(s\) refused a start before this one start first"):
        guard.admit_block(newcomer)  # type: ignore[arg-type]  # the opened longest ago, it still queues behind them
    with pytest.raises(AtCapacity, match=r"1 robot\(s\) refused a start before this one start first"):
        guard.admit_block(late)  # type: ignore[arg-type]  # early came first
    assert list(guard._line) == ["early", "late", "new"]
    _update(guard, sessions, now + SAMPLE_EVERY_S)  # the next sample grants room in the line's order
    assert list(guard._line) == [] and list(guard._granted) == ["early", "late", "new"]
    for robot in (late, newcomer, early):  # away between tries when granted: each starts when it is back
        guard.admit_block(robot)  # type: ignore[arg-type]
    assert guard._granted == {} and {"early", "late", "new"} <= guard._started.keys()


def test_a_held_robot_is_let_in_the_moment_its_turn_comes_and_a_newer_connection_takes_its_place():
    """`hold` waits on an event (no polling) and returns when the guard grants the robot room; a second connection of
    the same session takes the first's place (the first answered 429 at once): the line holds at most one connection
    per session."""

    async def main() -> None:
        guard, sessions = _guard(8)
        now = time.monotonic()
        guard.cpu_share = guard.process_share = 0.8
        _update(guard, sessions, now)
        robot = _waiting("w", now - 5)
        sessions.append(robot)
        first = asyncio.create_task(guard.hold(robot, 60))  # type: ignore[arg-type]
        await asyncio.sleep(0.05)
        assert not first.done() and "w" in guard._held
        second = asyncio.create_task(guard.hold(robot, 60))  # type: ignore[arg-type]
        await asyncio.sleep(0.05)
        assert first.done() and isinstance(first.exception(), AtCapacity)
        assert "a newer connection of session w waits in this one's place" in str(first.exception())
        assert not second.done() and len(guard._held) == 1
        guard.cpu_share = guard.process_share = 0.5  # room: the next sample grants it
        _update(guard, sessions, now + SAMPLE_EVERY_S)
        await asyncio.wait_for(second, 5)  # let in, no retry
        assert guard._held == {} and "w" in guard._started and "w" not in guard._granted

    asyncio.run(main())


def test_a_held_robot_is_answered_at_once_when_the_replica_shuts_down():
    async def main() -> None:
        guard = CapacityGuard(Settings(), ServiceMetrics(), lambda: sessions)
        sessions = [_waiting(f"s{i}", time.monotonic()) for i in range(2)]
        guard._shed.add("s1")
        held = asyncio.create_task(guard.hold(sessions[1], 60))  # type: ignore[arg-type]
        await asyncio.sleep(0.05)
        assert not held.done()
        guard.release_held()
        await asyncio.wait_for(held, 5)  # the route's next check (shutting down: 503) answers it

    asyncio.run(main())


# ---- a saturated session keeps its connection ----------------------------------------------------------------------
def test_a_robot_whose_session_is_saturated_keeps_its_socket_and_its_blocks_wait_for_the_pool(
    kit, base_settings, library_dir
):
    """The session's own backlog of windows is full (its pool thread held, as a slow CPU would): the socket is not
    closed 4429; the next block waits, unread, and is acknowledged once the pool drains the backlog. Every block is
    acknowledged once and every window estimated."""
    settings = base_settings.model_copy(
        update={
            "instance_id": "saturated-held",
            "pool_threads": 1,
            "session_queue_windows": 2,
            "max_block_windows": 1,
            "readmit_hold_s": 30.0,
        }
    )
    blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_002", 2.0))  # 100 blocks, 4 windows
    with kit.running(settings) as srv, httpx.Client(base_url=srv.url, timeout=10) as client:
        session = kit.create_session(client)
        stall = kit.PoolStall(srv)
        acks: list[dict] = []
        with connect(kit.socket_url(srv, session, "ingest")) as ws:
            for block in blocks:
                ws.send(encode_binary(block))
                if len(acks) < 50:  # 50 blocks of 20 ms complete the 2 windows the backlog holds
                    acks.append(json.loads(ws.recv(timeout=10)))
            with pytest.raises(TimeoutError):
                ws.recv(timeout=0.5)  # the next block waits, unread: not refused, and the socket is not closed
            assert kit.session_status(client, session)["state"] == "saturated"
            stall.release.set()
            stall.future.result(timeout=10)
            while len(acks) < len(blocks):
                acks.append(json.loads(ws.recv(timeout=30)))
        assert [a["seq"] for a in acks] == [b.seq for b in blocks] and all(a["ok"] and not a["duplicate"] for a in acks)
        status = kit.wait_for(lambda: (s := kit.session_status(client, session))["counters"]["windows"] >= 4 and s)
        assert status["counters"]["windows"] == 4 and status["counters"]["blocks_refused"] == 0


@pytest.mark.parametrize("transport", ["ws", "http"])
def test_the_robot_client_waits_out_a_saturated_session_on_its_connection_and_loses_nothing(
    kit, base_settings, library_dir, transport
):
    """`hapticlink robot`'s client against a session saturated by its own backlog (its pool thread held): it is
    never told to go away — no 429, no close 4429, no reconnect — and every block is acknowledged and estimated."""
    settings = base_settings.model_copy(
        update={
            "instance_id": f"saturated-client-{transport}",
            "pool_threads": 1,
            "session_queue_windows": 2,
            "max_block_windows": 1,
            "readmit_hold_s": 30.0,
        }
    )
    blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_004", 3.0))
    with kit.running(settings) as srv:
        sessions = srv.app.state.service.sessions

        async def main():
            robot = RobotClient(
                srv.url, kit.BlockList(blocks), transport=transport, backoff=(0.05, 0.2), seed=1, api_key=kit.API_KEY
            )
            stall = kit.PoolStall(srv)

            def saturated() -> bool:
                s = sessions.get(robot.session.session_id) if robot.session is not None else None
                return s is not None and s.saturated()

            # held until the session is saturated, and half a second of its robot waiting more
            spell = asyncio.create_task(stall.release_when(saturated))
            stats = await robot.run()
            await spell
            return robot, stats

        robot, stats = asyncio.run(main())
        assert stats.saturated == 0 and stats.reconnects == 0
        assert stats.acked == len(blocks) and stats.lost == 0 and stats.rejected == 0 and stats.unsent == 0
        session = kit.robot_session(robot)
        with httpx.Client(base_url=srv.url, timeout=10) as client:
            status = kit.wait_for(lambda: (s := kit.session_status(client, session))["counters"]["windows"] >= 6 and s)
        assert status["counters"]["windows"] == 6 and status["counters"]["blocks_refused"] == 0


# ---- fairness: no admitted robot starves behind the older ones -----------------------------------------------------
def test_the_batcher_serves_a_session_whose_windows_waited_starving_s_before_the_older_sessions():
    """Oldest first while the pool keeps up; a session whose windows have waited STARVING_S goes first (the
    longest-waiting first), so a crowd's newest robots are not left without windows while the older ones are served
    every hop."""
    from concurrent.futures import ThreadPoolExecutor

    from service.batcher import STARVING_S, WindowBatcher

    batcher = WindowBatcher(ThreadPoolExecutor(1), max_jobs=1, spill_after_s=0, max_sessions_per_job=2)
    taken: list[str] = []
    now = time.monotonic()
    for sid, opened, waited in (("old", 1.0, 0.0), ("mid", 2.0, 0.1), ("new", 3.0, STARVING_S + 0.5)):
        s = SimpleNamespace(id=sid, opened_at=opened, in_job=False)
        s.take_job = lambda max_windows=None, sid=sid: taken.append(sid) or SimpleNamespace(windows=1)
        batcher._ready[sid] = (s, now - waited)  # type: ignore[assignment]  # ready since `waited` seconds
    asyncio.run(batcher._gather())
    assert taken == ["new", "old"]  # the starving one, then the oldest
    taken.clear()
    for sid in ("old", "new"):  # back, ready again now; mid still waits
        s = SimpleNamespace(id=sid, opened_at={"old": 1.0, "new": 3.0}[sid], in_job=False)
        s.take_job = lambda max_windows=None, sid=sid: taken.append(sid) or SimpleNamespace(windows=1)
        batcher._ready[sid] = (s, time.monotonic())  # type: ignore[assignment]
    asyncio.run(batcher._gather())
    assert taken == ["old", "mid"]  # nobody starving: oldest first again
