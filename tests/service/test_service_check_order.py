"""The order of checks, against a live uvicorn with a real HTTP client: the credential first, then everything else, on
every route; a refused upload's 413 is read by the client that sent it."""

from __future__ import annotations

import socket
import time

import httpx
import pytest
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from drivers.blocks import BINARY_CONTENT_TYPE
from drivers.protocol import SCENE_CONTENT_TYPE, Close
from service import limits
from service.app import create_app, route_paths

LONG = "x" * 300  # past every length FastAPI would refuse 422 (an entry id: 128, ?session=: 200)
UNKNOWN = "test-a.no-such-session"
#: paths anyone may read: liveness, readiness, the console page and its two scripts, the API's description
OPEN = {"/health", "/ready", "/console", "/console/render-worklet.js", "/console/model-codec.js"}
OPEN |= {"/openapi.json", "/docs", "/redoc"}
OPEN_PREFIXES = ("/docs/", "/{path:path}")

#: (method, path, body, content type) for every route that opens or reads state, with what FastAPI or the route
#: would refuse were the credential not judged first: an overlong id, a missing or wrong body, a bad query
HTTP_CASES = [
    ("POST", "/sessions", b"{syntax", "application/json"),
    ("GET", f"/sessions/{LONG}", None, None),
    ("DELETE", f"/sessions/{UNKNOWN}", None, None),
    ("POST", f"/sessions/{UNKNOWN}/blocks", b"not a block", "text/plain"),
    ("POST", f"/sessions/{LONG}/frames", b"not a frame", "image/png"),
    ("POST", f"/sessions/{UNKNOWN}/scene", b"short", SCENE_CONTENT_TYPE),
    ("GET", "/library?session=" + LONG, None, None),
    ("GET", f"/library/{LONG}/model", None, None),
    ("GET", f"/library/{LONG}/model?session={LONG}", None, None),
    ("HEAD", f"/library/{LONG}/model", None, None),
    ("GET", "/metrics?format=" + LONG, None, None),
    ("GET", f"/robots/{LONG}/session", None, None),
]
SOCKET_PATHS = {"/sessions/{session_id}/ingest", "/sessions/{session_id}/events", "/robots/{robot}/events"}


def test_every_stateful_route_has_a_case_here(base_settings):
    """A route added without a case fails here: every path the app serves is open or named in HTTP_CASES."""
    covered = {path.split("?")[0] for _, path, _, _ in HTTP_CASES}
    templates = {
        "/sessions": "/sessions",
        "/sessions/{session_id}": f"/sessions/{LONG}",
        "/sessions/{session_id}/blocks": f"/sessions/{UNKNOWN}/blocks",
        "/sessions/{session_id}/frames": f"/sessions/{LONG}/frames",
        "/sessions/{session_id}/scene": f"/sessions/{UNKNOWN}/scene",
        "/library": "/library",
        "/library/{entry_id}/model": f"/library/{LONG}/model",
        "/metrics": "/metrics",
        "/robots/{robot}/session": f"/robots/{LONG}/session",
    }
    for path in route_paths(create_app(base_settings)):
        if path in OPEN or path.startswith(OPEN_PREFIXES) or path in SOCKET_PATHS:
            continue
        assert path in templates and templates[path] in covered, f"{path}: no credential-first case"


@pytest.mark.parametrize(("method", "path", "body", "kind"), HTTP_CASES, ids=lambda v: str(v)[:40])
def test_without_a_credential_every_route_answers_401_first(client, method, path, body, kind):
    headers = {"Content-Type": kind} if kind else {}
    r = client.request(method, path, content=body, headers=headers)
    assert r.status_code == 401, (method, path, r.status_code, r.text)
    assert r.headers["www-authenticate"] == "Bearer"
    # a wrong credential is refused as one too, before the overlong id or the bad body is looked at
    r = client.request(method, path, content=body, headers={**headers, "Authorization": "Bearer not-a-token"})
    assert r.status_code in (401, 404), (method, path, r.status_code, r.text)


def test_with_a_credential_the_rest_is_judged(kit, client):
    """The same requests with a fleet key: now the id's length and the entry are judged (422, 404)."""
    assert client.get(f"/library/{LONG}/model", headers=kit.FLEET).status_code == 422
    assert client.get("/library/no-such-entry/model", headers=kit.FLEET).status_code == 404
    assert client.get(f"/robots/{LONG}/session", headers=kit.FLEET).status_code == 422  # a robot id is ≤ 64
    assert client.get("/robots/no-such-robot/session", headers=kit.FLEET).status_code == 404
    r = client.get(f"/library?session={LONG}", headers={"Authorization": "Bearer a-token"})
    assert r.status_code == 404 and r.json()["detail"].startswith("no session 'xxx")
    session = kit.create_session(client)
    robot = {"Authorization": f"Bearer {session['robot_token']}"}
    r = client.post(f"/sessions/{session['session_id']}/blocks", content=b"x", headers=robot)
    assert r.status_code == 415


def test_sockets_without_a_credential_are_refused_as_unauthorised(server):
    """No ?token=: the events handshake is answered 401, the ingest socket closed 1008, whatever the session id."""
    for sid in (UNKNOWN, LONG):
        with pytest.raises(InvalidStatus) as refused:
            connect(f"{server.ws_url}/sessions/{sid}/events", open_timeout=10).close()
        assert refused.value.response.status_code == 401
        with connect(f"{server.ws_url}/sessions/{sid}/ingest", open_timeout=10) as ws:
            with pytest.raises(ConnectionClosed) as closed:
                ws.recv(timeout=10)
        assert closed.value.rcvd is not None and closed.value.rcvd.code == int(Close.POLICY)
    for robot in ("robot-7", LONG):  # a robot's feed: the fleet key first, then the robot id
        with pytest.raises(InvalidStatus) as refused:
            connect(f"{server.ws_url}/robots/{robot}/events", open_timeout=10).close()
        assert refused.value.response.status_code == 401


def test_a_10_mb_upload_reads_its_413(kit, client):
    """The probe: a 10 MB upload with Content-Length was reset mid-upload, so the client never read its 413. The
    service reads and drops the refused body, answers, then closes: the client reads the answer, declared or
    streamed, with the robot token (413) and without one (401)."""
    session = kit.create_session(client)
    url = f"/sessions/{session['session_id']}/blocks"
    robot = {"Authorization": f"Bearer {session['robot_token']}", "Content-Type": BINARY_CONTENT_TYPE}
    big = bytes(10 * 1000 * 1000)
    for _ in range(3):  # not a lucky race: every time
        r = client.post(url, content=big, headers=robot)
        assert r.status_code == 413 and "at most 8388608 bytes" in r.json()["detail"]
        assert r.headers["connection"] == "close"
    streamed = client.post(url, content=(big[i : i + 65536] for i in range(0, len(big), 65536)), headers=robot)
    assert streamed.status_code == 413 and "at most 8388608 bytes" in streamed.json()["detail"]
    anonymous = client.post(url, content=big, headers={"Content-Type": BINARY_CONTENT_TYPE})
    assert anonymous.status_code == 401
    frame = client.post(
        f"/sessions/{session['session_id']}/frames", content=big, headers={**robot, "Content-Type": "image/png"}
    )
    assert frame.status_code == 413
    # the session and the service go on
    operator = {"Authorization": f"Bearer {session['operator_token']}"}
    assert client.get(f"/sessions/{session['session_id']}", headers=operator).status_code == 200


def test_a_raw_socket_upload_reads_the_413_before_the_close(kit, client, server):
    """The same over a bare socket, the client writing all 10 MB before reading: the answer is there, not a reset."""
    session = kit.create_session(client)
    body = bytes(10 * 1000 * 1000)
    head = (
        f"POST /sessions/{session['session_id']}/blocks HTTP/1.1\r\nHost: test\r\n"
        f"Authorization: Bearer {session['robot_token']}\r\nContent-Type: {BINARY_CONTENT_TYPE}\r\n"
        f"Content-Length: {len(body)}\r\n\r\n"
    ).encode()
    host, port = server.url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=20) as sock:
        sock.sendall(head + body)
        answer = b""
        while chunk := sock.recv(65536):
            answer += chunk
    assert answer.startswith(b"HTTP/1.1 413"), answer[:200]
    assert b"at most 8388608 bytes" in answer


def test_a_trickled_refused_body_is_answered_after_the_drain_time(kit, base_settings, monkeypatch):
    """The drain is bounded: a client that declares a terabyte and trickles it gets its answer after DRAIN_S (here
    shortened), not when it has sent it all, and the service goes on."""
    monkeypatch.setattr(limits, "DRAIN_S", 0.5)
    with kit.running(base_settings.model_copy(update={"instance_id": "drain"})) as srv:
        host, port = srv.url.removeprefix("http://").split(":")
        with socket.create_connection((host, int(port)), timeout=20) as sock:
            sock.sendall(
                b"POST /sessions/drain.x/blocks HTTP/1.1\r\nHost: t\r\nAuthorization: Bearer t\r\n"
                b"Content-Length: 1000000000000\r\n\r\n" + bytes(65536)
            )
            started = time.monotonic()
            answer = sock.recv(65536)
            waited = time.monotonic() - started
        assert answer.startswith(b"HTTP/1.1 404"), answer[:200]  # a token was sent: the unknown session is said
        assert b"connection: close" in answer.lower()
        assert waited >= 0.4
        with httpx.Client(base_url=srv.url, timeout=10) as c:
            assert c.get("/health").status_code == 200
