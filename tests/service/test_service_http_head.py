"""HEAD on a real uvicorn: every GET route answers it with the GET's status and headers and no body, behind the
same credentials; a route without GET still says which methods it has. uvicorn drops a HEAD's body itself and httpx
reads none, so the middleware's own dropping is checked as plain ASGI."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

import httpx
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import JSONResponse, Response, StreamingResponse
from starlette.routing import Route
from starlette.types import ASGIApp, Message

from service.http_head import HeadAsGet
from tests.service.conftest import FLEET, SCRAPER, create_session


def _same_head(client: httpx.Client, path: str, headers: dict[str, str] | None = None) -> httpx.Response:
    """HEAD `path` beside its GET: the same status and content type, no body, and a Content-Length that is the
    GET's (a live document — a session's status, the metrics — may change by a few bytes between the two)."""
    got = client.get(path, headers=headers)
    head = client.head(path, headers=headers)
    assert head.status_code == got.status_code, path
    assert head.content == b"", path
    assert head.headers.get("content-type") == got.headers.get("content-type"), path
    if "content-length" in got.headers:
        assert abs(int(head.headers["content-length"]) - len(got.content)) <= 16, path
    return head


def test_every_get_route_answers_head_without_a_body(client):
    session = create_session(client)
    operator = {"Authorization": f"Bearer {session['operator_token']}"}
    entry = client.get("/library", headers=FLEET).json()["entries"][0]["id"]
    for path, headers in [
        ("/library", FLEET),
        (f"/library/{entry}/model", FLEET),
        ("/metrics", SCRAPER),
        (f"/sessions/{session['session_id']}", operator),
        ("/console", None),
        ("/console/render-worklet.js", None),
    ]:
        assert _same_head(client, path, headers).status_code == 200, path


def test_head_needs_the_credential_its_get_needs(client):
    session = create_session(client)
    path = f"/sessions/{session['session_id']}"
    for headers in (None, {"Authorization": f"Bearer {session['robot_token']}"}):  # none, the wrong role
        head = _same_head(client, path, headers)
        assert head.status_code in (401, 403), headers
    assert _same_head(client, path, {"Authorization": f"Bearer {session['operator_token']}"}).status_code == 200


def test_head_on_a_route_without_get_is_405_naming_its_methods(client):
    head = client.head("/sessions", headers=FLEET)
    assert head.status_code == 405 and head.content == b""
    assert "POST" in head.headers["allow"]


async def _document(request: Request) -> Response:
    return JSONResponse({"entries": list(range(20))})


async def _chunks() -> AsyncIterator[bytes]:
    yield b"speed,force\n"
    yield b"120,1.5\n"


async def _stream(request: Request) -> Response:
    return StreamingResponse(_chunks(), media_type="text/csv")


def _exchange(app: ASGIApp, method: str, path: str) -> list[Message]:
    """Every message `app` sends for one request, called directly (no server, no client between)."""
    scope = {
        "type": "http",
        "asgi": {"version": "3.0"},
        "http_version": "1.1",
        "method": method,
        "scheme": "http",
        "path": path,
        "raw_path": path.encode(),
        "root_path": "",
        "query_string": b"",
        "headers": [(b"host", b"test")],
        "server": ("test", 80),
        "client": ("127.0.0.1", 50000),
    }
    sent: list[Message] = []
    requests = [{"type": "http.request", "body": b"", "more_body": False}]

    async def receive() -> Message:
        if requests:
            return requests.pop()
        await asyncio.Event().wait()  # the client stays connected: a streamed response listens for it leaving
        raise AssertionError("unreachable")

    async def send(message: Message) -> None:
        sent.append(message)

    asyncio.run(app(scope, receive, send))
    return sent


def test_the_middleware_itself_sends_head_no_body_and_the_gets_headers():
    app = HeadAsGet(Starlette(routes=[Route("/document", _document), Route("/stream", _stream)]))
    for path in ("/document", "/stream"):  # one body message with a Content-Length; several, chunked
        got, head = _exchange(app, "GET", path), _exchange(app, "HEAD", path)
        assert [m["type"] for m in head] == [m["type"] for m in got], path
        assert head[0] == got[0], path  # http.response.start: status and headers, Content-Length and -Type too
        get_bodies = [m for m in got if m["type"] == "http.response.body"]
        head_bodies = [m for m in head if m["type"] == "http.response.body"]
        assert b"".join(m["body"] for m in get_bodies), path  # there was a body to drop
        assert [m["body"] for m in head_bodies] == [b""] * len(get_bodies), path
        assert [m.get("more_body", False) for m in head_bodies] == [m.get("more_body", False) for m in get_bodies]
    headers = dict(_exchange(app, "HEAD", "/document")[0]["headers"])
    assert headers[b"content-type"] == b"application/json" and int(headers[b"content-length"]) > 0
