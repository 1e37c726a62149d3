"""RobotClient against a fake service on loopback (uvicorn + Starlette), real httpx/websockets clients."""

from __future__ import annotations

import asyncio
import logging
import random
import socket

import numpy as np
import pytest

from drivers.blocks import Frame
from drivers.robot import (
    Backoff,
    Pending,
    ResendBuffer,
    RobotAuthError,
    RobotClient,
    ServiceRefused,
    ServiceUnavailable,
    SessionLostError,
)
from drivers.source import blocks_from_arrays

FAST = {"backoff": (0.01, 0.05), "seed": 7}
TRANSPORTS = [
    pytest.param("ws", True, id="ws-binary"),
    pytest.param("ws", False, id="ws-json"),
    pytest.param("http", True, id="http-binary"),
    pytest.param("http", False, id="http-json"),
]


async def _wait_until(predicate, timeout_s: float = 10.0) -> None:
    """Poll until predicate() holds (a hang guard, not a timing assertion)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while not predicate():
        if loop.time() > deadline:
            raise AssertionError("condition not reached within the hang guard")
        await asyncio.sleep(0.005)


def _assert_exactly_once(kit, sess, arrays, n_blocks: int) -> None:
    seqs = [b.seq for b in sess.accepted]
    assert seqs == list(range(n_blocks)), "every block accepted once, in order"
    for kind, (data, _, units) in arrays.items():
        np.testing.assert_array_equal(kit.concat(sess.accepted, kind), data)
        assert {b.channels[kind].units for b in sess.accepted} == {units}


@pytest.mark.parametrize("transport, binary", TRANSPORTS)
def test_every_sample_arrives_once_and_in_order_across_outages(kit, fake_service, transport, binary):
    arrays = kit.stroke_arrays(6000, seed=1)  # 6 s at 1 kHz → 300 blocks of 20 ms
    blocks = list(blocks_from_arrays(arrays, 0.02))
    source = kit.ListSource(blocks)
    fake_service.saturate = 2  # 429 (HTTP) / close 4429 (WS) twice
    fake_service.fail_after_accept = {10, 120}  # processed, but the acknowledgement never arrives
    fake_service.fail_at = {60: [503, 421, 503]}  # outage, another replica, outage: block 60 is retried, not dropped
    fake_service.ws_kill_every = 97 if transport == "ws" else 0
    server = kit.LoopbackServer(fake_service.app)
    restarts = []

    def on_accept(seq: int) -> None:
        if seq == 200 and not restarts:  # a full outage mid-stream: the server goes away for a while
            restarts.append(server.restart_soon(0.3))

    fake_service.on_accept = on_accept

    async def main():
        await server.start()
        try:
            client = RobotClient(server.url, source, transport=transport, binary=binary, **FAST)
            stats = await client.run()
            await asyncio.gather(*restarts)
            return client, stats
        finally:
            await server.stop()

    _, stats = asyncio.run(main())
    sess = fake_service.only_session()
    _assert_exactly_once(kit, sess, arrays, len(blocks))
    assert restarts, "the outage happened"
    assert stats.read == stats.acked == len(blocks)
    assert stats.lost == stats.unsent == stats.rejected == 0
    assert stats.saturated == 2
    assert stats.reconnects >= 2 and stats.resent >= 2
    assert stats.duplicates >= 2  # the blocks whose acknowledgement was lost came back as duplicates
    assert sess.deliveries[10] == 2 and sess.deliveries[120] >= 2
    assert source.closed


def test_a_robot_refused_at_the_handshake_waits_the_retry_after_the_service_gives(kit, fake_service):
    """A replica that sheds a session refuses its ingest handshake with 429 and Retry-After; the robot waits that
    long before it tries again (its own backoff is far shorter here), then delivers everything."""
    blocks = list(blocks_from_arrays(kit.stroke_arrays(500, seed=3), 0.02))
    fake_service.shed_handshakes = 2
    stats = kit.stream(fake_service.app, blocks, transport="ws", **FAST)
    waits = [b - a for a, b in zip(fake_service.handshakes, fake_service.handshakes[1:])]
    assert stats.saturated == 2 and stats.acked == len(blocks)
    assert len(waits) >= 2 and min(waits[:2]) >= 0.3  # Retry-After, not the 10–50 ms backoff


@pytest.mark.parametrize("transport", ["ws", "http"])
def test_frames_wait_until_the_service_takes_the_robots_blocks(kit, fake_service, transport):
    """A replica that has not let a session start, or sheds it, refuses its frames too: the robot holds its frames
    until its ingest socket is accepted (ws) or a block is (http), so a refused robot costs the replica one request
    per retry, not two. The frame then goes, once."""
    items = [Frame(0.0, b"\x89PNG\r\n\x1a\n", "image/png"), *blocks_from_arrays(kit.stroke_arrays(500, seed=5), 0.02)]
    if transport == "ws":
        fake_service.shed_handshakes = 2
    else:
        fake_service.saturate = 2
    stats = kit.stream(fake_service.app, items, transport=transport, **FAST)
    if transport == "ws":
        admitted = fake_service.handshakes[2]  # the first handshake accepted
    else:
        admitted = next(t for t, status in fake_service.block_answers if status == 202)
    assert stats.saturated == 2 and stats.acked == 25
    assert len(fake_service.frame_posts) == 1 and fake_service.frame_posts[0] > admitted
    assert stats.frames_sent == 1 and stats.frames_refused == 0


@pytest.mark.parametrize("transport", ["ws", "http"])
def test_a_refused_block_is_dropped_not_retried(kit, fake_service, transport):
    arrays = kit.stroke_arrays(1000, seed=2)
    blocks = list(blocks_from_arrays(arrays, 0.02))
    fake_service.reject_seqs = {7}
    stats = kit.stream(fake_service.app, blocks, transport=transport, **FAST)
    sess = fake_service.only_session()
    assert sess.deliveries[7] == 1, "a 400 block is not sent again"
    assert [b.seq for b in sess.accepted] == [s for s in range(len(blocks)) if s != 7]
    assert stats.rejected == 1 and stats.acked == len(blocks) - 1 and stats.unsent == 0


def test_full_buffer_drops_the_oldest_and_counts_them_lost(kit, fake_service, caplog):
    arrays = kit.stroke_arrays(1000, seed=3)  # 50 blocks of 20 ms
    blocks = list(blocks_from_arrays(arrays, 0.02))
    fake_service.add_session("s-fixed", "robot-secret")
    server = kit.LoopbackServer(fake_service.app)

    async def main():
        await server.start()  # learn a free port, then take the service away before the robot starts
        await server.stop()
        client = RobotClient(
            server.url,
            kit.ListSource(blocks),
            session_id="s-fixed",
            robot_token="robot-secret",
            max_buffer_s=0.2,
            **FAST,
        )
        run = asyncio.create_task(client.run())
        await _wait_until(lambda: client.stats.read == len(blocks))
        await server.start()
        try:
            return await run
        finally:
            await server.stop()

    with caplog.at_level(logging.ERROR, logger="drivers.robot"):
        stats = asyncio.run(main())
    sess = fake_service.sessions["s-fixed"]
    assert [b.seq for b in sess.accepted] == list(range(40, 50)), "the newest 0.2 s survive"
    np.testing.assert_array_equal(kit.concat(sess.accepted, "accel"), arrays["accel"][0][800:])
    assert stats.lost == 40 and stats.lost_s == pytest.approx(0.8)
    assert stats.acked == 10 and stats.unsent == 0
    assert any("resend buffer full" in r.message for r in caplog.records)


def test_creates_a_session_keeps_the_console_link_out_of_the_log_and_posts_frames(kit, fake_service, caplog):
    arrays = kit.stroke_arrays(200, seed=4)
    png = b"\x89PNG\r\n\x1a\n" + b"not really decoded by the fake"
    items = [Frame(0.0, png, "image/png"), *blocks_from_arrays(arrays, 0.02)]
    server = kit.LoopbackServer(fake_service.app)

    async def main():
        await server.start()
        try:
            client = RobotClient(server.url, kit.ListSource(items), session_name="bench", **FAST)
            stats = await client.run()
            return client, stats
        finally:
            await server.stop()

    with caplog.at_level(logging.INFO, logger="drivers.robot"):
        client, stats = asyncio.run(main())
    sess = fake_service.only_session()
    sid = client.session.session_id
    assert client.session.console_url == f"{server.url}/console?session={sid}&token={sess.operator_token}"
    assert sid in caplog.text and sess.operator_token not in caplog.text and sess.robot_token not in caplog.text
    assert sess.frames == [("image/png", png)]
    assert stats.frames_sent == 1 and stats.acked == 10


@pytest.mark.parametrize("transport", ["ws", "http"])
def test_a_refused_token_is_fatal(kit, fake_service, transport):
    fake_service.add_session("s-fixed", "robot-secret")
    server = kit.LoopbackServer(fake_service.app)

    async def main():
        await server.start()
        try:
            client = RobotClient(
                server.url, kit.EndlessSource(), session_id="s-fixed", robot_token="wrong", transport=transport, **FAST
            )
            await client.run()
        finally:
            await server.stop()

    with pytest.raises(RobotAuthError):
        asyncio.run(main())


@pytest.mark.parametrize("transport", ["ws", "http"])
def test_a_lost_session_stops_the_run_with_the_services_reason(kit, fake_service, transport):
    """410 (HTTP) / close 4410 (an open WebSocket): the replica holding the session is gone; retrying cannot help."""
    sess = fake_service.add_session("s-fixed", "robot-secret")
    fake_service.lose_after = 5
    server = kit.LoopbackServer(fake_service.app)

    async def main():
        await server.start()
        try:
            client = RobotClient(
                server.url,
                kit.EndlessSource(speed=4.0),
                session_id="s-fixed",
                robot_token="robot-secret",
                transport=transport,
                **FAST,
            )
            with pytest.raises(SessionLostError) as lost:
                await client.run()
            return client.stats, lost.value
        finally:
            await server.stop()

    stats, error = asyncio.run(main())
    assert isinstance(error, ServiceRefused)  # callers that stop on any final refusal stop on this one too
    assert "(HTTP 410)" in str(error) and kit.LOST_DETAIL[:100] in str(error), str(error)
    assert len(sess.accepted) == 5 and fake_service.lost_answers == 1  # told once, never retried
    assert stats.acked == 5 and stats.unsent == stats.read - 5


@pytest.mark.parametrize("transport", ["ws", "http"])
def test_a_session_lost_while_draining_ends_the_run_at_once(kit, fake_service, transport):
    """The source has ended (its blocks and a frame buffered) when the service says the session is lost: the run
    raises the reason at once. It waited out the drain timeout before (30 s by default): the frame sender still waited
    for an ingest that would never open again. The hang guard below is far under the drain timeout set here."""
    fake_service.add_session("s-fixed", "robot-secret")
    fake_service.lose_after = 0
    server = kit.LoopbackServer(fake_service.app)
    items = [Frame(0.0, b"\x89PNG\r\n\x1a\n", "image/png"), *blocks_from_arrays(kit.stroke_arrays(200, seed=3), 0.02)]

    async def main():
        await server.start()
        try:
            client = RobotClient(
                server.url,
                kit.ListSource(items),
                session_id="s-fixed",
                robot_token="robot-secret",
                transport=transport,
                drain_timeout_s=3600.0,
                **FAST,
            )
            with pytest.raises(SessionLostError) as lost:
                await asyncio.wait_for(client.run(), timeout=60.0)
            return client.stats, lost.value
        finally:
            await server.stop()

    stats, error = asyncio.run(main())
    assert kit.LOST_DETAIL[:100] in str(error), str(error)
    assert fake_service.lost_answers == 1 and stats.acked == 0 and stats.unsent == stats.read  # told once
    assert stats.frames_sent == 0


def test_duration_stops_reading_then_drains(kit, fake_service):
    server = kit.LoopbackServer(fake_service.app)
    source = kit.EndlessSource(speed=4.0)

    async def main():
        await server.start()
        try:
            return await RobotClient(server.url, source, **FAST).run(duration_s=0.3)
        finally:
            await server.stop()

    stats = asyncio.run(main())
    sess = fake_service.only_session()
    assert stats.read > 0 and stats.acked == stats.read and stats.unsent == 0
    assert [b.seq for b in sess.accepted] == list(range(stats.read))
    assert source.closed


def test_duration_holds_while_the_service_is_unreachable(kit):
    """The reading went on for the whole minute the robot retried opening a session (55 s of data for --duration 2),
    and only then did it give up."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        url = f"http://127.0.0.1:{s.getsockname()[1]}"  # closed at once: nothing listens there
    source = kit.EndlessSource(speed=4.0)
    client = RobotClient(url, source, **{**FAST, "drain_timeout_s": 0.5})

    async def main():
        return await asyncio.wait_for(client.run(duration_s=0.3), 20)  # a hang guard, not a timing assertion

    with pytest.raises(ServiceUnavailable, match="stopped, and no session could be opened"):
        asyncio.run(main())
    assert client.stats.unsent == client.stats.read > 0 and source.closed


def test_cancelling_run_closes_the_source_and_its_tasks(kit, fake_service):
    server = kit.LoopbackServer(fake_service.app)
    source = kit.EndlessSource(speed=4.0)

    async def main():
        await server.start()
        try:
            client = RobotClient(server.url, source, **FAST)
            run = asyncio.create_task(client.run())
            await _wait_until(lambda: fake_service.sessions and len(fake_service.only_session().accepted) >= 5)
            run.cancel()
            with pytest.raises(asyncio.CancelledError):
                await run
            leftovers = [t.get_name() for t in asyncio.all_tasks() if t.get_name().startswith("robot-")]
            return client, leftovers
        finally:
            await server.stop()

    client, leftovers = asyncio.run(main())
    assert source.closed and leftovers == []
    assert client.stats.unsent == client.stats.read - client.stats.acked


def test_bad_client_arguments_are_named():
    src = object()
    with pytest.raises(ValueError, match="http://"):
        RobotClient("ftp://x", src)
    with pytest.raises(ValueError, match="both session_id and robot_token"):
        RobotClient("http://x", src, session_id="s")
    with pytest.raises(ValueError, match="transport"):
        RobotClient("http://x", src, transport="udp")
    with pytest.raises(ValueError, match="backoff"):
        RobotClient("http://x", src, backoff=(1.0, 0.5))


def test_backoff_grows_exponentially_with_jitter_and_caps():
    b = Backoff(0.1, 1.0, rng=random.Random(0))
    delays = [b.next() for _ in range(8)]
    ceilings = [min(1.0, 0.1 * 2**k) for k in range(8)]
    assert all(c / 2 <= d <= c for d, c in zip(delays, ceilings))
    assert len(set(delays)) == len(delays), "jittered"
    b.reset()
    assert 0.05 <= b.next() <= 0.1
    # the service's Retry-After is a floor, spread over up to half as much again (robots refused together)
    b.reset()
    hinted = [b.next(2.0) for _ in range(3)]
    assert all(2.0 <= d <= 3.0 for d in hinted) and len(set(hinted)) == 3
    assert 0.4 <= b.next(0.01) <= 0.8  # a short Retry-After does not cut the backoff grown meanwhile


def test_resend_buffer_keeps_max_seconds_and_settles_cumulatively():
    buf = ResendBuffer(max_s=0.07)  # room for three blocks of 20 ms
    dropped = [d.seq for i in range(5) for d in buf.append(Pending(i, b"x", 0.02))]
    assert dropped == [0, 1] and len(buf) == 3 and buf.held_s == pytest.approx(0.06)
    assert buf.oldest_seq == 2
    assert buf.first_from(0).seq == 2 and buf.first_from(4).seq == 4 and buf.first_from(5) is None
    assert buf.count_before(4) == 2
    assert [e.seq for e in buf.settle(3)] == [2, 3] and buf.oldest_seq == 4
    with pytest.raises(ValueError, match="does not follow"):
        buf.append(Pending(9, b"x", 0.02))


class FailingSource:
    """Yields its blocks, then fails like an unplugged device."""

    name = "failing"

    def __init__(self, blocks) -> None:
        self.blocks = blocks
        self.closed = False

    async def _items(self):
        for block in self.blocks:
            yield block
        raise OSError("device unplugged")

    def __aiter__(self):
        return self._items()

    async def aclose(self) -> None:
        self.closed = True


def test_a_failing_source_ends_the_run_after_its_blocks_are_delivered(kit, fake_service):
    arrays = kit.stroke_arrays(400, seed=5)
    source = FailingSource(list(blocks_from_arrays(arrays, 0.02)))
    server = kit.LoopbackServer(fake_service.app)

    async def main():
        await server.start()
        try:
            await RobotClient(server.url, source, **FAST).run()
        finally:
            await server.stop()

    with pytest.raises(OSError, match="unplugged"):
        asyncio.run(main())
    _assert_exactly_once(kit, fake_service.only_session(), arrays, 20)
    assert source.closed


def test_a_service_that_never_becomes_ready_fails_fast_with_its_reason(kit):
    from starlette.applications import Starlette
    from starlette.responses import JSONResponse
    from starlette.routing import Route

    calls = []

    async def not_ready(request):
        calls.append(request.url.path)
        return JSONResponse({"detail": "not ready: loading the model"}, status_code=503)

    server = kit.LoopbackServer(Starlette(routes=[Route("/sessions", not_ready, methods=["POST"])]))

    async def main():
        await server.start()
        try:
            client = RobotClient(server.url, kit.EndlessSource(), open_timeout_s=0.3, **FAST)
            started = asyncio.get_running_loop().time()
            with pytest.raises(ServiceUnavailable) as refused:
                await client.run()
            return asyncio.get_running_loop().time() - started, str(refused.value)
        finally:
            await server.stop()

    elapsed, message = asyncio.run(main())
    assert len(calls) >= 2, "it retried before giving up"
    assert elapsed < 2.0, "gave up near open_timeout_s, not after the backoff cap"
    assert "within 0.3 s" in message and "HTTP 503: not ready: loading the model" in message


def test_an_unreachable_service_fails_fast_naming_it(kit):
    import socket

    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        url = f"http://127.0.0.1:{s.getsockname()[1]}"
    client = RobotClient(url, kit.EndlessSource(), open_timeout_s=0.3, **FAST)
    with pytest.raises(ServiceUnavailable, match=r"cannot reach it \(ConnectError"):
        asyncio.run(client.open_session())
