"""Sessions begin and end: explicit DELETE, idle timeout, the max_sessions bound; and the service's
read-only routes (health, readiness, library, metrics)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
import threading
import time

import httpx
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from drivers.blocks import BINARY_CONTENT_TYPE, encode_binary
from service.events import StatusEvent
from texture_library.library import Library


def test_ending_a_session_tells_its_operators_and_closes_their_sockets(kit, server, client):
    session = kit.create_session(client)
    with connect(kit.socket_url(server, session, "events")) as sub:
        sub.recv(timeout=5)
        r = client.delete(
            f"/sessions/{session['session_id']}", headers={"Authorization": f"Bearer {session['robot_token']}"}
        )
        assert r.status_code == 200 and r.json()["state"] == "ended"
        last = StatusEvent.model_validate(json.loads(sub.recv(timeout=5)))
        assert last.event == "session_ended" and last.message == "ended by request"
        with pytest.raises(ConnectionClosed):
            sub.recv(timeout=5)
        assert sub.close_code == 1000


def test_a_block_whose_body_arrives_after_its_session_ended_is_refused_not_acknowledged(kit, server, client):
    """The robot token is checked with the headers; a DELETE may end the session before the body is in. That block
    was answered 202 and counted, with no session to hold it: the robot was told a lost block was accepted."""
    session = kit.create_session(client)
    block = encode_binary(kit.recording_blocks(kit.stroke_recording(server.settings.library_dir, "synth_001", 0.1))[0])
    with socket.create_connection(("127.0.0.1", server.port), timeout=5) as raw:
        raw.sendall(
            f"POST /sessions/{session['session_id']}/blocks HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer "
            f"{session['robot_token']}\r\nContent-Type: {BINARY_CONTENT_TYPE}\r\n"
            f"Content-Length: {len(block)}\r\n\r\n".encode()
            + block[: len(block) // 2]
        )
        time.sleep(0.2)  # the request reaches the route, which waits for the rest of its body
        r = client.delete(
            f"/sessions/{session['session_id']}", headers={"Authorization": f"Bearer {session['robot_token']}"}
        )
        assert r.status_code == 200 and r.json()["last_seq"] == -1
        raw.sendall(block[len(block) // 2 :])
        answer = raw.recv(4096).decode()
    assert answer.startswith("HTTP/1.1 404"), answer
    assert f"no session '{session['session_id']}'" in answer


def test_ending_a_session_closes_its_robots_idle_ingest_socket(kit, server, client):
    """The robot learns at once that its session ended (1000), not at its next block: an idle or half-sent socket
    outlived its session (one was still open 90 s after it was reaped)."""
    session = kit.create_session(client)
    with connect(kit.socket_url(server, session, "ingest")) as robot:
        r = client.delete(
            f"/sessions/{session['session_id']}", headers={"Authorization": f"Bearer {session['robot_token']}"}
        )
        assert r.status_code == 200
        with pytest.raises(ConnectionClosed):
            robot.recv(timeout=5)
        assert robot.close_code == 1000 and robot.close_reason == "session ended"


def test_a_sessions_ingest_sockets_are_bounded_a_newer_one_replaces_the_oldest(kit, server, client):
    """Two at once (a robot's reconnect may overlap a link not yet known dead); a third closes the oldest 4409, which a
    robot answers by reconnecting and resending. One robot token held 500 sockets before."""
    from service.directory import MAX_INGEST_SOCKETS

    session = kit.create_session(client)
    url = kit.socket_url(server, session, "ingest")
    block = encode_binary(kit.recording_blocks(kit.stroke_recording(server.settings.library_dir, "synth_001", 0.1))[0])
    with contextlib.ExitStack() as stack:
        sockets = [stack.enter_context(connect(url)) for _ in range(MAX_INGEST_SOCKETS + 1)]
        with pytest.raises(ConnectionClosed):
            sockets[0].recv(timeout=5)
        assert sockets[0].close_code == 4409 and "replaced by a newer ingest connection" in sockets[0].close_reason
        for ws in sockets[1:]:  # the newer ones stream on
            ws.send(block)
            assert json.loads(ws.recv(timeout=5))["ok"] is True


def test_a_stopping_service_tells_every_operator_its_session_is_lost_before_it_closes(kit, base_settings):
    """The probe: on SIGTERM uvicorn closed every socket (1012) before the lifespan shutdown ended the sessions, so
    no operator learnt that its session was lost. The server stopping as a signal stops it (should_exit)."""
    settings = base_settings.model_copy(update={"instance_id": "stopping"})
    srv = kit.ServerThread(settings).start()
    try:
        with httpx.Client(base_url=srv.url, timeout=10) as client:
            sessions = [kit.create_session(client) for _ in range(2)]
        with contextlib.ExitStack() as stack:
            subs = [stack.enter_context(connect(kit.socket_url(srv, s, "events"))) for s in sessions]
            for sub in subs:
                assert json.loads(sub.recv(timeout=5))["event"] == "subscribed"
            stopping = threading.Thread(target=srv.stop)
            stopping.start()
            for sub in subs:
                last = json.loads(sub.recv(timeout=10))
                assert last["event"] == "session_ended" and last["lost"] is True, last
                assert "its replica stopping shut down" in last["message"]
                with pytest.raises(ConnectionClosed):
                    sub.recv(timeout=5)
                assert sub.close_code == 1000
            stopping.join(timeout=20)
    finally:
        srv.stop()


def test_idle_sessions_are_ended_and_max_sessions_is_enforced(kit, base_settings):
    settings = base_settings.model_copy(update={"session_idle_s": 0.4, "max_sessions": 2})
    with kit.running(settings) as srv, httpx.Client(base_url=srv.url, timeout=10) as client:
        first = kit.create_session(client)
        kit.create_session(client)
        refused = client.post("/sessions", json={}, headers=kit.FLEET)
        assert refused.status_code == 503 and "max_sessions" in refused.json()["detail"]
        with connect(kit.socket_url(srv, first, "events")) as sub:
            sub.recv(timeout=5)
            ended = json.loads(sub.recv(timeout=10))
        assert ended["event"] == "session_ended" and "no traffic" in ended["message"]
        kit.wait_for(lambda: client.post("/sessions", json={}, headers=kit.FLEET).status_code == 201)  # room again


def test_health_ready_library_and_metrics(kit, server, client, library_dir):
    assert client.get("/health").json() == {"status": "ok", "instance": "test-a"}
    ready = client.get("/ready").json()
    assert ready["ready"] is True and ready["model"] == "ridge-tactile" and ready["library_entries"] == 6
    refused = client.get("/library")  # the library is state: it takes a credential, as its models do
    assert refused.status_code == 401 and "fleet API key" in refused.json()["detail"]
    session = kit.create_session(client)
    as_operator = client.get(
        "/library",
        params={"session": session["session_id"]},
        headers={"Authorization": f"Bearer {session['operator_token']}"},
    )
    assert as_operator.status_code == 200
    lib = client.get("/library", headers=kit.FLEET).json()
    assert lib == as_operator.json()
    expected = Library.load(library_dir)
    assert [e["id"] for e in lib["entries"]] == expected.ids
    assert lib["entries"][0]["ratings"] == pytest.approx(
        dict(zip(("rough_smooth", "flat_bumpy", "sticky_slippery", "hard_soft"), expected.ratings[0]))
    )

    session = kit.create_session(client)
    for block in kit.recording_blocks(kit.stroke_recording(library_dir, "synth_000", 1.0)):
        kit.post_block(client, session, block)
    kit.wait_for(lambda: kit.session_status(client, session)["counters"]["windows"] == 2)
    metrics = client.get("/metrics", headers=kit.SCRAPER)
    assert metrics.headers["content-type"].startswith("text/plain; version=0.0.4")
    text = metrics.text
    assert "hapticlink_ready 1" in text
    assert 'hapticlink_blocks_total{outcome="accepted"}' in text
    assert 'hapticlink_window_latency_seconds_count{stage="total"}' in text
    assert client.get("/console").headers["content-type"].startswith("text/html")


def test_an_ingest_socket_opened_as_its_session_ends_is_closed_not_kept(kit, server, client, monkeypatch):
    """The session may end while the socket's handshake is answered (after its token was checked): that socket was
    kept, idle, for a session that no longer existed, until its client sent something."""
    from starlette.websockets import WebSocket

    accept = WebSocket.accept

    async def end_then_accept(self: WebSocket, *args, **kwargs) -> None:
        await self.app.state.service.directory.end(self.path_params["session_id"], "ended by request")
        await accept(self, *args, **kwargs)

    session = kit.create_session(client)
    monkeypatch.setattr(WebSocket, "accept", end_then_accept)
    with connect(kit.socket_url(server, session, "ingest")) as robot:
        with pytest.raises(ConnectionClosed):
            robot.recv(timeout=5)
        assert robot.close_code == 1000 and robot.close_reason == "session ended"
    assert session["session_id"] not in server.app.state.service.directory._ingest


def test_a_robot_whose_socket_a_newer_one_replaced_reconnects_and_says_replaced_not_saturated(kit, server, library_dir):
    """Closed 4409 (not 4429): the robot reconnects, resends, delivers every block, and its stats tell a replacement
    (another holder of its token, or an old link of its own) from a saturated session."""
    from websockets.asyncio.client import connect as connect_async

    from drivers.robot.client import RobotClient

    blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_001", 2.0))
    intruders: list = []

    class Source:  # after 20 blocks, two more sockets open with the robot's token: the robot's is the oldest
        name = "blocks"

        def __init__(self) -> None:
            self.robot: RobotClient | None = None

        async def _items(self):
            for i, block in enumerate(blocks):
                if i == 20:
                    assert self.robot is not None and self.robot.session is not None
                    session = {"session_id": self.robot.session.session_id}
                    session["robot_token"] = self.robot.session.robot_token
                    for _ in range(2):
                        intruders.append(await connect_async(kit.socket_url(server, session, "ingest")))
                yield block
                await asyncio.sleep(0.005)

        def __aiter__(self):
            return self._items()

        async def aclose(self) -> None:
            pass

    async def main():
        source = Source()
        robot = source.robot = RobotClient(
            server.url, source, transport="ws", backoff=(0.05, 0.2), seed=1, api_key=kit.API_KEY
        )
        try:
            return await robot.run()
        finally:
            for ws in intruders:
                await ws.close()

    stats = asyncio.run(main())
    assert stats.replaced >= 1 and stats.saturated == 0
    assert stats.acked == len(blocks) and stats.lost == stats.rejected == stats.unsent == 0


def test_a_sessions_event_connections_are_bounded_the_next_is_refused_with_the_reason(kit, server, client):
    """Each event connection holds a queue: one operator token opened them without bound. Past the bound the
    handshake is refused 429, naming it; a closed one makes room, and other sessions are not affected."""
    from websockets.exceptions import InvalidStatus

    from service.bus import MAX_SUBSCRIBERS_PER_SESSION

    session, other = kit.create_session(client), kit.create_session(client)
    url = kit.socket_url(server, session, "events")
    with contextlib.ExitStack() as stack:
        subs = [stack.enter_context(connect(url)) for _ in range(MAX_SUBSCRIBERS_PER_SESSION)]
        for sub in subs:
            assert json.loads(sub.recv(timeout=5))["event"] == "subscribed"
        with pytest.raises(InvalidStatus) as refused:
            connect(url)
        assert refused.value.response.status_code == 429
        assert f"already has {MAX_SUBSCRIBERS_PER_SESSION} event connections" in refused.value.response.body.decode()
        with connect(kit.socket_url(server, other, "events")) as elsewhere:
            assert json.loads(elsewhere.recv(timeout=5))["event"] == "subscribed"
        subs.pop().close()
        held = server.app.state.service.bus._per_session
        kit.wait_for(lambda: held[session["session_id"]] < MAX_SUBSCRIBERS_PER_SESSION)
        with connect(url) as again:
            assert json.loads(again.recv(timeout=5))["event"] == "subscribed"
    kit.wait_for(lambda: not held)
