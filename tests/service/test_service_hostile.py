"""Hostile input and overload: one test per finding of the hostile-client probe, against a live server."""

from __future__ import annotations

import asyncio
import json
import logging
import socket
import time

import httpx
import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from drivers.blocks import ChannelBlock, SampleBlock, encode_binary, encode_json
from service.app import create_app
from service.directory import reap_due
from service.fleet import ApiKeys, TokenBucket
from service.settings import Settings
from service.uncertainty import Assessment


# ---- credentials and session creation ---------------------------------------------------------------
def test_creating_a_session_needs_a_fleet_key(kit, server, client):
    missing = client.post("/sessions", json={})
    assert missing.status_code == 401 and "API key" in missing.json()["detail"]
    assert missing.headers["www-authenticate"] == "Bearer"
    wrong = client.post("/sessions", json={}, headers={"Authorization": "Bearer not-a-key"})
    assert wrong.status_code == 401 and "not valid" in wrong.json()["detail"]
    # a session token does not open sessions either
    session = kit.create_session(client)
    robot = client.post("/sessions", json={}, headers={"Authorization": f"Bearer {session['robot_token']}"})
    assert robot.status_code == 401


def test_without_a_configured_key_session_creation_is_closed_and_says_how(kit, base_settings):
    settings = base_settings.model_copy(update={"api_keys": None, "instance_id": "nokey"})
    with kit.running(settings) as srv, httpx.Client(base_url=srv.url, timeout=10) as client:
        r = client.post("/sessions", json={}, headers=kit.FLEET)
        assert r.status_code == 503
        assert "HAPTICLINK_API_KEYS" in r.json()["detail"] and "HAPTICLINK_API_KEYS_FILE" in r.json()["detail"]


def test_the_key_file_rotates_without_a_restart(tmp_path):
    path = tmp_path / "keys"
    path.write_text("# fleet keys\nold-key\n\n")
    keys = ApiKeys(None, path)
    assert keys.configured and keys.check("old-key") and not keys.check("new-key") and not keys.check(None)
    time.sleep(0.01)
    path.write_text("new-key\nspare-key\n")
    assert keys.check("new-key") and keys.check("spare-key") and not keys.check("old-key")
    path.unlink()
    assert not keys.configured


def test_the_session_rate_is_limited_per_client():
    now = [0.0]
    bucket = TokenBucket(rate=2.0, burst=3, clock=lambda: now[0])
    assert [bucket.take("a") for _ in range(3)] == [0.0, 0.0, 0.0]
    assert bucket.take("a") == pytest.approx(0.5)  # empty: the next token in 1/rate s
    assert bucket.take("b") == 0.0  # another client has its own bucket
    now[0] += 0.5
    assert bucket.take("a") == 0.0


def test_a_refused_session_request_does_not_count_against_the_clients_rate(kit, base_settings):
    # the probe: two POST /sessions refused 503 (the replica full) spent the burst, and the next, once a slot was
    # free, was refused 429 "too many sessions opened"
    settings = base_settings.model_copy(
        update={"session_burst": 2, "session_rate_per_s": 0.01, "max_sessions": 1, "instance_id": "refund"}
    )
    with kit.running(settings) as srv, httpx.Client(base_url=srv.url, timeout=10) as client:
        first = client.post("/sessions", json={}, headers=kit.FLEET)
        assert first.status_code == 201
        assert [client.post("/sessions", json={}, headers=kit.FLEET).status_code for _ in range(3)] == [503] * 3
        session = first.json()
        ended = client.delete(
            f"/sessions/{session['session_id']}", headers={"Authorization": f"Bearer {session['robot_token']}"}
        )
        assert ended.status_code == 200
        assert client.post("/sessions", json={}, headers=kit.FLEET).status_code == 201  # the second of the burst
        assert srv.app.state.service.session_limiter.take("127.0.0.1") > 0  # and the burst is spent now


def test_a_session_request_is_judged_key_first_body_second_rate_last(kit, base_settings):
    # the probe: 8 MB bodies without a key were parsed before their 401 (0.2–0.5 s of the event loop each, until
    # admission shed streaming robots), ten 422s spent a client's session rate, and a body sent as text/plain got
    # "Input should be a valid dictionary"
    settings = base_settings.model_copy(update={"session_burst": 2, "session_rate_per_s": 0.01, "instance_id": "order"})
    big = b"[" + b"[]," * 2_000_000 + b"[]]"  # 6 MB of JSON
    with kit.running(settings) as srv, httpx.Client(base_url=srv.url, timeout=10) as client:
        for headers in ({}, {"Authorization": "Bearer nope"}):  # no key, a wrong key: 401 whatever the body
            for body in (big, b"{syntax", b'{"name": 7}'):
                r = client.post("/sessions", content=body, headers={**headers, "Content-Type": "application/json"})
                assert r.status_code == 401, (headers, body[:10], r.text)
        # with a key: the body's size is bounded before it is read, its media type named, its fields named
        r = client.post("/sessions", content=big, headers={**kit.FLEET, "Content-Type": "application/json"})
        assert r.status_code == 413 and "at most 4096 bytes" in r.json()["detail"]
        streamed = (big[i : i + 1024] for i in range(0, 8192, 1024))  # no Content-Length: counted as it streams in
        r = client.post("/sessions", content=streamed, headers={**kit.FLEET, "Content-Type": "application/json"})
        assert r.status_code == 413 and r.headers["connection"] == "close"
        assert r.json()["detail"] == "a session request holds at most 4096 bytes (a name)"
        for kind in ("text/plain", "application/x-www-form-urlencoded", None):
            headers = {**kit.FLEET, **({"Content-Type": kind} if kind else {})}
            r = client.post("/sessions", content=b'{"name": "ok"}', headers=headers)
            assert r.status_code == 415, r.text
            assert r.json()["detail"] == f"a session request is application/json, got {kind or 'no Content-Type'}"
        for _ in range(10):
            r = client.post("/sessions", json={"nmae": "typo"}, headers=kit.FLEET)
            assert r.status_code == 422 and r.json()["detail"] == "body.nmae: Extra inputs are not permitted"
        # none of these opened a session, so none spent the rate: the burst of 2 is whole
        assert [client.post("/sessions", json={"name": "r"}, headers=kit.FLEET).status_code for _ in range(3)] == [
            201,
            201,
            429,
        ]
        assert client.post("/sessions", headers=kit.FLEET).status_code == 429  # an empty body is a request too


def test_a_burst_of_session_requests_is_refused_early_not_taking_every_slot(kit, base_settings):
    # the probe: 300 POST /sessions in 0.6 s took all 256 slots for 600 s
    # one token back every 1000 s: none comes back while the 40 requests go in, however busy the host (at 0.5 s⁻¹ one
    # did when they took over 2 s)
    settings = base_settings.model_copy(
        update={"session_burst": 5, "session_rate_per_s": 0.001, "instance_id": "burst"}
    )
    with kit.running(settings) as srv, httpx.Client(base_url=srv.url, timeout=10) as client:
        answers = [client.post("/sessions", json={}, headers=kit.FLEET) for _ in range(40)]
        codes = [r.status_code for r in answers]
        assert codes[:5] == [201] * 5 and set(codes[5:]) == {429}
        assert int(answers[-1].headers["retry-after"]) >= 1 and "too many sessions" in answers[-1].json()["detail"]
        assert len(srv.app.state.service.sessions) == 5
        assert 'hapticlink_sessions_refused_total{reason="rate"} 35' in client.get("/metrics", headers=kit.SCRAPER).text


def test_sessions_that_never_stream_are_reclaimed_before_idle_ones():
    settings = Settings(session_first_block_s=10, session_idle_s=60)

    class S:
        def __init__(self, sid, opened, last_seq, activity, contact=None):
            self.id, self.opened_at, self.last_seq, self.last_activity = sid, opened, last_seq, activity
            self.last_contact = activity if contact is None else contact

    sessions = [
        S("fresh", 95, -1, 95),
        S("abandoned", 80, -1, 80),
        S("waiting for room", 80, -1, 80, 95),  # its first block refused for capacity 5 s ago: its robot is there
        S("streaming", 0, 40, 99),
        S("idle", 0, 40, 30),
        S("shed, retrying as told", 0, 40, 30, 98),  # streamed, then shed: its robot's tries are refused
    ]
    due = dict(reap_due(sessions, 100.0, settings))
    assert set(due) == {"abandoned", "idle"}
    assert "no block within 10 s" in due["abandoned"] and "no traffic for 60 s" in due["idle"]


def test_an_abandoned_session_is_ended_and_its_slot_freed(kit, base_settings):
    settings = base_settings.model_copy(update={"session_first_block_s": 0.3, "instance_id": "reap"})
    with kit.running(settings) as srv, httpx.Client(base_url=srv.url, timeout=10) as client:
        session = kit.create_session(client)
        kit.wait_for(lambda: not srv.app.state.service.sessions, timeout_s=10)
        r = client.get(
            f"/sessions/{session['session_id']}", headers={"Authorization": f"Bearer {session['operator_token']}"}
        )
        assert r.status_code == 404


# ---- the cost of one block ------------------------------------------------------------------------------
def _block(seq: int, t0: float, n: int = 20, rate: float = 1000.0) -> SampleBlock:
    rng = np.random.default_rng(seq)
    return SampleBlock(
        t0,
        {
            "accel": ChannelBlock(rng.normal(size=(n, 3)).astype(np.float32), rate, "m/s^2"),
            "force": ChannelBlock(np.full(n, 1.5, np.float32), rate, "N"),
            "speed": ChannelBlock(np.full(n, 80.0, np.float32), rate, "mm/s"),
        },
        seq,
    )


def test_the_huge_legal_block_is_refused_by_stream_time_at_once(kit, server, client):
    # the probe: 10 Hz, 100 000 samples per channel (2.8 MB) made ~20 000 windows and 8–9 s of server CPU
    session = kit.create_session(client)
    started = time.perf_counter()
    r = kit.post_block(client, session, _block(0, 0.0, n=100_000, rate=10.0))
    assert r.status_code == 422 and "at most 1 s of stream time, got 10000 s" in r.json()["detail"]
    assert time.perf_counter() - started < 2.0  # refused before any window is computed
    assert client.get("/health").status_code == 200
    status = kit.session_status(client, session)
    assert status["last_seq"] == -1 and status["counters"]["blocks_rejected"] == 1 and status["windows_ready"] == 0


def test_publishing_many_windows_yields_to_the_event_loop(base_settings):
    from service.live_session import Session
    from service.metrics import ServiceMetrics
    from service.pipeline import SessionResult, WindowEstimate
    from service.runtime import load_runtime

    runtime = load_runtime(base_settings)
    published: list[int] = []
    ticks: list[int] = []

    async def publish(sid, event, final):
        published.append(event["window_index"])

    async def main():
        session = Session("s", "s", None, runtime, base_settings, None, publish, ServiceMetrics(), lambda s: None)  # type: ignore[arg-type]

        async def ticker():
            while True:
                ticks.append(len(published))
                await asyncio.sleep(0)

        tick = asyncio.create_task(ticker())
        await asyncio.sleep(0)
        z = np.zeros(4)
        unknown = Assessment(None, None, ())
        estimates = [
            WindowEstimate(i, 0.5 * i, 0.5 * i + 0.5, z, z, z, unknown, [], "x", i, 0, 0, 1.0, 1.0, 1.0, "tactile", "m")
            for i in range(40)
        ]
        await session.apply_result(SessionResult(estimates, 40))
        tick.cancel()

    asyncio.run(main())
    assert published == list(range(40))
    # the loop ran other tasks between the events, not only before and after all 40
    assert any(0 < n < 40 for n in ticks)


# ---- sequence numbers -----------------------------------------------------------------------------------
def test_a_seq_jump_past_the_resend_window_is_refused_and_the_session_lives_on(kit, server, client, library_dir):
    session = kit.create_session(client)
    blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_001", 1.2))
    assert kit.post_block(client, session, blocks[0]).status_code == 202
    huge = SampleBlock(blocks[1].t0, blocks[1].channels, 2**62)
    r = kit.post_block(client, session, huge)
    assert r.status_code == 422 and "seq jumps from 0 to 4611686018427387904" in r.json()["detail"]
    for block in blocks[1:]:  # every good block is still taken, not acknowledged as a duplicate
        r = kit.post_block(client, session, block)
        assert r.status_code == 202 and r.json()["duplicate"] is False
    final = kit.wait_for(lambda: (s := kit.session_status(client, session))["counters"]["windows"] == 2 and s)
    assert final["last_seq"] == blocks[-1].seq


def test_a_json_block_without_seq_is_refused(kit, server, client):
    session = kit.create_session(client)
    body = encode_json(_block(0, 0.0))
    del body["seq"]
    r = kit.post_block(client, session, json.dumps(body).encode(), "application/json")
    assert r.status_code == 422 and "seq is required" in r.json()["detail"]


# ---- logs ------------------------------------------------------------------------------------------------
class _Capture(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def test_no_token_reaches_a_log_line_and_refusals_log_one_warning(kit, base_settings, library_dir):
    capture = _Capture()
    names = ("uvicorn", "uvicorn.access", "service")  # uvicorn.access does not propagate; the others do
    settings = base_settings.model_copy(update={"instance_id": "logs", "log_level": "debug"})
    with kit.running(settings, log_level="debug") as srv, httpx.Client(base_url=srv.url, timeout=10) as client:
        levels = {name: logging.getLogger(name).level for name in names}
        for name in names:
            logging.getLogger(name).addHandler(capture)
            logging.getLogger(name).setLevel(logging.DEBUG)
        try:
            session = kit.create_session(client)
            with connect(kit.socket_url(srv, session, "ingest")) as ws:
                ws.send(encode_binary(_block(0, 0.0)))
                assert json.loads(ws.recv(timeout=5))["ok"] is True
            refused_token = "definitely-not-the-token-0123456789"
            for _ in range(5):  # each accepted, then closed 1008
                with pytest.raises(ConnectionClosed):
                    with connect(f"{srv.ws_url}/sessions/{session['session_id']}/ingest?token={refused_token}") as ws:
                        ws.recv(timeout=5)
            kit.wait_for(lambda: any("disconnected" in r.getMessage() for r in capture.records), timeout_s=5)
            # the scraper's token, and one that is not it: neither may reach a line
            assert client.get("/metrics", headers=kit.SCRAPER).status_code == 200
            assert client.get("/metrics", headers={"Authorization": f"Bearer {refused_token}"}).status_code == 401
        finally:
            for name in names:
                logging.getLogger(name).removeHandler(capture)
                logging.getLogger(name).setLevel(levels[name])
    lines = [r.getMessage() for r in capture.records]
    assert any('"WebSocket /sessions/' in line for line in lines), "uvicorn logged no handshake line"
    # uvicorn's two INFO lines per accepted socket: the robot's, then those of a wrong token once in 10 s, not twice
    # per wrong token (any client could)
    assert sum("[accepted]" in line for line in lines) == 2 and lines.count("connection open") == 2
    for secret in (session["robot_token"], session["operator_token"], refused_token, kit.API_KEY, kit.METRICS_TOKEN):
        assert not any(secret in line for line in lines), [line for line in lines if secret in line]
    refusals = [r for r in capture.records if "refused" in r.getMessage() and "ingest socket" in r.getMessage()]
    assert len(refusals) == 1 and refusals[0].levelno == logging.WARNING
    assert not any(r.levelno >= logging.ERROR for r in capture.records), [
        r.getMessage() for r in capture.records if r.levelno >= logging.ERROR
    ]
    assert not any(r.exc_info for r in capture.records)


def test_operators_are_told_when_the_robot_disconnects(kit, server, client):
    session = kit.create_session(client)
    with connect(kit.socket_url(server, session, "events")) as sub:
        assert json.loads(sub.recv(timeout=5))["event"] == "subscribed"
        with connect(kit.socket_url(server, session, "ingest")) as ws:
            ws.send(encode_binary(_block(0, 0.0)))
            ws.recv(timeout=5)
        event = json.loads(sub.recv(timeout=5))
        assert event["event"] == "robot_disconnected" and "closed" in event["message"]
        with pytest.raises(ConnectionClosed):  # the operator's token is no robot token
            with connect(
                f"{server.ws_url}/sessions/{session['session_id']}/ingest?token={session['operator_token']}"
            ) as ws:
                ws.recv(timeout=5)
        event = json.loads(sub.recv(timeout=5))
        assert event["event"] == "robot_refused" and "refused" in event["message"]
        assert session["operator_token"] not in event["message"]


def test_refused_ingest_connections_reach_the_operators_once_every_10_s_not_each(kit, server, client, monkeypatch):
    """Anyone who knows a session's id could push 1,800 robot_refused events a second into its operators' feeds
    (wrong tokens cost nothing): the next one says how many were left out."""
    session = kit.create_session(client)
    wrong = f"{server.ws_url}/sessions/{session['session_id']}/ingest?token=wrong-token"
    with connect(kit.socket_url(server, session, "events")) as sub:
        assert json.loads(sub.recv(timeout=5))["event"] == "subscribed"
        for _ in range(20):
            with pytest.raises(ConnectionClosed), connect(wrong) as ws:
                ws.recv(timeout=5)
        first = json.loads(sub.recv(timeout=5))
        assert first["event"] == "robot_refused" and "more" not in first["message"]
        with pytest.raises(TimeoutError):  # the other 19 were not sent on
            sub.recv(timeout=0.5)
        notices = server.app.state.service.sessions[session["session_id"]].notices
        monkeypatch.setattr(notices, "every_s", 0.0)  # as if 10 s had passed
        with pytest.raises(ConnectionClosed), connect(wrong) as ws:
            ws.recv(timeout=5)
        later = json.loads(sub.recv(timeout=5))
        assert later["event"] == "robot_refused" and "(and 19 more since the last such event)" in later["message"]


# ---- slow and half-open connections -----------------------------------------------------------------------
def test_half_open_requests_and_silent_connections_are_closed(kit, base_settings, caplog):
    """A stalled request is closed with a WARNING; a connection that never sent a byte (a browser's spare one: every
    console visit leaves one) is closed as fast, without a line."""
    settings = base_settings.model_copy(
        update={"request_read_timeout_s": 0.5, "timeout_keep_alive_s": 0.5, "instance_id": "halfopen"}
    )
    with kit.running(settings) as srv, caplog.at_level(logging.INFO, logger="service.server"):

        def closed_within(send: bytes, seconds: float) -> float:
            with socket.create_connection(("127.0.0.1", srv.port)) as sock:
                sock.settimeout(seconds)
                started = time.perf_counter()
                if send:
                    sock.sendall(send)
                data = sock.recv(65536)
                while data:  # a response may come before the close
                    data = sock.recv(65536)
                return time.perf_counter() - started

        assert closed_within(b"", 5.0) < 3.0  # connected, said nothing
        assert not [r for r in caplog.records if r.levelno >= logging.WARNING], caplog.text
        half = b"POST /sessions HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: 100\r\n\r\n{"
        assert closed_within(half, 5.0) < 3.0
        assert "no complete request within 0.5 s" in caplog.text
        assert closed_within(b"GET /health HTTP/1.1\r\nHo", 5.0) < 3.0  # half the headers
        # a whole request is answered, and the idle keep-alive connection is closed afterwards
        with socket.create_connection(("127.0.0.1", srv.port)) as sock:
            sock.settimeout(5.0)
            sock.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n\r\n")
            assert sock.recv(65536).startswith(b"HTTP/1.1 200")
            started = time.perf_counter()
            assert sock.recv(65536) == b"" and time.perf_counter() - started < 3.0


# ---- smaller findings ---------------------------------------------------------------------------------------
def test_frame_errors_do_not_leak_object_reprs(kit, server, client):
    session = kit.create_session(client)
    r = client.post(
        f"/sessions/{session['session_id']}/frames",
        content=b"\x89PNG\r\n\x1a\n garbage",
        headers={"Authorization": f"Bearer {session['robot_token']}", "Content-Type": "image/png"},
    )
    assert r.status_code == 422 and "not a readable image" in r.json()["detail"]
    assert "BytesIO" not in r.json()["detail"] and " at 0x" not in r.json()["detail"]


def test_the_block_schema_is_as_strict_as_the_validator(client):
    schemas = client.get("/openapi.json").json()["components"]["schemas"]
    block = schemas["JsonBlock"]
    assert "seq" in block["required"] and block["properties"]["channels"]["minProperties"] == 1
    assert set(block["properties"]["channels"]["propertyNames"]["enum"]) == {"accel", "force", "speed", "position"}
    channel = schemas["JsonChannel"]["properties"]
    assert channel["rate_hz"]["minimum"] == 10 and channel["rate_hz"]["maximum"] == 100_000
    assert all(option.get("minItems") == 1 for option in channel["data"]["anyOf"])


def test_cors_is_closed_by_default_and_opens_for_configured_origins(kit, server, client, base_settings):
    preflight = {"Origin": "https://evil.example", "Access-Control-Request-Method": "POST"}
    r = client.options("/sessions", headers=preflight)
    assert r.status_code == 400 and "access-control-allow-origin" not in r.headers
    settings = base_settings.model_copy(update={"cors_origins": ("https://ops.example",), "instance_id": "cors"})
    with kit.running(settings) as srv, httpx.Client(base_url=srv.url, timeout=10) as c:
        r = c.options("/sessions", headers={**preflight, "Origin": "https://ops.example"})
        assert r.status_code == 200 and r.headers["access-control-allow-origin"] == "https://ops.example"
        assert "POST" in r.headers["access-control-allow-methods"]


def test_the_console_sends_no_referrer_and_no_other_site_may_frame_it(client):
    """Its URL carries the operator token: no Referer carries it on, and no page of another site shows it in a frame."""
    r = client.get("/console")
    assert r.status_code == 200 and r.headers["referrer-policy"] == "no-referrer"
    assert r.headers["x-frame-options"] == "DENY" and r.headers["content-security-policy"] == "frame-ancestors 'none'"


def _upgrade(path: str = "/sessions/x/events", extra: bytes = b"") -> bytes:
    return (
        f"GET {path} HTTP/1.1\r\nHost: x\r\nConnection: Upgrade\r\nUpgrade: websocket\r\n"
        "Sec-WebSocket-Version: 13\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n".encode()
        + extra
        + b"\r\n"
    )


#: upgrade requests the websockets library refuses itself, before the app sees them, and its answer
REFUSED_UPGRADES = {
    "a 9 kB header line": (_upgrade(extra=b"Cookie: " + b"a" * 9000 + b"\r\n"), b"HTTP/1.1 431 "),
    "a 10 kB request line": (_upgrade("/sessions/" + "x" * 10_000 + "/events"), b"HTTP/1.1 414 "),
    "130 headers": (_upgrade(extra=b"".join(b"X-%d: y\r\n" % k for k in range(130))), b"HTTP/1.1 431 "),
}


@pytest.mark.parametrize("case", REFUSED_UPGRADES)
def test_an_upgrade_the_websockets_library_refuses_is_answered_and_closed_not_held(kit, server, case):
    """Its answer was queued but never written, and the connection held for ever (no deadline once upgrading): one
    client held 150 such connections, unanswered, for as long as it liked, without a credential."""
    request, status = REFUSED_UPGRADES[case]
    with socket.create_connection(("127.0.0.1", server.port), timeout=5) as raw:
        raw.sendall(request)
        answer = b""
        while chunk := raw.recv(65536):  # to the end: the server closes the connection
            answer += chunk
    assert answer.startswith(status), answer[:200]


def test_a_request_whose_body_is_still_arriving_does_not_hold_the_shutdown_or_write_an_error(kit, base_settings):
    """Half a body at shutdown: uvicorn waited its graceful 5 s for the rest, then cancelled the route, with an ERROR
    and a traceback for every such client."""
    srv = kit.ServerThread(base_settings.model_copy(update={"instance_id": "half-body"})).start()
    capture = _Capture()
    logging.getLogger("uvicorn.error").addHandler(capture)
    logging.getLogger("service").addHandler(capture)
    try:
        with socket.create_connection(("127.0.0.1", srv.port), timeout=5) as raw:
            raw.sendall(
                b"POST /sessions HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer " + kit.API_KEY.encode()
                + b"\r\nContent-Type: application/json\r\nContent-Length: 1000\r\n\r\n{\"a\":"
            )  # fmt: skip
            time.sleep(0.3)
            srv.stop()
    finally:
        logging.getLogger("uvicorn.error").removeHandler(capture)
        logging.getLogger("service").removeHandler(capture)
    assert not [r.getMessage() for r in capture.records if r.levelno >= logging.ERROR]


def test_a_refused_upgrade_held_open_does_not_break_the_shutdown(kit, base_settings, monkeypatch):
    """uvicorn's shutdown answered such a connection 500 on top of the refusal already queued, and raised: the
    service exited 1 with two tracebacks, its lifespan shutdown never run."""
    import threading

    raised: list[BaseException | None] = []
    monkeypatch.setattr(threading, "excepthook", lambda args: raised.append(args.exc_value))
    srv = kit.ServerThread(base_settings.model_copy(update={"instance_id": "held-upgrade"})).start()
    capture = _Capture()
    logging.getLogger("uvicorn.error").addHandler(capture)
    try:
        with socket.create_connection(("127.0.0.1", srv.port), timeout=5) as raw:
            raw.sendall(REFUSED_UPGRADES["a 9 kB header line"][0])  # and never reads
            time.sleep(0.3)
            srv.stop()
    finally:
        logging.getLogger("uvicorn.error").removeHandler(capture)
    assert raised == []
    assert not [r.getMessage() for r in capture.records if r.levelno >= logging.ERROR]


def test_settings_refuse_a_block_bound_the_queue_could_never_hold():
    with pytest.raises(ValueError, match="max_block_windows"):
        Settings(max_block_windows=9, session_queue_windows=8)


def test_the_routers_serve_every_route():
    # sessions, ingest, events, library and ops are separate routers; the app serves them all
    from service.app import route_paths

    paths = route_paths(create_app(Settings()))
    assert {
        "/sessions",
        "/sessions/{session_id}",
        "/sessions/{session_id}/blocks",
        "/sessions/{session_id}/frames",
        "/sessions/{session_id}/scene",
        "/sessions/{session_id}/ingest",
        "/sessions/{session_id}/events",
        "/health",
        "/ready",
        "/metrics",
        "/library",
        "/library/{entry_id}/model",
        "/console",
    } <= paths


def test_a_ping_flood_closes_its_socket_1008_and_the_session_streams_on(kit, server, client, library_dir):
    # the probe: 180 k pings a second for 12 s, their pongs never read, grew the server by 22 MB/s (and stalled
    # /health): uvicorn wrote a pong for every ping whatever the client read
    session = kit.create_session(client)
    url = kit.socket_url(server, session, "ingest")
    with connect(url) as ws:
        for k in range(400):
            try:
                ws.ping(str(k))
            except ConnectionClosed:
                break
        with pytest.raises(ConnectionClosed) as closed:
            ws.recv(timeout=10)
    assert closed.value.rcvd is not None and closed.value.rcvd.code == 1008
    assert closed.value.rcvd.reason == "too many pings"
    # a keepalive's pace is answered, and the session's blocks still go in
    with connect(url) as ws:
        for k in range(5):
            assert ws.ping(str(k)).wait(timeout=5)
        blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_000", 0.1))
        ws.send(encode_binary(blocks[0]))
        assert json.loads(ws.recv(timeout=10))["ok"] is True


def test_request_headers_are_bounded_before_they_are_parsed(kit, server, client, library_dir):
    # the probe: one 64 MB header on GET /library, no credential, held the event loop 2.5–5 s (/health with it)
    many = b"".join(b"X-%d: %s\r\n" % (k, b"z" * 900) for k in range(200))
    for head in (b"X-A: " + b"y" * 2_000_000 + b"\r\n", many):
        with socket.create_connection(("127.0.0.1", server.port), timeout=10) as raw:
            t0 = time.perf_counter()
            try:
                raw.sendall(b"GET /library HTTP/1.1\r\nHost: x\r\n" + head + b"\r\n")
            except OSError:
                pass  # the server may close before the last bytes are in
            answer = raw.recv(4096)
            assert answer.startswith(b"HTTP/1.1 431 "), answer[:100]
            assert b"request line and headers exceed 65536 bytes" in answer
            assert time.perf_counter() - t0 < 2
    assert client.get("/health").status_code == 200
    # a body in the same reads as a small head is no header: a 200 kB block whose head and body arrive together
    session = kit.create_session(client)
    rec = kit.stroke_recording(library_dir, "synth_000", 3.0)
    block = kit.recording_blocks(rec, block_s=1.0)[0]
    body = json.dumps(encode_json(block)).encode()
    assert len(body) > 64 * 1024
    r = kit.post_block(client, session, body, "application/json")
    assert r.status_code == 202, r.text
